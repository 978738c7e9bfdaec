//! Arrays that a traversal reads at random places (the wide nodes, the corner blocks, the blocks' triangle ids), placed
//! so that Linux can back them with 2 MiB pages: each incoherent ray touches a few lines of each of several pages, and
//! with 4 KiB pages a large accel's pages are far more than the CPU's address-translation caches hold, so that most
//! node and block reads also wait for a page-table walk (BENCHMARKS.md, "A random ray against Embree's, visit by
//! visit; and the traversal's arrays on large pages").
//!
//! The arrays of one accel lie one after another in one allocation (`LargePages`), so that only the last of them ends
//! on ordinary pages: a bunny-sized accel's 0.85 MB of nodes, which alone would not fill a large page, share one with
//! its blocks; and copies of the arrays share the allocation, which makes the copy a refit starts from free
//! (BENCHMARKS.md, "2026-11-29: refits had slowed below the goal…"). An allocation of at least [`LARGE_PAGE`] bytes
//! starts on a 2 MiB boundary and its whole 2 MiB stretches are marked `MADV_HUGEPAGE` before anything is written to
//! them, so that their first touch maps large pages wherever the kernel's transparent huge pages are `always` or
//! `madvise` (the common default) and memory allows; the rest of it (less than 2 MiB) and smaller allocations use
//! ordinary pages, so no memory is spent beyond what the arrays hold. Where the kernel offers no large pages (another
//! OS, `never`, fragmented memory) the same arrays work with small ones. [`set_enabled`] turns the advice off for
//! allocations made afterwards.

use std::alloc::{Layout, alloc, dealloc, handle_alloc_error};
use std::fmt;
use std::ops::Deref;
use std::ptr::NonNull;
use std::sync::Arc;
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

/// Bytes planned for the arrays of one [`LargePages`] allocation: each array starts at the next multiple of its
/// element's alignment after the one before it.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Room {
    /// Bytes up to the end of the last array planned.
    bytes: usize,
    /// The largest alignment an array planned needs.
    align: usize,
}

impl Room {
    /// Room for `len` more elements of `T`, after the arrays planned so far.
    pub fn and<T>(self, len: usize) -> Room {
        let bytes = len.checked_mul(size_of::<T>()).expect("an array's size in bytes fits a usize");
        let start = self.bytes.next_multiple_of(align_of::<T>());
        Room {
            bytes: start.checked_add(bytes).expect("arrays' sizes in bytes fit a usize"),
            align: self.align.max(align_of::<T>()),
        }
    }

    /// How the allocation is laid out: aligned to [`LARGE_PAGE`] when it fills at least one; none when there is
    /// nothing to allocate.
    fn layout(self) -> Option<Layout> {
        let align = if self.bytes >= LARGE_PAGE { LARGE_PAGE } else { self.align };
        (self.bytes > 0).then(|| Layout::from_size_align(self.bytes, align).expect("a valid allocation layout"))
    }
}

/// One allocation, freed when the last array in it is dropped.
#[derive(Debug)]
struct Allocation {
    /// Its first byte.
    start: NonNull<u8>,
    /// How it was allocated.
    layout: Layout,
}

// SAFETY: the allocation is plain memory; who reads and writes it is up to the arrays, which own their parts.
unsafe impl Send for Allocation {}
// SAFETY: as above.
unsafe impl Sync for Allocation {}

impl Drop for Allocation {
    fn drop(&mut self) {
        // SAFETY: allocated by `LargePages::new` with this very layout; the arrays in it hold `Copy` elements only.
        unsafe { dealloc(self.start.as_ptr(), self.layout) };
    }
}

/// One allocation, laid out for large pages (see the module's documentation), that arrays are made in one after
/// another, as planned by a [`Room`].
pub(super) struct LargePages {
    /// The allocation; `None` when the room planned is empty.
    allocation: Option<Arc<Allocation>>,
    /// Bytes taken by the arrays made so far.
    used: usize,
    /// Bytes planned.
    room: usize,
}

impl LargePages {
    /// Allocates `room` and asks for large pages for it.
    pub fn new(room: Room) -> LargePages {
        let allocation = room.layout().map(|layout| {
            // SAFETY: the layout's size is not zero (`Room::layout` gives none for an empty room).
            let Some(start) = NonNull::new(unsafe { alloc(layout) }) else { handle_alloc_error(layout) };
            if layout.align() == LARGE_PAGE && ENABLED.load(Ordering::Relaxed) {
                advise_large_pages(start.as_ptr(), layout.size() / LARGE_PAGE * LARGE_PAGE);
            }
            Arc::new(Allocation { start, layout })
        });
        LargePages { allocation, used: 0, room: room.bytes }
    }

