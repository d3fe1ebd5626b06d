//! The C allocator's policy for a process that runs large networks.

/// Blocks of at least this size are mapped on their own and unmapped when freed.
pub const MMAP_THRESHOLD: usize = 4 << 20;

/// Make glibc's malloc give large freed blocks back to the system at once.
///
/// By default glibc raises its mmap threshold (up to 32 MiB) each time a mapped block is freed;
/// after the first inference the 4-32 MiB activations of a U-Net are carved from the heap
/// instead and stay resident. Measured with ONNX Runtime on the reference U-Net at 512^2:
/// +95 MB resident after every inference and a peak 110 MB higher at the next one; with a
/// fixed threshold the memory returns to the model's size after each run. ONNX Runtime (its
/// arena is off, see `steps::runtime`) and tract both allocate through this malloc.
///
/// Process-wide, so the binary calls it at start-up; programs embedding the library may call
/// it too. Does nothing on other C libraries.
pub fn release_large_blocks_promptly() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets a tuning parameter of glibc's allocator; it takes plain integers,
    // is thread-safe, and no memory is touched.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD as libc::c_int);
    }
}
