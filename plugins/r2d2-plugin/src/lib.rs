//! The C ABI of r2d2 native network-step plugins, and support for writing one in Rust.
//!
//! The contract is `include/r2d2_plugin.h` (ABI version [`ABI_VERSION`]); this crate mirrors
//! it in Rust for both sides: the host (`r2d2`) loads libraries with these types, and a
//! plugin implements [`Plugin`] and exports the C symbols with [`export_plugin!`]:
//!
//! ```no_run
//! struct Halve;
//! impl r2d2_plugin::Plugin for Halve {
//!     fn create(_config_json: &str, _setup: &r2d2_plugin::Setup) -> Result<Self, String> {
//!         Ok(Halve)
//!     }
//!     fn step(&mut self, input: &r2d2_plugin::StepInput<'_>, increment: &mut [f64]) -> Result<(), String> {
//!         for (d, r) in increment.iter_mut().zip(input.residual) {
//!             *d = 0.5 * r;
//!         }
//!         Ok(())
//!     }
//! }
//! r2d2_plugin::export_plugin!(Halve);
//! ```
//!
//! with `crate-type = ["cdylib"]` in the plugin's `Cargo.toml`. The exported functions catch
//! every panic (it becomes the error message), so a panic never crosses the C boundary; the
//! plugin must be built with `panic = "unwind"` (the default) for that to work.

use std::cell::RefCell;
use std::ffi::{c_char, c_void, CStr, CString};
use std::panic::{catch_unwind, AssertUnwindSafe};

#[cfg(feature = "host")]
pub mod host;

/// Version of the C ABI; equal to `R2D2_PLUGIN_ABI_VERSION` in the header.
pub const ABI_VERSION: u32 = 1;

/// The header, for tools and tests that check it against these definitions.
pub const HEADER: &str = include_str!("../include/r2d2_plugin.h");

/// Exported symbol names, NUL-terminated for `dlsym`.
pub mod symbols {
    pub const ABI_VERSION: &[u8] = b"r2d2_plugin_abi_version\0";
    pub const CREATE: &[u8] = b"r2d2_plugin_create\0";
    pub const STEP: &[u8] = b"r2d2_plugin_step\0";
    pub const LAST_ERROR: &[u8] = b"r2d2_plugin_last_error\0";
    pub const DESTROY: &[u8] = b"r2d2_plugin_destroy\0";
}

/// `r2d2_step_input` of the header: two 64-bit integers then pointers, so no padding.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct RawStepInput {
    pub size: u64,
    pub iteration: u64,
    pub residual: *const f64,
    pub model: *const f64,
    pub dirty: *const f64,
    pub psf_2n: *const f64,
}

/// Signatures of the five exported functions.
pub type AbiVersionFn = unsafe extern "C" fn() -> u32;
pub type CreateFn = unsafe extern "C" fn(config_json: *const c_char, image_size: u64, iterations: u32) -> *mut c_void;
pub type StepFn = unsafe extern "C" fn(handle: *mut c_void, input: *const RawStepInput, increment_out: *mut f64) -> i32;
pub type LastErrorFn = unsafe extern "C" fn(handle: *const c_void) -> *const c_char;
pub type DestroyFn = unsafe extern "C" fn(handle: *mut c_void);

/// What the host tells a plugin when creating it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Setup {
    /// N: images are N x N.
    pub image_size: usize,
    /// Series length the pipeline will run (iterations are 1..=iterations).
    pub iterations: usize,
}

/// One step's inputs (see the header for units and conventions).
#[derive(Clone, Copy, Debug)]
pub struct StepInput<'a> {
    /// 1-based.
    pub iteration: usize,
    /// N.
    pub size: usize,
    /// `r_{i-1}`, N x N row-major.
    pub residual: &'a [f64],
    /// `x_{i-1}`, N x N.
    pub model: &'a [f64],
    /// `x_d`, N x N.
    pub dirty: &'a [f64],
    /// 2N x 2N PSF, peak at (N, N).
    pub psf_2n: &'a [f64],
}

