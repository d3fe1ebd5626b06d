//! Process isolation for native plugins (`isolation: process`, the default): the plugin runs
//! in a child process, `r2d2-plugin-host`, that this module starts and supervises. Images
//! cross over two pipes of the protocol's own (`r2d2_plugin::host::wire`), on descriptors 3
//! and 4 of the host: its standard input is `/dev/null` and its standard output this
//! process's standard error, so what the plugin does with those cannot reach the protocol. A
//! plugin that crashes (segfault, abort), ends its process (exit) or runs past the timeout,
//! also while it is torn down ([`HostedInstance::finish`]), becomes an error naming what
//! happened; the caller adds the library, and the runner the stage and the job.
//!
//! The host executable is found, in order: `$R2D2_PLUGIN_HOST`; beside the running
//! executable (the `r2d2` CLI, next to which `cargo build` puts it) or in its parent
//! directory (test and example binaries); then on `PATH`. An embedding program whose
//! executable is not `r2d2` (Python, say) sets `R2D2_PLUGIN_HOST` or puts the host on `PATH`.

pub use super::error::HostError;
use r2d2_plugin::host::wire;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use crate::pipeline::cancel::{HookGuard, RunStop};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Name of the host executable.
pub const HOST: &str = "r2d2-plugin-host";
/// Environment variable naming the host executable.
pub const HOST_ENV: &str = "R2D2_PLUGIN_HOST";

/// Longest wait for a started host's greeting. A host sends it before loading the plugin, so
/// only an executable that is not a plugin host (or a stopped machine) comes near it.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// The host's descriptors for the protocol (engine -> host, host -> engine).
#[cfg(unix)]
const PROTOCOL_FDS: [i32; 2] = [3, 4];

/// The protocol's two ends on this side.
type ToHost = Box<dyn Write + Send>;
type FromHost = Box<dyn Read + Send>;

/// Starts `host` for `library` with the protocol on pipes of its own ([`PROTOCOL_FDS`]),
/// standard input `/dev/null`, standard output and error this process's standard error, in a
/// process group of its own (whatever it starts is killed with it).
#[cfg(unix)]
fn spawn_host(host: &Path, library: &Path) -> std::io::Result<(Child, ToHost, FromHost)> {
    use std::os::fd::{AsFd, AsRawFd, FromRawFd, OwnedFd};
    use std::os::unix::process::CommandExt;
    // std's pipes are close-on-exec: no other child (another stage's host) inherits them.
    let (host_input, to_host) = std::io::pipe()?;
    let (from_host, host_output) = std::io::pipe()?;
    // The host's ends copied above its descriptor numbers, so that placing one in the child
    // cannot close the other.
    let above = |fd: &dyn AsRawFd| -> std::io::Result<OwnedFd> {
        // SAFETY: fcntl(2) duplicating an open descriptor; the copy is owned by the OwnedFd only.
        match unsafe { libc::fcntl(fd.as_raw_fd(), libc::F_DUPFD_CLOEXEC, 10) } {
            -1 => Err(std::io::Error::last_os_error()),
            copy => Ok(unsafe { OwnedFd::from_raw_fd(copy) }),
        }
    };
    let ends = [above(&host_input)?, above(&host_output)?];
    drop((host_input, host_output));
    let raw = [ends[0].as_raw_fd(), ends[1].as_raw_fd()];
    let mut command = Command::new(host);
    command
        .arg(library)
        .args(PROTOCOL_FDS.map(|fd| fd.to_string()))
        .stdin(Stdio::null())
        .stdout(Stdio::from(std::io::stderr().as_fd().try_clone_to_owned()?))
        .stderr(Stdio::inherit())
        .process_group(0);
    // SAFETY: between fork and exec only dup2(2), which is async-signal-safe; `raw` stays open
    // in this process until spawn returns (`ends` outlives it), so in the child too, and the
    // copies dup2 makes are not close-on-exec.
    unsafe {
        command.pre_exec(move || {
            for (from, to) in raw.into_iter().zip(PROTOCOL_FDS) {
                if libc::dup2(from, to) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
            }
            Ok(())
        })
    };
    let child = command.spawn()?;
    // The host's ends now live in the host alone: its end closes them.
    drop(ends);
    Ok((child, Box::new(to_host), Box::new(from_host)))
}

