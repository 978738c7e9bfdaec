//! A tenant's running quotas: operations at once (a counter, taken for the life of a guard), rays per second (a
//! token bucket that may go into debt by one batch, so a batch larger than a second's allowance still runs, and
//! the ones after it wait for the bucket to refill), and the bytes that uploads in progress will add to its
//! buffers (reserved for the life of a guard, so that uploads at once cannot outgrow `max_total_buffer_bytes`).

use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use crate::error::{ServiceError, ServiceResult};

/// The state behind a tenant's quotas.
#[derive(Debug)]
pub struct Quotas {
    /// Operations running now.
    running: AtomicU32,
    /// Rays that may still be traced, and when that was computed.
    rays: Mutex<(f64, Instant)>,
    /// Bytes declared by the uploads in progress.
    uploading: Arc<AtomicU64>,
}

/// Bytes reserved for an upload in progress; released when dropped.
#[derive(Debug)]
pub struct Reservation {
    /// The counter they are reserved in.
    uploading: Arc<AtomicU64>,
    /// How many.
    bytes: u64,
}

impl Drop for Reservation {
    fn drop(&mut self) {
        self.uploading.fetch_sub(self.bytes, Ordering::AcqRel);
    }
}

/// One running operation; it ends when dropped.
#[derive(Debug)]
pub struct Running<'a> {
    /// The counter it holds one of.
    running: &'a AtomicU32,
}

impl Drop for Running<'_> {
    fn drop(&mut self) {
        self.running.fetch_sub(1, Ordering::AcqRel);
    }
}

impl Quotas {
    /// No operation running; a full second of rays allowed.
    pub fn new(rays_per_second: u64) -> Quotas {
        Quotas {
            running: AtomicU32::new(0),
            rays: Mutex::new((rays_per_second as f64, Instant::now())),
            uploading: Arc::default(),
        }
    }

    /// Bytes reserved by the uploads in progress.
    pub fn uploading(&self) -> u64 {
        self.uploading.load(Ordering::Acquire)
    }

    /// Reserves `bytes` for an upload when the `held` buffer bytes, every reservation and these stay within
    /// `allowed` (RESOURCE_EXHAUSTED naming `max_total_buffer_bytes` otherwise).
    pub fn reserve_upload(&self, bytes: u64, held: u64, allowed: u64) -> ServiceResult<Reservation> {
        self.uploading
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |uploading| {
                (held.saturating_add(uploading).saturating_add(bytes) <= allowed).then_some(uploading + bytes)
            })
            .map_err(|uploading| ServiceError::Limit {
                what: format!("buffer bytes of this tenant ({held} held, {uploading} being uploaded, {bytes} more)"),
                requested: held.saturating_add(uploading).saturating_add(bytes),
                limit: "max_total_buffer_bytes",
                allowed,
            })?;
        Ok(Reservation { uploading: Arc::clone(&self.uploading), bytes })
    }

    /// Operations running now.
    pub fn running(&self) -> u32 {
        self.running.load(Ordering::Acquire)
    }

    /// Starts an operation, unless `limit` are running (RESOURCE_EXHAUSTED naming `max_concurrent_operations`).
    pub fn start(&self, limit: u32) -> ServiceResult<Running<'_>> {
        let now = self.running.fetch_add(1, Ordering::AcqRel) + 1;
        let running = Running { running: &self.running };
        ServiceError::check_limit(
            || "operations running at once".into(),
            u64::from(now),
            "max_concurrent_operations",
            u64::from(limit),
        )?;
        Ok(running)
    }

    /// Takes `rays` from the allowance of `per_second` rays a second (0: no limit); RESOURCE_EXHAUSTED naming
    /// `max_rays_per_second` while the allowance is spent.
    pub fn take_rays(&self, rays: u64, per_second: u64) -> ServiceResult<()> {
        if per_second == 0 {
            return Ok(());
        }
        let mut bucket = self.rays.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let (tokens, since) = *bucket;
        let now = Instant::now();
        let rate = per_second as f64;
        let tokens = (tokens + now.duration_since(since).as_secs_f64() * rate).min(rate);
        if tokens <= 0.0 {
            *bucket = (tokens, now);
            return Err(ServiceError::Limit {
                what: format!("rays this second (the allowance refills in {:.0} ms)", -tokens / rate * 1e3),
                requested: rays,
                limit: "max_rays_per_second",
                allowed: per_second,
            });
        }
        *bucket = (tokens - rays as f64, now);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn operations_are_counted_while_they_run_and_rays_run_into_debt_once() {
        let quotas = Quotas::new(1000);
        let first = quotas.start(2).unwrap();
        let second = quotas.start(2).unwrap();
        let error = quotas.start(2).unwrap_err().to_string();
        assert!(error.contains("max_concurrent_operations = 2"), "{error}");
        drop((first, second));
        quotas.start(2).unwrap();
        quotas.take_rays(5000, 1000).unwrap();
        let error = quotas.take_rays(1, 1000).unwrap_err().to_string();
        assert!(error.contains("max_rays_per_second = 1000"), "{error}");
        assert!(quotas.take_rays(u64::MAX, 0).is_ok(), "0 is no limit");
    }

    #[test]
    fn uploads_in_progress_reserve_their_bytes_until_they_end() {
        let quotas = Quotas::new(0);
        let first = quotas.reserve_upload(60, 30, 100).unwrap();
        let error = quotas.reserve_upload(20, 30, 100).unwrap_err().to_string();
        assert!(error.contains("60 being uploaded") && error.contains("max_total_buffer_bytes = 100"), "{error}");
        let second = quotas.reserve_upload(10, 30, 100).unwrap();
        assert_eq!(quotas.uploading(), 70);
        drop((first, second));
        assert_eq!(quotas.uploading(), 0);
        quotas.reserve_upload(70, 30, 100).unwrap();
    }
}
