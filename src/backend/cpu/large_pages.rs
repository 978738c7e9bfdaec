//! Arrays that a traversal reads at random places (the wide nodes, the corner blocks), placed so that Linux can back
//! them with 2 MiB pages: each incoherent ray touches a few lines of each of several pages, and with 4 KiB pages a
//! large accel's pages are far more than the CPU's address-translation caches hold, so that most node and block reads
//! also wait for a page-table walk (BENCHMARKS.md, "A random ray against Embree's, visit by visit; and the
//! traversal's arrays on large pages").
//!
//! An array of at least [`LARGE_PAGE`] bytes starts on a 2 MiB boundary and its whole 2 MiB stretches are marked
//! `MADV_HUGEPAGE` before anything is written to them, so that their first touch maps large pages wherever the
//! kernel's transparent huge pages are `always` or `madvise` (the common default) and memory allows; the rest of it
//! (less than 2 MiB) and smaller arrays use ordinary pages, so no memory is spent beyond what the array holds. Where
//! the kernel offers no large pages (another OS, `never`, fragmented memory) the same array works with small ones.
//! [`set_enabled`] turns the advice off for arrays made afterwards.

use std::alloc::{Layout, alloc, dealloc, handle_alloc_error};
use std::fmt;
use std::ops::Deref;
use std::ptr::NonNull;
use std::sync::atomic::{AtomicBool, Ordering};

use rayon::prelude::*;

use super::bvh::VecLen;

/// Bytes of a large page (x86-64 and most 64-bit Linux platforms).
pub const LARGE_PAGE: usize = 2 << 20;

/// Whether arrays made from now on ask for large pages ([`set_enabled`]).
static ENABLED: AtomicBool = AtomicBool::new(true);

/// Whether CPU accels built from now on ask the kernel for large pages for their traversal arrays (default: yes).
/// rayd sets it from its `large_pages` configuration key at start.
pub fn set_enabled(enabled: bool) {
    ENABLED.store(enabled, Ordering::Relaxed);
}

/// A fixed-length array of `T` laid out for large pages (see the module's documentation); otherwise a boxed slice.
pub(super) struct LargePageArray<T: Copy> {
    /// The first element; dangling when the array is empty.
    start: NonNull<T>,
    /// Elements.
    len: usize,
}

// SAFETY: the array owns its elements as a `Box<[T]>` would.
unsafe impl<T: Copy + Send> Send for LargePageArray<T> {}
// SAFETY: shared access only reads the elements.
unsafe impl<T: Copy + Sync> Sync for LargePageArray<T> {}

impl<T: Copy> LargePageArray<T> {
    /// An array of `len` elements, element `i` being `element(i)`, written after the large-page advice by rayon's
    /// threads, a large page's worth of neighbours at least each (an accel's arrays are made once a build: the
    /// writes, and the kernel's zeroing of the pages they touch first, spread over the cores).
    pub fn from_fn(len: usize, element: impl Fn(usize) -> T + Sync) -> LargePageArray<T>
    where
        T: Send,
    {
        /// The array's first element, shared by the threads that write it.
        struct Start<T>(NonNull<T>);
        // SAFETY: each thread writes elements no other thread writes (below), and `T` may be sent between threads.
        unsafe impl<T: Send> Sync for Start<T> {}
        impl<T> Start<T> {
            /// Where element `i` goes.
            fn at(&self, i: usize) -> *mut T {
                self.0.as_ptr().wrapping_add(i)
            }
        }

        let Some(layout) = Self::layout(len) else { return LargePageArray::default() };
        // SAFETY: the layout's size is not zero (`layout` gives none for an empty array or a zero-sized `T`).
        let Some(start) = NonNull::new(unsafe { alloc(layout) }.cast::<T>()) else { handle_alloc_error(layout) };
        if layout.align() == LARGE_PAGE && ENABLED.load(Ordering::Relaxed) {
            advise_large_pages(start.as_ptr().cast(), layout.size() / LARGE_PAGE * LARGE_PAGE);
        }
        let shared = Start(start);
        // Whole large pages a thread, so that no two threads wait on the same page's first touch.
        let run = (LARGE_PAGE / size_of::<T>()).max(1);
        (0..len).into_par_iter().with_min_len(run).for_each(|i| {
            // SAFETY: `i` is within the allocation of `len` elements, and each is written once, by one thread.
            unsafe { shared.at(i).write(element(i)) };
        });
        LargePageArray { start, len }
    }