#[cfg(not(unix))]
fn spawn_host(host: &Path, library: &Path) -> std::io::Result<(Child, ToHost, FromHost)> {
    let mut child = Command::new(host).arg(library).stdin(Stdio::piped()).stdout(Stdio::piped()).stderr(Stdio::inherit()).spawn()?;
    let (input, output) = (child.stdin.take().expect("piped"), child.stdout.take().expect("piped"));
    Ok((child, Box::new(input), Box::new(output)))
}

/// Kills host `pid` and its process group (whatever it started) if `alive` still says it has
/// not been reaped.
#[cfg(unix)]
fn kill(pid: u32, alive: &Mutex<bool>) {
    let alive = alive.lock().unwrap_or_else(|e| e.into_inner());
    if *alive {
        kill_group(pid);
    }
}

/// SIGKILL to the host's process group (its id is the host's pid: it was started as the
/// group's leader). Only while the host is not reaped: until then no other group has that id.
#[cfg(unix)]
fn kill_group(pid: u32) {
    // SAFETY: kill(2) takes plain integers; the callers hold the host unreaped (see above).
    unsafe { libc::kill(-(pid as libc::pid_t), libc::SIGKILL) };
}

#[cfg(not(unix))]
fn kill(_pid: u32, _alive: &Mutex<bool>) {}

#[cfg(not(unix))]
fn kill_group(_pid: u32) {}

/// Whether child `pid` has ended, without reaping it (its pid, and so its process group's id,
/// stays reserved until it is waited for).
#[cfg(unix)]
fn has_ended(child: &mut Child) -> bool {
    // SAFETY: waitid(2) with WNOWAIT on our own child writes only into `info`.
    unsafe {
        let mut info: libc::siginfo_t = std::mem::zeroed();
        let flags = libc::WEXITED | libc::WNOHANG | libc::WNOWAIT;
        libc::waitid(libc::P_PID, child.id() as libc::id_t, &mut info, flags) == 0 && info.si_pid() != 0
    }
}

#[cfg(not(unix))]
fn has_ended(child: &mut Child) -> bool {
    matches!(child.try_wait(), Ok(Some(_)))
}

/// The host executable (see the module documentation for the search order).
pub fn find_host() -> Result<PathBuf, String> {
    if let Some(path) = std::env::var_os(HOST_ENV) {
        let path = PathBuf::from(path);
        return match std::fs::metadata(&path) {
            Ok(m) if m.is_file() => Ok(path),
            Ok(m) => Err(format!("{HOST_ENV}={} is not a file: it is {}", path.display(), crate::error::file_kind(&m))),
            Err(e) => Err(format!("{HOST_ENV}={} is not a file ({e})", path.display())),
        };
    }
    let name = format!("{HOST}{}", std::env::consts::EXE_SUFFIX);
    let mut places = Vec::new();
    if let Ok(exe) = std::env::current_exe() {
        if let Some(dir) = exe.parent() {
            places.push(dir.to_path_buf());
            places.extend(dir.parent().map(Path::to_path_buf));
        }
    }
    places.extend(std::env::var_os("PATH").map(|p| std::env::split_paths(&p).collect::<Vec<_>>()).unwrap_or_default());
    places.iter().map(|dir| dir.join(&name)).find(|p| p.is_file()).ok_or_else(|| {
        format!(
            "the plugin host `{name}` was not found beside this executable nor on PATH: build it (`cargo build --release` puts it beside r2d2), point {HOST_ENV} at it, or set `isolation: none` to load the plugin into this process"
        )
    })
}

/// The host as messages name it: `R2D2_PLUGIN_HOST=PATH` when the variable chose it.
fn host_name(host: &Path) -> String {
    match std::env::var_os(HOST_ENV) {
        Some(_) => format!("{HOST_ENV}={}", host.display()),
        None => format!("the plugin host {}", host.display()),
    }
}

enum Reply {
    /// The host's greeting: it runs and speaks the protocol.
    Hello,
    Ok,
    Error(String),
    Increment(Vec<f64>),
    /// The host gave up itself, with its reason (the engine sent what it does not take).
    Fatal(String),
    /// The host sent what the protocol does not allow (a frame over its limit): what.
    Broken(String),
    /// The host's output ended (or broke): the process is gone or going.
    Gone,
}

/// The reply after a text frame's tag: the text, [`Reply::Broken`] naming a frame over the
/// limit, or [`Reply::Gone`] when the output ended.
fn text_reply(output: &mut impl Read, reply: fn(String) -> Reply) -> Reply {
    match wire::read_text(output) {
        Ok(text) => reply(text),
        Err(e) if e.kind() == std::io::ErrorKind::InvalidData => Reply::Broken(e.to_string()),
        Err(_) => Reply::Gone,
    }
}

