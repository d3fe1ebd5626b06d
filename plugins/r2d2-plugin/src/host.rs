//! The host side of the ABI: loading a plugin library and calling it ([`Instance`]), and the
//! wire protocol between the engine and the isolated plugin host process ([`wire`]).
//!
//! Both the engine (plugins loaded into its own process, `isolation: none`) and the
//! `r2d2-plugin-host` executable (one plugin per child process, the default) load plugins
//! through [`Instance`], so a plugin fails with the same messages either way.

use crate::{symbols, AbiVersionFn, CreateFn, DestroyFn, LastErrorFn, RawStepInput, StepFn, ABI_VERSION};
use libloading::Library;
use std::ffi::{c_char, c_void, CStr, CString};
use std::path::Path;
use std::ptr::NonNull;

/// A created plugin instance and the library it lives in.
pub struct Instance {
    handle: NonNull<c_void>,
    step: StepFn,
    last_error: LastErrorFn,
    destroy: DestroyFn,
    size: usize,
    /// Declared last so it is dropped after `Drop::drop` has destroyed the handle: the
    /// library's code must stay mapped while the handle exists.
    _library: Library,
}

// SAFETY: the ABI (header, "Threads") requires that a handle may be used from any thread, one
// thread at a time; `Instance` is only used through `&mut self` (or dropped), so Rust's
// ownership rules already give one thread at a time. The function pointers are plain code.
unsafe impl Send for Instance {}

impl Drop for Instance {
    fn drop(&mut self) {
        // SAFETY: the handle came from this library's create, is destroyed exactly once here,
        // and the library (a later field) is still loaded.
        unsafe { (self.destroy)(self.handle.as_ptr()) };
    }
}

/// A message returned by the plugin (NUL-terminated UTF-8 owned by the plugin).
///
/// # Safety
/// `p` is NULL or points to a NUL-terminated string valid until the next call into the plugin.
unsafe fn plugin_message(p: *const c_char) -> String {
    if p.is_null() {
        return "(the plugin gave no message)".into();
    }
    // SAFETY: non-NULL and NUL-terminated by the caller's contract; copied out at once.
    let text = unsafe { CStr::from_ptr(p) }.to_string_lossy().trim().to_string();
    if text.is_empty() {
        "(the plugin gave an empty message)".into()
    } else {
        text
    }
}

/// Why a plugin library could not be loaded and created ([`Instance::load`]); the dynamic
/// loader's own error, where there is one, is the [`source`](std::error::Error::source). The
/// caller names the library.
#[derive(Debug)]
#[non_exhaustive]
pub enum LoadError {
    /// The dynamic loader refused the file.
    Library(libloading::Error),
    /// The library does not export the ABI version symbol.
    NotAPlugin { symbol: String, source: libloading::Error },
    /// The library speaks another version of the ABI.
    AbiVersion { found: u32 },
    /// A symbol of the ABI version it declares is missing.
    MissingSymbol { symbol: String, source: libloading::Error },
    /// The configuration JSON holds a NUL character (it crosses the ABI as a C string).
    ConfigurationNul,
    /// More iterations than the ABI's `uint32_t` holds.
    TooManyIterations(usize),
    /// The plugin's `create` refused the configuration, with its own message.
    Refused { configuration: String, message: String },
}

impl std::fmt::Display for LoadError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LoadError::Library(_) => write!(f, "cannot load the plugin library"),
            LoadError::NotAPlugin { symbol, .. } => write!(f, "not an r2d2 plugin: missing symbol {symbol}"),
            LoadError::AbiVersion { found } => write!(
                f,
                "plugin ABI version {found}, but this r2d2 speaks version {ABI_VERSION}: rebuild the plugin against r2d2_plugin.h version {ABI_VERSION}"
            ),
            LoadError::MissingSymbol { symbol, .. } => write!(f, "plugin ABI version {ABI_VERSION} but missing symbol {symbol}"),
            LoadError::ConfigurationNul => write!(f, "the plugin configuration contains a NUL character"),
            LoadError::TooManyIterations(n) => write!(f, "{n} iterations is too many"),
            LoadError::Refused { configuration, message } => write!(f, "the plugin refused its configuration {configuration}: {message}"),
        }
    }
}