/// A network step implemented in Rust.
pub trait Plugin: Send + Sized + 'static {
    /// Build from the stage's `config:` mapping (a JSON object) before imaging starts;
    /// reject anything wrong here, with a message naming the key and what was expected.
    fn create(config_json: &str, setup: &Setup) -> Result<Self, String>;

    /// Write the increment for every pixel (`increment` has N x N values; its contents on
    /// entry are unspecified).
    fn step(&mut self, input: &StepInput<'_>, increment: &mut [f64]) -> Result<(), String>;
}

/// Exports the C symbols of the header for a [`Plugin`] type. Use once per cdylib.
#[macro_export]
macro_rules! export_plugin {
    ($plugin:ty) => {
        /// ABI version this plugin was built against.
        #[no_mangle]
        pub extern "C" fn r2d2_plugin_abi_version() -> u32 {
            $crate::ABI_VERSION
        }

        /// # Safety
        /// As `r2d2_plugin_create` in `r2d2_plugin.h`: `config_json` is NULL or a NUL-terminated string.
        #[no_mangle]
        pub unsafe extern "C" fn r2d2_plugin_create(
            config_json: *const ::std::ffi::c_char,
            image_size: u64,
            iterations: u32,
        ) -> *mut ::std::ffi::c_void {
            // SAFETY: the caller keeps the header's contract, which is create's precondition.
            unsafe { $crate::export::create::<$plugin>(config_json, image_size, iterations) }
        }

        /// # Safety
        /// As `r2d2_plugin_step` in `r2d2_plugin.h`: a live handle from create, valid input, N x N output.
        #[no_mangle]
        pub unsafe extern "C" fn r2d2_plugin_step(
            handle: *mut ::std::ffi::c_void,
            input: *const $crate::RawStepInput,
            increment_out: *mut f64,
        ) -> i32 {
            // SAFETY: as above, the header's contract is step's precondition.
            unsafe { $crate::export::step::<$plugin>(handle, input, increment_out) }
        }

        /// # Safety
        /// As `r2d2_plugin_last_error` in `r2d2_plugin.h`: NULL or a live handle from create.
        #[no_mangle]
        pub unsafe extern "C" fn r2d2_plugin_last_error(handle: *const ::std::ffi::c_void) -> *const ::std::ffi::c_char {
            // SAFETY: as above.
            unsafe { $crate::export::last_error::<$plugin>(handle) }
        }

        /// # Safety
        /// As `r2d2_plugin_destroy` in `r2d2_plugin.h`: NULL or a live handle, destroyed once.
        #[no_mangle]
        pub unsafe extern "C" fn r2d2_plugin_destroy(handle: *mut ::std::ffi::c_void) {
            // SAFETY: as above.
            unsafe { $crate::export::destroy::<$plugin>(handle) }
        }
    };
}

/// What a handle points at: the plugin and the message of its last failure.
struct Instance<P> {
    plugin: P,
    last_error: CString,
    /// Set when a step panicked: the plugin's state may be half-updated, so later steps refuse.
    poisoned: bool,
}

thread_local! {
    /// The last create failure on this thread (a failed create has no handle to hold it).
    static CREATE_ERROR: RefCell<CString> = RefCell::new(CString::default());
}

/// A C string from a message (interior NULs, which C cannot carry, become spaces).
fn c_message(message: &str) -> CString {
    CString::new(message.replace('\0', " ")).unwrap_or_default()
}

fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    let text = payload
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "(no message)".to_string());
    format!("plugin panicked: {text}")
}

/// Length of an N x N (factor 1) or 2N x 2N (factor 4) image, if it is addressable.
fn image_len(size: u64, factor: usize) -> Option<usize> {
    let n = usize::try_from(size).ok()?;
    let len = n.checked_mul(n)?.checked_mul(factor)?;
    (len <= isize::MAX as usize / std::mem::size_of::<f64>()).then_some(len)
}

/// The generic bodies of the exported functions (called by [`export_plugin!`]).
#[doc(hidden)]
pub mod export {
    use super::*;