    /// The next array of the room: `len` elements, element `i` being `element(i)`, written by rayon's threads, a
    /// large page's worth of neighbours at least each (an accel's arrays are made once a build: the writes, and the
    /// kernel's zeroing of the pages they touch first, spread over the cores).
    ///
    /// Panics when the room planned has no such array left.
    pub fn array_from_fn<T: Copy + Send>(
        &mut self,
        len: usize,
        element: impl Fn(usize) -> T + Sync,
    ) -> LargePageArray<T> {
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

        let room = Room { bytes: self.used, align: 1 }.and::<T>(len);
        assert!(room.bytes <= self.room, "{} bytes of arrays in a room of {}", room.bytes, self.room);
        let offset = room.bytes - len * size_of::<T>();
        self.used = room.bytes;
        let Some(allocation) = self.allocation.as_ref().filter(|_| len > 0 && size_of::<T>() > 0) else {
            return LargePageArray::default();
        };
        // SAFETY: `offset` lies within the allocation (the room holds the array), a multiple of `T`'s alignment from
        // a start aligned to the largest alignment planned (`Room::and`).
        let start = unsafe { allocation.start.add(offset) }.cast::<T>();
        let shared = Start(start);
        // Whole large pages a thread, so that no two threads wait on the same page's first touch.
        let run = (LARGE_PAGE / size_of::<T>()).max(1);
        (0..len).into_par_iter().with_min_len(run).for_each(|i| {
            // SAFETY: `i` is within the array's part of the allocation, which no other array has, and each element
            // is written once, by one thread.
            unsafe { shared.at(i).write(element(i)) };
        });
        LargePageArray { start, len, _allocation: Some(Arc::clone(allocation)) }
    }
}

/// A fixed-length array of `T` in a [`LargePages`] allocation, alone or with others; otherwise a boxed slice. A copy
/// shares the elements (they are never written again).
pub(super) struct LargePageArray<T: Copy> {
    /// The first element; dangling when the array is empty.
    start: NonNull<T>,
    /// Elements.
    len: usize,
    /// The allocation the elements lie in; `None` when the array is empty.
    _allocation: Option<Arc<Allocation>>,
}

// SAFETY: the array owns its elements as a `Box<[T]>` would, and only reads them once made.
unsafe impl<T: Copy + Send> Send for LargePageArray<T> {}
// SAFETY: shared access only reads the elements.
unsafe impl<T: Copy + Sync> Sync for LargePageArray<T> {}

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

impl<T: Copy> Default for LargePageArray<T> {
    fn default() -> Self {
        LargePageArray { start: NonNull::dangling(), len: 0, _allocation: None }
    }
}

impl<T: Copy> Deref for LargePageArray<T> {
    type Target = [T];

    fn deref(&self) -> &[T] {
        // SAFETY: `len` initialised elements from `start` (dangling and aligned when there are none).
        unsafe { std::slice::from_raw_parts(self.start.as_ptr(), self.len) }
    }
}

impl<T: Copy> Clone for LargePageArray<T> {
    fn clone(&self) -> Self {
        LargePageArray { start: self.start, len: self.len, _allocation: self._allocation.clone() }
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
            let array = LargePages::new(Room::default().and::<u64>(len)).array_from_fn(len, |i| i as u64 * 3);
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

    #[test]
    fn arrays_made_together_lie_one_after_another_aligned_and_keep_their_elements() {
        // A large page's worth and more of three arrays of different sizes and alignments, the middle one odd.
        let (wide, odd, small) = (LARGE_PAGE / 64 + 3, 1001, 77);
        let room = Room::default().and::<[u64; 8]>(wide).and::<[u8; 3]>(odd).and::<u32>(small);
        let mut pages = LargePages::new(room);
        let first = pages.array_from_fn(wide, |i| [i as u64; 8]);
        let second = pages.array_from_fn(odd, |i| [i as u8; 3]);
        let third = pages.array_from_fn(small, |i| i as u32 * 7);
        assert_eq!(first.as_ptr() as usize % LARGE_PAGE, 0, "the allocation starts on a large page");
        let end_of = |start: usize, bytes: usize| start + bytes;
        assert_eq!(second.as_ptr() as usize, end_of(first.as_ptr() as usize, wide * 64));
        assert_eq!(third.as_ptr() as usize, end_of(second.as_ptr() as usize, odd * 3).next_multiple_of(4));
        // Dropping one array leaves the others' elements as they were made.
        let copy = third.clone();
        drop((first, third));
        assert!(second.iter().enumerate().all(|(i, &v)| v == [i as u8; 3]));
        assert!(copy.iter().enumerate().all(|(i, &v)| v == i as u32 * 7));
    }

    #[test]
    #[should_panic(expected = "bytes of arrays in a room of")]
    fn an_array_beyond_the_room_planned_is_refused() {
        let mut pages = LargePages::new(Room::default().and::<u32>(4));
        let _fits = pages.array_from_fn(4, |i| i as u32);
        let _beyond = pages.array_from_fn(1, |i| i as u32);
    }
}