impl std::error::Error for LoadError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            LoadError::Library(e) | LoadError::NotAPlugin { source: e, .. } | LoadError::MissingSymbol { source: e, .. } => Some(e),
            _ => None,
        }
    }
}

fn symbol_name(s: &[u8]) -> String {
    String::from_utf8_lossy(&s[..s.len() - 1]).into_owned()
}

impl Instance {
    /// Load the library, check its ABI version and symbols, and create an instance for
    /// `image_size` x `image_size` images. The caller names the library in its messages.
    pub fn load(path: &Path, config_json: &str, image_size: usize, iterations: usize) -> Result<Instance, LoadError> {
        // SAFETY: loading a library runs its initialisers, arbitrary code the user chose to
        // trust by naming it in the pipeline; nothing more can be checked before loading.
        let library = unsafe { Library::new(path) }.map_err(LoadError::Library)?;
        // SAFETY (each `get`): the type is the header's signature for that symbol, which a
        // library exporting the symbol promises by the ABI version checked first. The copied
        // function pointers are only used while `library` stays loaded (it lives in `Instance`).
        let abi_version: AbiVersionFn = *unsafe { library.get::<AbiVersionFn>(symbols::ABI_VERSION) }
            .map_err(|source| LoadError::NotAPlugin { symbol: symbol_name(symbols::ABI_VERSION), source })?;
        // SAFETY: takes no arguments and, by the ABI, cannot fail.
        let version = unsafe { abi_version() };
        if version != ABI_VERSION {
            return Err(LoadError::AbiVersion { found: version });
        }
        fn get<T: Copy>(library: &Library, name: &[u8]) -> Result<T, LoadError> {
            // SAFETY: see above; T is the header's signature for `name`.
            unsafe { library.get::<T>(name) }.map(|s| *s).map_err(|source| LoadError::MissingSymbol { symbol: symbol_name(name), source })
        }
        let create: CreateFn = get(&library, symbols::CREATE)?;
        let step: StepFn = get(&library, symbols::STEP)?;
        let last_error: LastErrorFn = get(&library, symbols::LAST_ERROR)?;
        let destroy: DestroyFn = get(&library, symbols::DESTROY)?;
        let config = CString::new(config_json).map_err(|_| LoadError::ConfigurationNul)?;
        let iterations = u32::try_from(iterations).map_err(|_| LoadError::TooManyIterations(iterations))?;
        // SAFETY: a NUL-terminated string that outlives the call, as create requires.
        let handle = unsafe { create(config.as_ptr(), image_size as u64, iterations) };
        let Some(handle) = NonNull::new(handle) else {
            // SAFETY: NULL asks for the calling thread's create error, read right after create.
            let message = unsafe { plugin_message(last_error(std::ptr::null())) };
            return Err(LoadError::Refused { configuration: config_json.to_string(), message });
        };
        Ok(Instance { handle, step, last_error, destroy, size: image_size, _library: library })
    }

    /// Image size N the instance was created for.
    pub fn size(&self) -> usize {
        self.size
    }

    /// One step: writes the increment (N x N, filled with NaN first, so that a pixel the
    /// plugin leaves unwritten shows). The caller checks the increment for finiteness.
    pub fn step(
        &mut self,
        iteration: usize,
        residual: &[f64],
        model: &[f64],
        dirty: &[f64],
        psf_2n: &[f64],
        increment: &mut [f64],
    ) -> Result<(), String> {
        let n = self.size;
        let pixels = n * n;
        let lengths = [residual.len(), model.len(), dirty.len(), increment.len()];
        if lengths.iter().any(|&l| l != pixels) || psf_2n.len() != 4 * pixels {
            return Err(format!("inconsistent image sizes for N = {n}"));
        }
        increment.fill(f64::NAN);
        let raw = RawStepInput {
            size: n as u64,
            iteration: iteration as u64,
            residual: residual.as_ptr(),
            model: model.as_ptr(),
            dirty: dirty.as_ptr(),
            psf_2n: psf_2n.as_ptr(),
        };
        // SAFETY: a live handle used by this thread only (`&mut self`); every input pointer
        // covers the lengths checked above and outlives the call; `increment` has N x N
        // writable values and, being borrowed mutably, overlaps no input.
        let status = unsafe { (self.step)(self.handle.as_ptr(), &raw, increment.as_mut_ptr()) };
        if status != 0 {
            // SAFETY: the handle's message, valid until the next call, copied at once.
            let message = unsafe { plugin_message((self.last_error)(self.handle.as_ptr())) };
            return Err(format!("plugin step {iteration} failed (status {status}): {message}"));
        }
        Ok(())
    }
}

