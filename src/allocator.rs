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

/// Blocks of at least this size are mapped by [`LargeBlocksOnHugePages`] with transparent huge
/// pages allowed.
pub const HUGE_PAGE_THRESHOLD: usize = MMAP_THRESHOLD;

/// A global allocator that maps large blocks ([`HUGE_PAGE_THRESHOLD`] and more) itself and
/// asks the kernel for transparent huge pages on them (`MADV_HUGEPAGE`), and passes every
/// other request to the system allocator.
///
/// A streamed pass plans, applies and drops an operator per chunk of samples: each of its
/// arrays (tens of MB) is a fresh mapping whose pages are faulted in one 4 KiB page at a time,
/// chunk after chunk. On 2 MiB pages the same memory takes 512 times fewer faults (and fewer
/// TLB misses while gridding); the blocks are still given back when freed, so what is
/// resident is what is in use, as with [`release_large_blocks_promptly`]. Where the kernel has
/// huge pages off (`transparent_hugepage/enabled: never`) the advice is ignored and this is
/// the system's mapping of large blocks. Elsewhere than Linux everything goes to the system
/// allocator.
pub struct LargeBlocksOnHugePages;

#[cfg(target_os = "linux")]
mod huge {
    use crate::allocator::HUGE_PAGE_THRESHOLD;
    use std::alloc::{GlobalAlloc, Layout, System};

    /// Alignment a mapping has (the page size); larger alignments go to the system allocator.
    const PAGE: usize = 4096;

    fn is_large(layout: &Layout) -> bool {
        layout.size() >= HUGE_PAGE_THRESHOLD && layout.align() <= PAGE
    }

    /// A fresh anonymous mapping of `size` bytes (zeroed), huge pages advised; null on failure.
    fn map(size: usize) -> *mut u8 {
        // SAFETY: an anonymous private mapping at an address of the kernel's choosing touches no
        // existing memory; the result is checked before use.
        let p = unsafe {
            libc::mmap(std::ptr::null_mut(), size, libc::PROT_READ | libc::PROT_WRITE, libc::MAP_PRIVATE | libc::MAP_ANONYMOUS, -1, 0)
        };
        if p == libc::MAP_FAILED {
            return std::ptr::null_mut();
        }
        // SAFETY: `p .. p + size` is the mapping just made; advice changes no contents, and a
        // refusal (huge pages off) leaves an ordinary mapping.
        unsafe { libc::madvise(p, size, libc::MADV_HUGEPAGE) };
        p.cast()
    }

    // SAFETY (the trait's contract): large blocks are whole mappings of at least the size asked,
    // page-aligned (every alignment up to PAGE), released with the size they were made with
    // (the layout's, which `dealloc` and `realloc` receive unchanged); all else is System's.
    unsafe impl GlobalAlloc for crate::allocator::LargeBlocksOnHugePages {
        unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
            if is_large(&layout) {
                map(layout.size())
            } else {
                // SAFETY: the caller's layout, as System requires.
                unsafe { System.alloc(layout) }
            }
        }

        unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
            if is_large(&layout) {
                map(layout.size()) // anonymous mappings are zeroed
            } else {
                // SAFETY: as `alloc`.
                unsafe { System.alloc_zeroed(layout) }
            }
        }

        unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
            if is_large(&layout) {
                // SAFETY: `ptr` is a mapping of `layout.size()` bytes made by `map` (the layout
                // it was allocated with), no longer used by the caller.
                unsafe { libc::munmap(ptr.cast(), layout.size()) };
            } else {
                // SAFETY: allocated by System with this layout.
                unsafe { System.dealloc(ptr, layout) }
            }
        }

        unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
            // SAFETY: the trait requires a valid layout for the new size with the same alignment.
            let new = unsafe { Layout::from_size_align_unchecked(new_size, layout.align()) };
            match (is_large(&layout), is_large(&new)) {
                // SAFETY: both small: System's own block, resized by System.
                (false, false) => unsafe { System.realloc(ptr, layout, new_size) },
                (true, true) => {
                    // SAFETY: `ptr` is a mapping of `layout.size()` bytes; mremap moves or grows
                    // it whole (its advice and contents with it) or fails leaving it as it was.
                    let p = unsafe { libc::mremap(ptr.cast(), layout.size(), new_size, libc::MREMAP_MAYMOVE) };
                    if p == libc::MAP_FAILED {
                        std::ptr::null_mut()
                    } else {
                        p.cast()
                    }
                }
                _ => {
                    // SAFETY: `new` is a valid layout (the trait's precondition); the copy takes the
                    // bytes both blocks hold, then the old block is released with its own layout.
                    unsafe {
                        let p = self.alloc(new);
                        if !p.is_null() {
                            std::ptr::copy_nonoverlapping(ptr, p, layout.size().min(new_size));
                            self.dealloc(ptr, layout);
                        }
                        p
                    }
                }
            }
        }
    }
}

#[cfg(not(target_os = "linux"))]
// SAFETY: every request goes to the system allocator unchanged.
unsafe impl std::alloc::GlobalAlloc for LargeBlocksOnHugePages {
    unsafe fn alloc(&self, layout: std::alloc::Layout) -> *mut u8 {
        // SAFETY: the caller's layout, as System requires.
        unsafe { std::alloc::System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: std::alloc::Layout) {
        // SAFETY: allocated by System with this layout.
        unsafe { std::alloc::System.dealloc(ptr, layout) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::alloc::{GlobalAlloc, Layout};

    /// Large blocks are zeroed where asked, writable to their last byte, keep their contents
    /// through a resize within and across the threshold, and small ones still work.
    #[test]
    fn large_and_small_blocks_round_trip_through_every_resize() {
        let a = LargeBlocksOnHugePages;
        let big = HUGE_PAGE_THRESHOLD + 12345;
        for (from, to) in [(big, 3 * big), (3 * big, big), (big, 100), (100, big), (64, 128)] {
            let layout = Layout::from_size_align(from, 8).unwrap();
            // SAFETY: a valid non-zero layout; every access stays within the block's current
            // size; the block is freed once, with the layout it has at that point.
            unsafe {
                let p = a.alloc_zeroed(layout);
                assert!(!p.is_null());
                assert!(std::slice::from_raw_parts(p, from).iter().all(|&b| b == 0));
                for i in 0..from {
                    *p.add(i) = (i % 251) as u8;
                }
                let q = a.realloc(p, layout, to);
                assert!(!q.is_null());
                let kept = from.min(to);
                assert!(std::slice::from_raw_parts(q, kept).iter().enumerate().all(|(i, &b)| b == (i % 251) as u8));
                *q.add(to - 1) = 7;
                a.dealloc(q, Layout::from_size_align(to, 8).unwrap());
            }
        }
        // Alignments beyond a page go to the system allocator, and are honoured.
        let layout = Layout::from_size_align(big, 1 << 16).unwrap();
        // SAFETY: a valid layout, freed once with it.
        unsafe {
            let p = a.alloc(layout);
            assert!(!p.is_null() && (p as usize).is_multiple_of(1 << 16));
            a.dealloc(p, layout);
        }
    }
}
