//! What input may ask of the machine: sizes that files and configurations declare are checked
//! against the memory there is before anything is allocated, so that a hostile or mistaken
//! number gives an error instead of an aborted process.
//!
//! The memory is `MemAvailable` from `/proc/meminfo` (what can be allocated without swapping),
//! or `R2D2_MEMORY_LIMIT` (bytes, or with a suffix K, M, G or T: powers of 1024) when set, or
//! [`DEFAULT_MEMORY_CAP`] where neither is known.

use std::fmt;

/// The memory assumed where `/proc/meminfo` cannot be read (not Linux) and no limit is set.
pub const DEFAULT_MEMORY_CAP: u64 = 16 << 30;

/// The environment variable that sets the memory limit explicitly.
pub const MEMORY_LIMIT_VAR: &str = "R2D2_MEMORY_LIMIT";

/// How much memory work may take, and where that figure comes from (for messages).
#[derive(Clone, Copy, Debug)]
pub struct MemoryBudget {
    pub bytes: u64,
    pub origin: &'static str,
}

impl fmt::Display for MemoryBudget {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "the {} of memory available ({})", format_bytes(self.bytes as f64), self.origin)
    }
}

/// The memory available now (read each time: other processes come and go).
pub fn memory_budget() -> MemoryBudget {
    if let Ok(text) = std::env::var(MEMORY_LIMIT_VAR) {
        match parse_bytes(&text) {
            Some(bytes) => return MemoryBudget { bytes, origin: "R2D2_MEMORY_LIMIT" },
            None => log::warn!("{MEMORY_LIMIT_VAR}={text:?} ignored: expected bytes, or a number with K, M, G or T"),
        }
    }
    let available = match std::fs::read_to_string("/proc/meminfo").ok().and_then(|t| mem_available(&t)) {
        Some(bytes) => MemoryBudget { bytes, origin: "MemAvailable in /proc/meminfo" },
        None => MemoryBudget { bytes: DEFAULT_MEMORY_CAP, origin: "the default cap; set R2D2_MEMORY_LIMIT to change it" },
    };
    // An address-space limit (`ulimit -v`) below that: what is left of it is the budget, so
    // that a size it cannot hold is an error about memory, not an aborted allocation.
    match address_space_left() {
        Some(left) if left < available.bytes => MemoryBudget {
            bytes: left,
            origin: "the address-space limit (ulimit -v) less what the process maps and a reserve for its threads and inference runtime",
        },
        _ => available,
    }
}

/// Address space a run maps after its first size check, whatever its images: thread stacks
/// (each reserves its full stack under `ulimit -v`) and ONNX Runtime's library, weights and
/// threads. Without it a limit that passes the check aborts later, in an allocation no error
/// can come back from, or inside the runtime. Counted once: what the process maps after the
/// first check is taken from it.
pub const ADDRESS_SPACE_RESERVE: u64 = 896 << 20;

/// `RLIMIT_AS` less the process's current virtual size, when a limit is set.
#[cfg(target_os = "linux")]
fn address_space_left() -> Option<u64> {
    // SAFETY: getrlimit writes one `rlimit` into the valid, exclusively borrowed struct.
    let mut limit = libc::rlimit { rlim_cur: 0, rlim_max: 0 };
    if unsafe { libc::getrlimit(libc::RLIMIT_AS, &mut limit) } != 0 || limit.rlim_cur == libc::RLIM_INFINITY {
        return None;
    }
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let kib: u64 = status.lines().find(|l| l.starts_with("VmSize:"))?.split_whitespace().nth(1)?.parse().ok()?;
    let mapped = kib.saturating_mul(1024);
    // The process will map at least its size at the first check plus the reserve; what it has
    // mapped since counts against the reserve, not on top of it.
    static FIRST: std::sync::OnceLock<u64> = std::sync::OnceLock::new();
    let expected = mapped.max(FIRST.get_or_init(|| mapped).saturating_add(ADDRESS_SPACE_RESERVE));
    Some((limit.rlim_cur as u64).saturating_sub(expected))
}

#[cfg(not(target_os = "linux"))]
fn address_space_left() -> Option<u64> {
    None
}

/// `MemAvailable` of a `/proc/meminfo` text, in bytes.
fn mem_available(meminfo: &str) -> Option<u64> {
    let line = meminfo.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kib.checked_mul(1024)
}

/// `1234`, `512M`, `4G`, `1.5T` (powers of 1024).
fn parse_bytes(text: &str) -> Option<u64> {
    let text = text.trim();
    let (number, scale) = match text.char_indices().last()? {
        (i, c) if c.is_ascii_alphabetic() => {
            let power = "KMGT".find(c.to_ascii_uppercase())? as i32 + 1;
            (&text[..i], 1024f64.powi(power))
        }
        _ => (text, 1.0),
    };
    let bytes = number.trim().parse::<f64>().ok()? * scale;
    (bytes.is_finite() && bytes >= 1.0 && bytes < u64::MAX as f64).then_some(bytes as u64)
}