/// The byte protocol between the engine and `r2d2-plugin-host`, over two pipes of its own
/// (Unix: the host's descriptors given on its command line; the plugin's standard input is
/// `/dev/null` and its standard output goes to standard error, so nothing the plugin does with
/// descriptors 0 to 2 reaches the protocol). Every message starts with a tag byte; integers
/// are little-endian u64; images are raw little-endian f64, N x N (the PSF 2N x 2N).
///
/// - host -> engine, first: [`HELLO`], before the plugin is loaded.
/// - engine -> host, once: [`CREATE`], image size, iterations, config length, config JSON.
/// - host -> engine: [`OK`], or [`ERROR`] then a message.
/// - engine -> host, per step: [`STEP`], iteration, flags ([`WITH_DIRTY`], [`WITH_PSF`]),
///   residual, model, then the dirty image and PSF when flagged (they change per job, not
///   per step, so the host keeps the last ones it was sent).
/// - host -> engine: [`INCREMENT`] then N x N values, or [`ERROR`] then a message.
/// - engine -> host, last: [`DESTROY`]; the host destroys the instance and unloads the
///   library, answers [`OK`] and exits with status 0, which the engine checks before it
///   commits anything the plugin computed.
/// - host -> engine, at any time: [`FATAL`] then a message: the host itself gives up (the
///   engine sent what the protocol does not allow), then exits with [`HOST_FAILED`].
///
/// A message is at most [`MAX_TEXT`] bytes; the host cuts a plugin's message to
/// [`MAX_MESSAGE`] ([`bounded_message`]). The engine closing the host's input also ends it.
pub mod wire {
    use std::io::{self, Read, Write};

    /// The host's first byte, before it loads the plugin: it is a plugin host.
    pub const HELLO: u8 = b'H';
    pub const CREATE: u8 = b'C';
    pub const STEP: u8 = b'S';
    pub const OK: u8 = b'K';
    pub const ERROR: u8 = b'E';
    pub const INCREMENT: u8 = b'I';
    pub const DESTROY: u8 = b'D';
    pub const FATAL: u8 = b'F';
    /// The host's exit status when it gives up itself (after [`FATAL`], where it could send it).
    pub const HOST_FAILED: i32 = 3;
    pub const WITH_DIRTY: u64 = 1;
    pub const WITH_PSF: u64 = 2;
    /// Longest message or configuration accepted (a bound on what a length field may claim).
    pub const MAX_TEXT: u64 = 1 << 24;
    /// Longest plugin message the host passes on: an error message is read by a person.
    pub const MAX_MESSAGE: usize = 1 << 16;

