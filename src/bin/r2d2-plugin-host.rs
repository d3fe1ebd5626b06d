//! `r2d2-plugin-host LIBRARY`: runs one native plugin in a process of its own, so that a
//! plugin that crashes, exits or hangs takes only this process down; the engine supervises
//! it (`src/steps/native_host.rs`) and turns its end into an error naming the library.
//!
//! It speaks `r2d2_plugin::host::wire` on standard input and output; the plugin's own
//! writes to standard output go to standard error, so they cannot corrupt the protocol.
//! Not meant to be run by hand.

use r2d2_plugin::host::{wire, Instance};
use std::io::{self, BufReader, BufWriter, Read, Write};
use std::path::PathBuf;

fn main() {
    let mut args = std::env::args_os().skip(1);
    let (Some(library), None) = (args.next(), args.next()) else {
        eprintln!("usage: r2d2-plugin-host LIBRARY (started by r2d2 for `kind: native` steps; not meant to be run by hand)");
        std::process::exit(2);
    };
    let protocol_out = protocol_output();
    let result = serve(PathBuf::from(library), &mut BufReader::new(io::stdin().lock()), &mut BufWriter::new(protocol_out));
    if let Err(e) = result {
        // The engine is gone or sent garbage: nothing to answer to.
        eprintln!("r2d2-plugin-host: {e}");
        std::process::exit(3);
    }
}

/// The protocol's output: a duplicate of standard output, which then points at standard
/// error (a plugin's printf must not land in the protocol). Also asks the kernel to kill this
/// process when the engine dies, so a hung plugin never outlives it.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn protocol_output() -> Box<dyn Write> {
    use std::os::fd::FromRawFd;
    // SAFETY: plain system calls on this process's own standard descriptors, before any
    // other thread exists; `dup` returns a fresh descriptor that only the File below owns.
    unsafe {
        libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
        let fd = libc::dup(1);
        if fd >= 0 && libc::dup2(2, 1) >= 0 {
            return Box::new(std::fs::File::from_raw_fd(fd));
        }
    }
    Box::new(io::stdout())
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn protocol_output() -> Box<dyn Write> {
    Box::new(io::stdout())
}

fn error(out: &mut impl Write, message: &str) -> io::Result<()> {
    out.write_all(&[wire::ERROR])?;
    wire::write_text(out, message)?;
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