/// Refuses `needed` bytes (an estimate, in f64 so that no product of sizes overflows) when
/// they exceed the memory available; the message says what needed them.
pub fn check_memory(needed: f64, what: &str) -> std::result::Result<(), String> {
    let budget = memory_budget();
    if needed <= budget.bytes as f64 {
        return Ok(());
    }
    Err(format!("{what} needs about {} of memory, more than {budget}", format_bytes(needed)))
}

/// Bytes one job holds per pixel of its N x N image: dirty image, PSF, model, residual and
/// truth (5 x 8), the 2N PSF (4 x 8), the FFTs of the 2N-PSF convolution (kernel and work
/// grid, 2 x 4 x 16) and the NUFFT grid (4 x 16), rounded up for previews and scratch space.
pub const IMAGE_BYTES_PER_PIXEL: f64 = 320.0;

/// The smallest image side the operator takes (it also needs an even side: the phase centre
/// is the pixel N/2, and the PSF is 2N).
pub const MIN_IMAGE_SIZE: usize = 8;

/// Refuses an image size the operator cannot take (odd, or under [`MIN_IMAGE_SIZE`]) or whose
/// job cannot fit in the memory available (the product in f64: no overflow whatever the size).
pub fn check_image_size(size: usize) -> std::result::Result<(), String> {
    if size < MIN_IMAGE_SIZE || !size.is_multiple_of(2) {
        return Err(format!("expected an even image size of at least {MIN_IMAGE_SIZE} pixels, got {size}"));
    }
    let pixels = size as f64 * size as f64;
    check_memory(pixels * IMAGE_BYTES_PER_PIXEL, &format!("an image of {size} x {size} pixels"))
}

/// Threads per core allowed: more only adds switching (and 100 000 threads take minutes to
/// start, or fail to).
pub const THREADS_PER_CORE: usize = 4;

/// Refuses a thread count above [`THREADS_PER_CORE`] per core (0, all cores, is fine).
pub fn check_threads(threads: usize) -> std::result::Result<(), String> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let most = THREADS_PER_CORE * cores;
    if threads <= most {
        return Ok(());
    }
    Err(format!("{threads} threads is more than {THREADS_PER_CORE} per core of this machine's {cores} cores ({most}); 0 uses every core"))
}

/// `1.5 GB`, `12 MB`, `800 B` (decimal units, as `free -h` users read them closely enough).
pub fn format_bytes(bytes: f64) -> String {
    const UNITS: [&str; 7] = ["B", "kB", "MB", "GB", "TB", "PB", "EB"];
    let mut value = bytes;
    let mut unit = 0;
    while value >= 1000.0 && unit + 1 < UNITS.len() {
        value /= 1000.0;
        unit += 1;
    }
    if unit == 0 {
        format!("{value:.0} B")
    } else if !value.is_finite() || unit + 1 == UNITS.len() && value >= 1000.0 {
        format!("{bytes:.3e} B")
    } else {
        format!("{value:.1} {}", UNITS[unit])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_and_threads_are_checked() {
        assert!(check_image_size(64).is_ok());
        let err = check_image_size(1 << 40).unwrap_err();
        assert!(err.contains("1099511627776 x 1099511627776") && err.contains("memory available"), "{err}");
        for size in [0, 6, 63, 511] {
            let err = check_image_size(size).unwrap_err();
            assert!(err.contains("even image size of at least 8") && err.contains(&format!("got {size}")), "{err}");
        }
        assert!(check_threads(0).is_ok() && check_threads(1).is_ok());
        let err = check_threads(usize::MAX).unwrap_err();
        assert!(err.contains("cores"), "{err}");
    }

    #[test]
    fn memory_figures_parse() {
        assert_eq!(mem_available("MemTotal: 100 kB\nMemAvailable:   2048 kB\n"), Some(2 << 20));
        assert_eq!(mem_available("MemTotal: 100 kB\n"), None);
        assert_eq!(parse_bytes("4096"), Some(4096));
        assert_eq!(parse_bytes("2G"), Some(2 << 30));
        assert_eq!(parse_bytes("1.5k"), Some(1536));
        for bad in ["", "G", "-1", "1e400", "3X", "nan"] {
            assert_eq!(parse_bytes(bad), None, "{bad:?}");
        }
        assert_eq!(format_bytes(512.0), "512 B");
        assert_eq!(format_bytes(1.5e9), "1.5 GB");
        assert_eq!(format_bytes(1.1e12), "1.1 TB");
        assert_eq!(format_bytes(1e300), "1.000e300 B");
    }
}