/// A plugin instance living in a supervised child process.
pub struct HostedInstance {
    child: Child,
    input: Option<BufWriter<ToHost>>,
    replies: crossbeam_channel::Receiver<Reply>,
    timeout: Duration,
    size: usize,
    /// The dirty image and PSF the host holds (sent again only when a new job brings others).
    sent_dirty: Vec<f64>,
    sent_psf: Vec<f64>,
    /// Set once the host has failed: later calls report that instead of talking to it.
    dead: Option<String>,
    /// Whether the child is not yet reaped: its pid may be signalled only while this holds.
    alive: Arc<Mutex<bool>>,
    /// The run this host works for (its stop kills the host: a hung plugin cannot keep the
    /// run waiting), and the registration of that kill.
    run: Option<RunStop>,
    _kill_on_stop: Option<HookGuard>,
}

impl HostedInstance {
    /// Start the host for `library` and create the plugin there; `timeout` bounds every call.
    pub fn start(library: &Path, config_json: &str, size: usize, iterations: usize, timeout: Duration) -> Result<HostedInstance, HostError> {
        let host = find_host().map_err(HostError::NotFound)?;
        let (child, input, output) = spawn_host(&host, library).map_err(|source| HostError::Spawn { host: host_name(&host), source })?;
        let alive = Arc::new(Mutex::new(true));
        let run = crate::pipeline::cancel::current();
        let kill_on_stop = run.as_ref().map(|run| {
            let (pid, alive) = (child.id(), alive.clone());
            run.on_stop(move || kill(pid, &alive))
        });
        let input = BufWriter::with_capacity(1 << 16, input);
        let (send, replies) = crossbeam_channel::bounded(1);
        let pixels = size * size;
        std::thread::Builder::new()
            .name("plugin-host-reader".into())
            .spawn(move || {
                let mut output = BufReader::with_capacity(1 << 16, output);
                loop {
                    let reply = match wire::read_tag(&mut output) {
                        Ok(Some(wire::HELLO)) => Reply::Hello,
                        Ok(Some(wire::OK)) => Reply::Ok,
                        Ok(Some(wire::ERROR)) => text_reply(&mut output, Reply::Error),
                        Ok(Some(wire::FATAL)) => text_reply(&mut output, Reply::Fatal),
                        Ok(Some(wire::INCREMENT)) => {
                            let mut increment = vec![0.0; pixels];
                            match wire::read_f64s(&mut output, &mut increment) {
                                Ok(()) => Reply::Increment(increment),
                                Err(_) => Reply::Gone,
                            }
                        }
                        Ok(Some(tag)) => Reply::Broken(format!("a message of unknown tag {tag}")),
                        Ok(None) | Err(_) => Reply::Gone,
                    };
                    let gone = matches!(reply, Reply::Gone | Reply::Broken(_) | Reply::Fatal(_));
                    if send.send(reply).is_err() || gone {
                        return;
                    }
                }
            })
            .map_err(HostError::Thread)?;
        let mut hosted = HostedInstance {
            child,
            input: Some(input),
            replies,
            timeout,
            size,
            sent_dirty: Vec::new(),
            sent_psf: Vec::new(),
            dead: None,
            alive,
            run,
            _kill_on_stop: kill_on_stop,
        };
        hosted.handshake().map_err(|how| HostError::Handshake { host: host_name(&host), how })?;
        let sent = hosted.send(|w| {
            w.write_all(&[wire::CREATE])?;
            wire::write_u64(w, size as u64)?;
            wire::write_u64(w, iterations as u64)?;
            wire::write_text(w, config_json)
        });
        let reply = match sent {
            Ok(()) => hosted.reply("creating the plugin"),
            Err(()) => hosted.gone("creating the plugin"),
        };
        match reply.map_err(HostError::Failed)? {
            Reply::Ok => Ok(hosted),
            Reply::Error(message) => Err(HostError::Failed(message)),
            _ => Err(HostError::Failed(hosted.fail("creating the plugin", "an unexpected reply from the plugin host".into()))),
        }
    }

