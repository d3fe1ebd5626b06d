//! The C allocator's policy for a process that runs large networks.

/// Blocks of at least this size are mapped on their own and unmapped when freed.
pub const MMAP_THRESHOLD: usize = 4 << 20;

/// Free memory at the top of a malloc heap kept for reuse, up to this much, rather than given
/// back at once. glibc's default (128 KiB) applies once the mmap threshold is set: a reader
/// decoding batch after batch of a table (each column a few hundred KB) then gave its heap
/// back and faulted it in again at every batch (measured: docs/user-guide.md, "Memory and
/// Dask").
pub const TRIM_THRESHOLD: usize = 16 << 20;

/// Make glibc's malloc give large freed blocks back to the system at once, and keep a bounded
/// amount of small freed memory for reuse ([`TRIM_THRESHOLD`]).
///
/// By default glibc raises its mmap threshold (up to 32 MiB) each time a mapped block is freed;
/// after the first inference the 4-32 MiB activations of a U-Net are carved from the heap
/// instead and stay resident. Measured with ONNX Runtime on the reference U-Net at 512^2:
/// +95 MB resident after every inference and a peak 110 MB higher at the next one; with a
/// fixed threshold the memory returns to the model's size after each run. ONNX Runtime (its
/// arena is off for large networks, see `steps::runtime`) and tract both allocate through this malloc.
///
/// Process-wide, so the binary calls it at start-up; programs embedding the library may call
/// it too. Does nothing on other C libraries.
pub fn release_large_blocks_promptly() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets a tuning parameter of glibc's allocator; it takes plain integers,
    // is thread-safe, and no memory is touched.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD as libc::c_int);
        libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD as libc::c_int);
    }
}
