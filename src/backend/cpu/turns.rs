//! Incoherent rays walked in turns through a static accel larger than the CPU's last-level cache: each ray of a
//! group takes one step of its walk at a time (up to the next node or leaf it enters, whose data its step only just
//! asked for), then the next ray does, so that the memory one ray waits for arrives while the others work, instead of
//! the core standing still. Each ray's walk is [`super::wide::Tree::walk_lanes`]'s, visit for visit (the same
//! boxes in the same order, the same leaves, the same pruning), so its answer and the statistics are those of walking
//! the rays one after another; only the interleaving differs.
//!
//! Turns cost instructions (each step reloads its ray's state: about a fifth more a ray), which pays only where the
//! walk waits on memory rather than on the caches: an accel that does not fit the last-level cache. With one that
//! fits, they lost up to 11% on a 16-core Xeon and 25% on a 2-vCPU AMD EPYC (a scene of uneven triangles); with one
//! that does not, they gained 10–45% on the Xeon (16 threads to 1) and 16–31% on the EPYC (BENCHMARKS.md,
//! "Incoherent rays walked in turns").

use std::sync::OnceLock;
#[cfg(target_arch = "x86_64")]
pub(super) use walk::TURNS;

/// Whether a static accel has its incoherent rays walked in turns: when its traversal arrays exceed the CPU's
/// last-level cache ([`exceed_last_level_cache`]). `RAYD_CPU_TRAVERSAL=turns` or `alone`, read once, sets it for
/// every accel, for A/B benchmarks.
pub(super) fn walks_in_turns(exceeding_cache: bool) -> bool {
    static FORCED: OnceLock<Option<bool>> = OnceLock::new();
    let forced = FORCED.get_or_init(|| match std::env::var("RAYD_CPU_TRAVERSAL").as_deref() {
        Ok("turns") => Some(true),
        Ok("alone") => Some(false),
        _ => None,
    });
    forced.unwrap_or(exceeding_cache)
}

/// Whether traversal arrays (wide nodes and corner blocks) of `bytes` are larger than the CPU's last-level cache
/// (read from Linux's sysfs once; where it cannot be read, never).
pub(super) fn exceed_last_level_cache(bytes: u64) -> bool {
    last_level_cache_bytes().is_some_and(|cache| bytes > cache)
}

/// Bytes of the largest cache of CPU 0, the last level, as Linux reports it.
fn last_level_cache_bytes() -> Option<u64> {
    static BYTES: OnceLock<Option<u64>> = OnceLock::new();
    *BYTES.get_or_init(|| {
        let caches = std::fs::read_dir("/sys/devices/system/cpu/cpu0/cache").ok()?;
        caches
            .filter_map(|entry| std::fs::read_to_string(entry.ok()?.path().join("size")).ok())
            .filter_map(|size| cache_size(&size))
            .max()
    })
}

/// A sysfs cache size (`32K`, `32768K`, `300M`) in bytes.
fn cache_size(text: &str) -> Option<u64> {
    let text = text.trim();
    let (digits, unit) = text.split_at(text.find(|c: char| !c.is_ascii_digit()).unwrap_or(text.len()));
    let scale = match unit {
        "" => 1,
        "K" => 1 << 10,
        "M" => 1 << 20,
        "G" => 1 << 30,
        _ => return None,
    };
    digits.parse::<u64>().ok()?.checked_mul(scale)
}

#[cfg(target_arch = "x86_64")]
mod walk;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cache_sizes_read_as_sysfs_writes_them() {
        assert_eq!(cache_size("32K\n"), Some(32 << 10));
        assert_eq!(cache_size("32768K"), Some(32 << 20));
        assert_eq!(cache_size("300M"), Some(300 << 20));
        assert_eq!(cache_size("1G"), Some(1 << 30));
        assert_eq!(cache_size("4096"), Some(4096));
        assert_eq!(cache_size(""), None);
        assert_eq!(cache_size("12X"), None);
        assert_eq!(cache_size("K"), None);
    }
}