    /// # Safety
    /// `config_json` is NULL or points to a NUL-terminated string valid for the call.
    pub unsafe fn create<P: Plugin>(config_json: *const c_char, image_size: u64, iterations: u32) -> *mut c_void {
        let made = catch_unwind(AssertUnwindSafe(|| -> Result<P, String> {
            if config_json.is_null() {
                return Err("config_json is NULL (expected a JSON object)".into());
            }
            // SAFETY: non-NULL, and the caller guarantees NUL termination and validity.
            let text = unsafe { CStr::from_ptr(config_json) }
                .to_str()
                .map_err(|e| format!("config_json is not UTF-8: {e}"))?;
            let setup = Setup {
                image_size: usize::try_from(image_size).map_err(|_| format!("image size {image_size} is too large"))?,
                iterations: iterations as usize,
            };
            P::create(text, &setup)
        }));
        let message = match made {
            Ok(Ok(plugin)) => {
                let instance = Box::new(Instance { plugin, last_error: CString::default(), poisoned: false });
                return Box::into_raw(instance).cast();
            }
            Ok(Err(message)) => message,
            Err(payload) => panic_message(payload.as_ref()),
        };
        CREATE_ERROR.with(|e| *e.borrow_mut() = c_message(&message));
        std::ptr::null_mut()
    }

    /// # Safety
    /// `handle` came from [`create`] for the same `P` and is used by one thread at a time;
    /// `input` and its arrays and `increment_out` are valid as the header states.
    pub unsafe fn step<P: Plugin>(handle: *mut c_void, input: *const RawStepInput, increment_out: *mut f64) -> i32 {
        if handle.is_null() {
            return -1;
        }
        // SAFETY: a live handle is a Box<Instance<P>> from create, and the host does not use it
        // from another thread during this call (the header's threading rule).
        let instance = unsafe { &mut *handle.cast::<Instance<P>>() };
        let result = catch_unwind(AssertUnwindSafe(|| -> Result<(), String> {
            if instance.poisoned {
                return Err("an earlier step panicked; the plugin's state is not trustworthy".into());
            }
            if input.is_null() || increment_out.is_null() {
                return Err("NULL input or output pointer".into());
            }
            // SAFETY: non-NULL and valid for the call (caller's contract).
            let raw = unsafe { *input };
            let n2 = image_len(raw.size, 1).ok_or_else(|| format!("image size {} is not addressable", raw.size))?;
            let n4 = image_len(raw.size, 4).ok_or_else(|| format!("image size {} is not addressable", raw.size))?;
            if raw.residual.is_null() || raw.model.is_null() || raw.dirty.is_null() || raw.psf_2n.is_null() {
                return Err("NULL image pointer in the step input".into());
            }
            // SAFETY: the header guarantees N x N (2N x 2N for the PSF) readable doubles behind
            // each input pointer and N x N writable ones behind increment_out, not overlapping
            // the inputs, for the duration of this call; lengths were checked to be addressable.
            let (residual, model, dirty, psf_2n, increment) = unsafe {
                (
                    std::slice::from_raw_parts(raw.residual, n2),
                    std::slice::from_raw_parts(raw.model, n2),
                    std::slice::from_raw_parts(raw.dirty, n2),
                    std::slice::from_raw_parts(raw.psf_2n, n4),
                    std::slice::from_raw_parts_mut(increment_out, n2),
                )
            };
            let step_input = StepInput {
                iteration: raw.iteration as usize,
                size: raw.size as usize,
                residual,
                model,
                dirty,
                psf_2n,
            };
            instance.plugin.step(&step_input, increment)
        }));
        let message = match result {
            Ok(Ok(())) => return 0,
            Ok(Err(message)) => message,
            Err(payload) => {
                instance.poisoned = true;
                panic_message(payload.as_ref())
            }
        };
        instance.last_error = c_message(&message);
        1
    }

    /// # Safety
    /// `handle` is NULL or a live handle from [`create`] for the same `P`.
    pub unsafe fn last_error<P: Plugin>(handle: *const c_void) -> *const c_char {
        if handle.is_null() {
            // The pointer stays valid until the next create on this thread replaces the string.
            return CREATE_ERROR.with(|e| e.borrow().as_ptr());
        }
        // SAFETY: a live Box<Instance<P>> not being mutated concurrently (threading rule).
        unsafe { (*handle.cast::<Instance<P>>()).last_error.as_ptr() }
    }

