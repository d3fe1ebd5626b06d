//! `r2d2-plugin-host LIBRARY IN_FD OUT_FD`: runs one native plugin in a process of its own,
//! so that a plugin that crashes, exits or hangs takes only this process down; the engine
//! supervises it (`src/steps/native_host.rs`) and turns its end into an error naming the
//! library.
//!
//! It speaks `r2d2_plugin::host::wire` over the two pipe descriptors it is given, not over
//! its standard streams: the engine makes standard input `/dev/null` and standard output a
//! copy of standard error, so a plugin that reads standard input, prints, or closes
//! descriptors 0 and 1 cannot touch the protocol. Without descriptors (systems other than
//! Unix) it speaks over standard input and output. Not meant to be run by hand.

use r2d2_plugin::host::{wire, Instance};
use std::ffi::OsString;
use std::io::{self, BufReader, BufWriter, Read, Write};
use std::path::PathBuf;

fn main() {
    let args: Vec<OsString> = std::env::args_os().skip(1).collect();
    let usage = "usage: r2d2-plugin-host LIBRARY IN_FD OUT_FD (started by r2d2 for `kind: native` steps; not meant to be run by hand)";
    let Some((library, descriptors)) = args.split_first() else {
        eprintln!("{usage}");
        std::process::exit(2);
    };
    let (input, output) = match protocol_channel(descriptors) {
        Ok(channel) => channel,
        Err(e) => {
            eprintln!("r2d2-plugin-host: {e}\n{usage}");
            std::process::exit(2);
        }
    };
    die_with_the_engine();
    let mut out = BufWriter::new(output);
    if let Err(e) = serve(PathBuf::from(library), &mut BufReader::new(input), &mut out) {
        // The engine sent what the protocol does not allow, or is gone: say so where it can
        // still be read, so that the engine does not take this end for the plugin's.
        eprintln!("r2d2-plugin-host: {e}");
        let _ = out.write_all(&[wire::FATAL]).and_then(|()| wire::write_text(&mut out, &e.to_string())).and_then(|()| out.flush());
        std::process::exit(wire::HOST_FAILED);
    }
}

/// The protocol's input and output: the pipe descriptors named by the engine, marked
/// close-on-exec (a program the plugin starts must not hold them open).
#[cfg(unix)]
fn protocol_channel(descriptors: &[OsString]) -> Result<(std::fs::File, std::fs::File), String> {
    use std::os::fd::FromRawFd;
    let [input, output] = descriptors else {
        return Err(format!("expected the protocol's two descriptors after the library, got {} argument(s)", descriptors.len()));
    };
    let mut fds = [0; 2];
    for (fd, given) in fds.iter_mut().zip([input, output]) {
        *fd = given
            .to_str()
            .and_then(|s| s.parse::<libc::c_int>().ok())
            .filter(|&fd| fd > 2)
            .ok_or_else(|| format!("{} is not a descriptor number above 2", given.to_string_lossy()))?;
        // SAFETY: fcntl(2) on a plain integer; an unopened descriptor only fails.
        if unsafe { libc::fcntl(*fd, libc::F_SETFD, libc::FD_CLOEXEC) } != 0 {
            return Err(format!("descriptor {fd} is not open ({})", io::Error::last_os_error()));
        }
    }
    if fds[0] == fds[1] {
        return Err(format!("the same descriptor {} for input and output", fds[0]));
    }
    // SAFETY: two distinct open descriptors the engine handed to this process for the
    // protocol alone; each File below is their only owner.
    Ok(unsafe { (std::fs::File::from_raw_fd(fds[0]), std::fs::File::from_raw_fd(fds[1])) })
}

#[cfg(not(unix))]
fn protocol_channel(descriptors: &[OsString]) -> Result<(io::Stdin, io::Stdout), String> {
    match descriptors {
        [] => Ok((io::stdin(), io::stdout())),
        _ => Err("protocol descriptors are a Unix feature".into()),
    }
}

/// Asks the kernel to kill this process when the engine dies, so a hung plugin never outlives
/// it.
#[cfg(target_os = "linux")]
fn die_with_the_engine() {
    // SAFETY: prctl(2) with integer arguments, on this process only.
    unsafe { libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) };
}

#[cfg(not(target_os = "linux"))]
fn die_with_the_engine() {}

/// A plugin's failure, cut to what the protocol passes on (`wire::bounded_message`).
fn error(out: &mut impl Write, message: &str) -> io::Result<()> {
    out.write_all(&[wire::ERROR])?;
    wire::write_text(out, &wire::bounded_message(message))?;
    out.flush()
}

fn serve(library: PathBuf, input: &mut impl Read, out: &mut impl Write) -> io::Result<()> {
    let bad = |what: String| io::Error::new(io::ErrorKind::InvalidData, what);
    // Before the plugin is loaded: the engine tells a failing host from a failing plugin.
    out.write_all(&[wire::HELLO])?;
    out.flush()?;
    if wire::read_tag(input)? != Some(wire::CREATE) {
        return Err(bad("expected a create message first".into()));
    }
    let size = wire::read_u64(input)?;
    let iterations = wire::read_u64(input)?;
    let config = wire::read_text(input)?;
    let (Ok(size), Ok(iterations)) = (usize::try_from(size), usize::try_from(iterations)) else {
        return Err(bad(format!("image size {size} or {iterations} iterations out of range")));
    };
    let pixels = size.checked_mul(size).filter(|p| p.checked_mul(32).is_some()).ok_or_else(|| bad(format!("image size {size}")))?;
    let mut instance = match Instance::load(&library, &config, size, iterations) {
        Ok(instance) => instance,
        // The cause crosses the pipe as text: the library's report and the loader's, once.
        Err(e) => return error(out, &r2d2_imaging::error::Report(&e).to_string()),
    };
    out.write_all(&[wire::OK])?;
    out.flush()?;
    let (mut residual, mut model, mut dirty) = (vec![0.0; pixels], vec![0.0; pixels], vec![0.0; pixels]);
    let mut psf_2n = vec![0.0; 4 * pixels];
    let mut increment = vec![0.0; pixels];
    while let Some(tag) = wire::read_tag(input)? {
        if tag == wire::DESTROY {
            // The plugin's destroy and the library's destructors run now: a crash there is
            // this process's end, which the engine sees before it commits anything.
            drop(instance);
            out.write_all(&[wire::OK])?;
            return out.flush();
        }
        if tag != wire::STEP {
            return Err(bad(format!("unexpected message tag {tag}")));
        }
        let iteration = wire::read_u64(input)? as usize;
        let flags = wire::read_u64(input)?;
        wire::read_f64s(input, &mut residual)?;
        wire::read_f64s(input, &mut model)?;
        if flags & wire::WITH_DIRTY != 0 {
            wire::read_f64s(input, &mut dirty)?;
        }
        if flags & wire::WITH_PSF != 0 {
            wire::read_f64s(input, &mut psf_2n)?;
        }
        match instance.step(iteration, &residual, &model, &dirty, &psf_2n, &mut increment) {
            Ok(()) => {
                out.write_all(&[wire::INCREMENT])?;
                wire::write_f64s(out, &increment)?;
                out.flush()?;
            }
            Err(message) => error(out, &message)?,
        }
    }
    Ok(())
}