    /// How an array of `len` elements is allocated: aligned to [`LARGE_PAGE`] when it fills at least one; none when
    /// nothing needs allocating.
    fn layout(len: usize) -> Option<Layout> {
        let bytes = len.checked_mul(size_of::<T>()).expect("an array's size in bytes fits a usize");
        let align = if bytes >= LARGE_PAGE { LARGE_PAGE } else { align_of::<T>() };
        (bytes > 0).then(|| Layout::from_size_align(bytes, align).expect("a valid array layout"))
    }
}

/// Asks the kernel to map the `bytes` from `start` (a multiple of [`LARGE_PAGE`], from a boundary) with large pages.
/// Only advice: what the memory holds does not depend on it, so a refusal is ignored.
#[cfg(target_os = "linux")]
fn advise_large_pages(start: *mut u8, bytes: usize) {
    // SAFETY: the range lies within one live allocation of ours; MADV_HUGEPAGE changes how it is mapped, not what it
    // holds.
    unsafe { libc::madvise(start.cast(), bytes, libc::MADV_HUGEPAGE) };
}

/// Elsewhere no advice is given.
#[cfg(not(target_os = "linux"))]
fn advise_large_pages(_start: *mut u8, _bytes: usize) {}

impl<T: Copy> Drop for LargePageArray<T> {
    fn drop(&mut self) {
        if let Some(layout) = Self::layout(self.len) {
            // SAFETY: allocated by `from_fn` with this very layout; `T: Copy` has nothing to drop.
            unsafe { dealloc(self.start.as_ptr().cast(), layout) };
        }
    }
}

impl<T: Copy> Default for LargePageArray<T> {
    fn default() -> Self {
        LargePageArray { start: NonNull::dangling(), len: 0 }
    }
}

impl<T: Copy> Deref for LargePageArray<T> {
    type Target = [T];

    fn deref(&self) -> &[T] {
        // SAFETY: `len` initialised elements from `start` (dangling and aligned when there are none).
        unsafe { std::slice::from_raw_parts(self.start.as_ptr(), self.len) }
    }
}

impl<T: Copy + Send + Sync> Clone for LargePageArray<T> {
    fn clone(&self) -> Self {
        LargePageArray::from_fn(self.len, |i| self[i])
    }
}

impl<T: Copy + fmt::Debug> fmt::Debug for LargePageArray<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_list().entries(self.iter()).finish()
    }
}

impl<T: Copy> VecLen for LargePageArray<T> {
    fn len(&self) -> usize {
        self.len
    }

    fn capacity(&self) -> usize {
        self.len
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arrays_hold_what_they_were_made_of_and_large_ones_start_on_a_large_page() {
        for len in [0, 1, 1000, LARGE_PAGE / 8 - 1, LARGE_PAGE / 8, 3 * LARGE_PAGE / 8 + 5] {
            let array = LargePageArray::from_fn(len, |i| i as u64 * 3);
            assert_eq!(array.len(), len);
            assert!(array.iter().enumerate().all(|(i, &v)| v == i as u64 * 3), "{len} elements");
            if len * 8 >= LARGE_PAGE {
                assert_eq!(array.as_ptr() as usize % LARGE_PAGE, 0, "{len} elements");
            }
            let copy = array.clone();
            assert_eq!(&copy[..], &array[..]);
        }
        assert!(LargePageArray::<u64>::default().is_empty());
    }
}