    /// The host's greeting, within [`HANDSHAKE_TIMEOUT`]; else how the executable failed (it
    /// is then stopped). Nothing of the plugin has run yet: a failure here is the host's.
    fn handshake(&mut self) -> Result<(), String> {
        let began = Instant::now();
        let failed = loop {
            match self.replies.recv_timeout(Duration::from_millis(50)) {
                Ok(Reply::Hello) => return Ok(()),
                Ok(Reply::Gone) | Err(crossbeam_channel::RecvTimeoutError::Disconnected) => {
                    break match self.reap(Duration::from_secs(5)) {
                        _ if self.run.as_ref().is_some_and(RunStop::is_stopped) => "interrupted: it was stopped".to_string(),
                        Some(status) => format!("it ended ({status}) before its handshake"),
                        None => "it closed its output before its handshake".to_string(),
                    };
                }
                Ok(_) => break "it answered the handshake with another message".to_string(),
                Err(crossbeam_channel::RecvTimeoutError::Timeout) => {
                    // Processes it started may hold its output open after it ended.
                    if let Some(status) = self.reap(Duration::ZERO) {
                        break format!("it ended ({status}) before its handshake");
                    }
                    if began.elapsed() >= HANDSHAKE_TIMEOUT {
                        break format!("it sent no handshake within {} s", HANDSHAKE_TIMEOUT.as_secs());
                    }
                }
            }
        };
        self.stop();
        self.dead = Some(failed.clone());
        Err(failed)
    }

    /// Write one message and flush; `Err` when the host's input is closed (the host is gone).
    fn send(&mut self, write: impl FnOnce(&mut BufWriter<ToHost>) -> std::io::Result<()>) -> Result<(), ()> {
        let input = self.input.as_mut().ok_or(())?;
        write(input).and_then(|()| input.flush()).map_err(|_| ())
    }

    /// The next reply, within the timeout; the host's end (or a timeout) is an error.
    fn reply(&mut self, doing: &str) -> Result<Reply, String> {
        let began = Instant::now();
        match self.replies.recv_timeout(self.timeout) {
            Ok(Reply::Gone) | Err(crossbeam_channel::RecvTimeoutError::Disconnected) => self.gone(doing),
            // Not the plugin's doing: the host or the engine broke the protocol.
            Ok(Reply::Fatal(reason)) => {
                let status = self.reap(Duration::from_secs(5)).map_or_else(|| "still running, stopped".to_string(), |s| s.to_string());
                self.stop();
                Err(self.fail_host(doing, format!("it gave up ({status}): {reason}")))
            }
            Ok(Reply::Broken(what)) => {
                self.stop();
                Err(self.fail_host(doing, format!("it sent {what}; it was stopped")))
            }
            Ok(reply) => Ok(reply),
            Err(crossbeam_channel::RecvTimeoutError::Timeout) => {
                let waited = began.elapsed().as_secs_f64();
                self.stop();
                Err(self.fail(doing, format!("the plugin did not answer within {waited:.1} s (timeout: {} s); its host process was stopped", self.timeout.as_secs_f64())))
            }
        }
    }

    /// The host ended: say how.
    fn gone<T>(&mut self, doing: &str) -> Result<T, String> {
        let status = self.reap(Duration::from_secs(5));
        let how = match status {
            _ if self.run.as_ref().is_some_and(RunStop::is_stopped) => "interrupted: its host process was stopped".to_string(),
            Some(status) => describe_end(status),
            None => {
                self.stop();
                "its host process closed its output and was stopped".to_string()
            }
        };
        Err(self.fail(doing, how))
    }

    fn fail(&mut self, doing: &str, how: String) -> String {
        let message = format!("the plugin failed while {doing}: {how}");
        self.dead = Some(message.clone());
        message
    }

    /// A failure of the host's, not the plugin's: `how` says what happened.
    fn fail_host(&mut self, doing: &str, how: String) -> String {
        let message = format!("the plugin host failed while {doing}: {how}");
        self.dead = Some(message.clone());
        message
    }