    /// # Safety
    /// `handle` is NULL or a live handle from [`create`] for the same `P`, not used afterwards.
    pub unsafe fn destroy<P: Plugin>(handle: *mut c_void) {
        if handle.is_null() {
            return;
        }
        // SAFETY: the handle is the Box created by `create`, destroyed exactly once.
        let instance = unsafe { Box::from_raw(handle.cast::<Instance<P>>()) };
        // A panicking Drop of the plugin must not unwind into C either.
        let _ = catch_unwind(AssertUnwindSafe(move || drop(instance)));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_states_the_same_version_and_symbols() {
        let define = HEADER.lines().find(|l| l.starts_with("#define R2D2_PLUGIN_ABI_VERSION")).expect("version define");
        assert_eq!(define.split_whitespace().nth(2), Some(format!("{ABI_VERSION}u").as_str()));
        for symbol in [symbols::ABI_VERSION, symbols::CREATE, symbols::STEP, symbols::LAST_ERROR, symbols::DESTROY] {
            let name = std::str::from_utf8(&symbol[..symbol.len() - 1]).unwrap();
            // Declared as `<type> name(` or `<type> *name(` (pointer results).
            let declared = HEADER.contains(&format!(" {name}(")) || HEADER.contains(&format!(" *{name}("));
            assert!(declared, "{name} not declared in the header");
        }
        assert_eq!(std::mem::size_of::<RawStepInput>(), 16 + 4 * std::mem::size_of::<*const f64>());
    }

    /// A plugin that doubles the residual, fails on request and panics on request.
    struct Doubler {
        panic_at: usize,
    }
    impl Plugin for Doubler {
        fn create(config_json: &str, setup: &Setup) -> Result<Self, String> {
            match config_json {
                "fail" => Err(format!("asked to fail at size {}", setup.image_size)),
                "panic" => panic!("create panicked on request"),
                _ => Ok(Doubler { panic_at: config_json.parse().unwrap_or(0) }),
            }
        }
        fn step(&mut self, input: &StepInput<'_>, increment: &mut [f64]) -> Result<(), String> {
            if input.iteration == self.panic_at {
                panic!("step {} panicked", input.iteration);
            }
            for (d, r) in increment.iter_mut().zip(input.residual) {
                *d = 2.0 * r;
            }
            Ok(())
        }
    }

    fn message(p: *const c_char) -> String {
        // SAFETY: the functions under test return NUL-terminated strings valid until the next call.
        unsafe { CStr::from_ptr(p) }.to_string_lossy().into_owned()
    }

    #[test]
    fn create_failures_and_panics_become_messages() {
        for (config, expected) in [("fail", "asked to fail at size 4"), ("panic", "plugin panicked: create panicked on request")] {
            let c = CString::new(config).unwrap();
            // SAFETY: a valid C string; the handle is checked before use.
            unsafe {
                let handle = export::create::<Doubler>(c.as_ptr(), 4, 2);
                assert!(handle.is_null());
                assert_eq!(message(export::last_error::<Doubler>(std::ptr::null())), expected);
            }
        }
    }

    #[test]
    fn step_writes_the_increment_and_a_panic_poisons_the_handle() {
        let n = 2usize;
        let residual = [1.0, -2.0, 3.0, 0.5];
        let zeros = [0.0; 4];
        let psf = [0.0; 16];
        let mut out = [f64::NAN; 4];
        let input = RawStepInput {
            size: n as u64,
            iteration: 1,
            residual: residual.as_ptr(),
            model: zeros.as_ptr(),
            dirty: residual.as_ptr(),
            psf_2n: psf.as_ptr(),
        };
        let config = CString::new("2").unwrap();
        // SAFETY: all buffers have the sizes the header requires and outlive the calls.
        unsafe {
            let handle = export::create::<Doubler>(config.as_ptr(), n as u64, 3);
            assert!(!handle.is_null());
            assert_eq!(export::step::<Doubler>(handle, &input, out.as_mut_ptr()), 0);
            assert_eq!(out, [2.0, -4.0, 6.0, 1.0]);
            let second = RawStepInput { iteration: 2, ..input };
            assert_eq!(export::step::<Doubler>(handle, &second, out.as_mut_ptr()), 1);
            assert_eq!(message(export::last_error::<Doubler>(handle)), "plugin panicked: step 2 panicked");
            assert_eq!(export::step::<Doubler>(handle, &input, out.as_mut_ptr()), 1);
            assert!(message(export::last_error::<Doubler>(handle)).contains("earlier step panicked"));
            export::destroy::<Doubler>(handle);
        }
    }
}