    /// `message` cut to [`MAX_MESSAGE`] bytes (at a character boundary), with a note saying so.
    pub fn bounded_message(message: &str) -> std::borrow::Cow<'_, str> {
        if message.len() <= MAX_MESSAGE {
            return message.into();
        }
        let mut end = MAX_MESSAGE;
        while !message.is_char_boundary(end) {
            end -= 1;
        }
        format!("{} [... cut: the message has {} bytes, the first {end} are shown]", &message[..end], message.len()).into()
    }

    pub fn write_u64(w: &mut impl Write, v: u64) -> io::Result<()> {
        w.write_all(&v.to_le_bytes())
    }

    pub fn read_u64(r: &mut impl Read) -> io::Result<u64> {
        let mut b = [0u8; 8];
        r.read_exact(&mut b)?;
        Ok(u64::from_le_bytes(b))
    }

    /// Refuses (writing nothing) a text longer than [`MAX_TEXT`], which the other side would refuse.
    pub fn write_text(w: &mut impl Write, text: &str) -> io::Result<()> {
        if text.len() as u64 > MAX_TEXT {
            return Err(too_long(text.len() as u64));
        }
        write_u64(w, text.len() as u64)?;
        w.write_all(text.as_bytes())
    }

    pub fn read_text(r: &mut impl Read) -> io::Result<String> {
        let len = read_u64(r)?;
        if len > MAX_TEXT {
            return Err(too_long(len));
        }
        let mut bytes = vec![0u8; len as usize];
        r.read_exact(&mut bytes)?;
        Ok(String::from_utf8_lossy(&bytes).into_owned())
    }

    fn too_long(len: u64) -> io::Error {
        io::Error::new(io::ErrorKind::InvalidData, format!("a message of {len} bytes, more than the protocol's limit of {MAX_TEXT} bytes"))
    }

    /// Values converted through a small buffer (no copy of the whole image).
    pub fn write_f64s(w: &mut impl Write, values: &[f64]) -> io::Result<()> {
        let mut buffer = [0u8; 8 * 1024];
        for chunk in values.chunks(1024) {
            for (b, v) in buffer.chunks_exact_mut(8).zip(chunk) {
                b.copy_from_slice(&v.to_le_bytes());
            }
            w.write_all(&buffer[..8 * chunk.len()])?;
        }
        Ok(())
    }

    pub fn read_f64s(r: &mut impl Read, values: &mut [f64]) -> io::Result<()> {
        let mut buffer = [0u8; 8 * 1024];
        for chunk in values.chunks_mut(1024) {
            let bytes = &mut buffer[..8 * chunk.len()];
            r.read_exact(bytes)?;
            for (v, b) in chunk.iter_mut().zip(bytes.chunks_exact(8)) {
                *v = f64::from_le_bytes(b.try_into().expect("8 bytes"));
            }
        }
        Ok(())
    }

    /// A tag byte, or None at the end of the stream.
    pub fn read_tag(r: &mut impl Read) -> io::Result<Option<u8>> {
        let mut b = [0u8; 1];
        loop {
            match r.read(&mut b) {
                Ok(0) => return Ok(None),
                Ok(_) => return Ok(Some(b[0])),
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(e),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::wire;

    #[test]
    fn a_long_message_is_cut_at_a_character_with_a_note_and_a_short_one_kept() {
        assert_eq!(wire::bounded_message("step 2 failed"), "step 2 failed");
        // 'é' is two bytes: the cut may not split it.
        let long = format!("x{}", "é".repeat(wire::MAX_MESSAGE));
        let cut = wire::bounded_message(&long);
        let shown = wire::MAX_MESSAGE - 1;
        assert!(cut.starts_with(&long[..shown]), "the message's start is kept");
        assert!(cut.ends_with(&format!(" [... cut: the message has {} bytes, the first {shown} are shown]", long.len())), "{}", &cut[shown..]);
        assert!(cut.len() < wire::MAX_MESSAGE + 100);
    }

    #[test]
    fn frames_longer_than_the_limit_are_refused_on_both_sides_naming_it() {
        let limit = wire::MAX_TEXT as usize;
        let mut sent = Vec::new();
        let err = wire::write_text(&mut sent, &"x".repeat(limit + 1)).unwrap_err();
        assert!(sent.is_empty(), "nothing of a refused frame is written");
        assert_eq!(err.to_string(), format!("a message of {} bytes, more than the protocol's limit of {limit} bytes", limit + 1));
        // A length field claiming more is refused before anything is allocated.
        let mut frame = (u64::MAX).to_le_bytes().to_vec();
        frame.extend_from_slice(b"xyz");
        let err = wire::read_text(&mut frame.as_slice()).unwrap_err();
        assert_eq!(err.to_string(), format!("a message of {} bytes, more than the protocol's limit of {limit} bytes", u64::MAX));
        wire::write_text(&mut sent, "fits").unwrap();
        assert_eq!(wire::read_text(&mut sent.as_slice()).unwrap(), "fits");
    }
}