    /// Wait up to `patience` for the host to end; its status, or None if it still runs.
    fn reap(&mut self, patience: Duration) -> Option<ExitStatus> {
        let began = Instant::now();
        loop {
            // Under `alive`'s lock: once reaped, the pid must not be signalled.
            let mut alive = self.alive.lock().unwrap_or_else(|e| e.into_inner());
            if *alive && has_ended(&mut self.child) {
                // What the host started dies with it, before its group id is given up.
                kill_group(self.child.id());
                let status = self.child.wait().ok();
                *alive = false;
                return status;
            }
            if !*alive || began.elapsed() >= patience {
                return None;
            }
            drop(alive);
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    /// Kill the host and reap it.
    fn stop(&mut self) {
        self.input = None;
        let mut alive = self.alive.lock().unwrap_or_else(|e| e.into_inner());
        if *alive {
            kill_group(self.child.id());
            let _ = self.child.kill();
            let _ = self.child.wait();
            *alive = false;
        }
    }

    /// One step in the host: the increment (N x N), unchecked.
    pub fn step(&mut self, iteration: usize, residual: &[f64], model: &[f64], dirty: &[f64], psf_2n: &[f64]) -> Result<Vec<f64>, String> {
        if let Some(message) = &self.dead {
            return Err(format!("the plugin host failed earlier ({message})"));
        }
        let pixels = self.size * self.size;
        if [residual.len(), model.len(), dirty.len()].iter().any(|&l| l != pixels) || psf_2n.len() != 4 * pixels {
            return Err(format!("inconsistent image sizes for N = {}", self.size));
        }
        let new_dirty = self.sent_dirty != dirty;
        let new_psf = self.sent_psf != psf_2n;
        let flags = if new_dirty { wire::WITH_DIRTY } else { 0 } | if new_psf { wire::WITH_PSF } else { 0 };
        let sent = self.send(|w| {
            w.write_all(&[wire::STEP])?;
            wire::write_u64(w, iteration as u64)?;
            wire::write_u64(w, flags)?;
            wire::write_f64s(w, residual)?;
            wire::write_f64s(w, model)?;
            if new_dirty {
                wire::write_f64s(w, dirty)?;
            }
            if new_psf {
                wire::write_f64s(w, psf_2n)?;
            }
            Ok(())
        });
        let doing = format!("running step {iteration}");
        if sent.is_err() {
            return self.gone(&doing);
        }
        if new_dirty {
            self.sent_dirty = dirty.to_vec();
        }
        if new_psf {
            self.sent_psf = psf_2n.to_vec();
        }
        match self.reply(&doing)? {
            Reply::Increment(increment) => Ok(increment),
            Reply::Error(message) => Err(message),
            _ => Err(self.fail(&doing, "an unexpected reply from the plugin host".into())),
        }
    }
}

impl HostedInstance {
    /// Tears the plugin down in the host (its destroy, the library's unloading) and waits for
    /// the host's clean end (exit status 0): a crash there, also in what runs as the host
    /// exits, is an error, which the run sees before it commits what the plugin computed.
    pub fn finish(&mut self) -> Result<(), String> {
        if let Some(message) = &self.dead {
            return Err(format!("the plugin host failed earlier ({message})"));
        }
        let doing = "being torn down (its destroy, the library's unloading)";
        if self.send(|w| w.write_all(&[wire::DESTROY])).is_err() {
            return self.gone(doing);
        }
        match self.reply(doing)? {
            Reply::Ok => {}
            _ => return Err(self.fail(doing, "an unexpected reply from the plugin host".into())),
        }
        self.input = None;
        let doing = "exiting after its teardown";
        match self.reap(self.timeout) {
            _ if self.run.as_ref().is_some_and(RunStop::is_stopped) => Err(self.fail(doing, "interrupted: its host process was stopped".into())),
            Some(status) if status.success() => Ok(()),
            Some(status) => Err(self.fail(doing, describe_end(status))),
            None => {
                self.stop();
                Err(self.fail(doing, format!("it did not end within {:.1} s (timeout); it was stopped", self.timeout.as_secs_f64())))
            }
        }
    }
}

impl Drop for HostedInstance {
    /// Closing the host's input ends it (the plugin's destroy runs there); one that does not
    /// end promptly is killed.
    fn drop(&mut self) {
        self.input = None;
        if self.reap(Duration::from_secs(2)).is_none() {
            self.stop();
        }
    }
}

/// How a host process ended, in words.
fn describe_end(status: ExitStatus) -> String {
    #[cfg(unix)]
    {
        use std::os::unix::process::ExitStatusExt;
        if let Some(signal) = status.signal() {
            let name = match signal {
                libc::SIGSEGV => " (SIGSEGV, a segmentation fault)",
                libc::SIGABRT => " (SIGABRT, abort)",
                libc::SIGBUS => " (SIGBUS)",
                libc::SIGFPE => " (SIGFPE)",
                libc::SIGILL => " (SIGILL)",
                libc::SIGKILL => " (SIGKILL)",
                libc::SIGINT => " (SIGINT)",
                libc::SIGTERM => " (SIGTERM)",
                _ => "",
            };
            return format!("its host process crashed: killed by signal {signal}{name}");
        }
    }
    match status.code() {
        Some(code) => format!("the plugin ended its host process with exit status {code} (a plugin must return from every call, never exit)"),
        None => format!("its host process ended ({status})"),
    }
}
