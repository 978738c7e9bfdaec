//! The metrics recorder `rayd` installs must not keep what it records: Prometheus' exporter holds every histogram
//! sample until an upkeep folds it into its buckets, and a server that nobody scrapes grew by every call it answered
//! (issue 13's hour soak: +152 MiB). This test counts the bytes the process holds, records a million latencies
//! through the recorder `rayd_server::run` installed, and expects the upkeep to give them back.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// The system allocator, counting the bytes held.
struct Counting;

static HELD: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        HELD.fetch_add(layout.size(), Ordering::Relaxed);
        // SAFETY: the caller's contract is passed on unchanged.
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        HELD.fetch_sub(layout.size(), Ordering::Relaxed);
        // SAFETY: the caller's contract is passed on unchanged.
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// A mebibyte.
const MIB: usize = 1 << 20;

#[tokio::test]
async fn recorded_latencies_are_folded_into_buckets_and_their_memory_given_back() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    tokio::spawn(rayd_server::run(rayd_server::Config::default(), listener, None, std::future::pending()));
    // `run` installs the recorder as it starts: give it a moment.
    tokio::time::sleep(Duration::from_secs(1)).await;

    let before = HELD.load(Ordering::Relaxed);
    let latency = metrics::histogram!("rayd_request_duration_seconds", "method" => "Test", "tenant" => "test");
    for i in 0..1_000_000u32 {
        latency.record(f64::from(i % 1000) * 1e-6);
    }
    let recorded = HELD.load(Ordering::Relaxed);
    assert!(recorded >= before + 4 * MIB, "a million samples held: {} bytes more", recorded - before);

    // While calls go on (a trickle of samples: the recorder frees drained samples once later recordings move its
    // epoch on), a few upkeep periods give them back.
    let start = Instant::now();
    let mut held = recorded;
    while held > before + MIB && start.elapsed() < Duration::from_secs(30) {
        tokio::time::sleep(Duration::from_millis(10)).await;
        for _ in 0..100 {
            latency.record(1e-4);
        }
        held = HELD.load(Ordering::Relaxed);
    }
    assert!(
        held <= before + MIB,
        "{:.1} MiB still held 30 s after recording a million samples ({:.1} MiB at most, {:.1} MiB before)",
        held as f64 / MIB as f64,
        (before + MIB) as f64 / MIB as f64,
        before as f64 / MIB as f64
    );
}
