//! A tenant's running quotas: operations at once (a counter, taken for the life of a guard), rays per second (a
//! token bucket that may go into debt by one batch, so a batch larger than a second's allowance still runs, and
//! the ones after it wait for the bucket to refill), and what operations in progress will add to what it holds:
//! the buffers being made (uploads, traces into buffers) with their bytes, and the accels of builds, copies and
//! loads with their bytes (reserved for the life of a guard, so that operations at once cannot together outgrow
//! `max_total_buffer_bytes`, `max_buffers`, `max_accels` or `max_total_accel_bytes`).

use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use crate::error::{ServiceError, ServiceResult};

/// The state behind a tenant's quotas.
#[derive(Debug)]
pub struct Quotas {
    /// Operations running now (shared with their guards, which may outlive a borrow: a trace's is held by its job).
    running: Arc<AtomicU32>,
    /// Rays that may still be traced, and when that was computed.
    rays: Mutex<(f64, Instant)>,
    /// Bytes of buffers being made: declared by the uploads in progress, or written by traces into buffers.
    pub buffer_bytes_coming: Pending,
    /// Those buffers.
    pub buffers_coming: Pending,
    /// Accels that builds, copies and loads in progress will add.
    pub accels_coming: Pending,
    /// Bytes those accels will take at most.
    pub accel_bytes_coming: Pending,
}

/// What operations in progress will add to something a tenant holds, reserved against its limit.
#[derive(Debug, Default)]
pub struct Pending(Arc<AtomicU64>);

/// An amount reserved in a [`Pending`]; released when dropped. The operation adds what it made to what the tenant
/// holds before it drops the reservation, so that what it makes is always counted in one or the other.
#[derive(Debug)]
pub struct Reservation {
    /// Where it is reserved.
    pending: Arc<AtomicU64>,
    /// How much.
    amount: u64,
}

impl Reservation {
    /// How much it reserves.
    pub fn amount(&self) -> u64 {
        self.amount
    }
}

impl Drop for Reservation {
    fn drop(&mut self) {
        self.pending.fetch_sub(self.amount, Ordering::AcqRel);
    }
}

impl Pending {
    /// Reserved now.
    pub fn get(&self) -> u64 {
        self.0.load(Ordering::Acquire)
    }

    /// Reserves `amount` when what is held (`held()`), everything reserved and `amount` stay within `allowed`, the
    /// limit called `limit`; otherwise RESOURCE_EXHAUSTED, `what` describing what is counted from the amounts held
    /// and reserved. What is held is read after what is reserved, in the same attempt: an operation that ends in
    /// between (adding what it made to what is held, then releasing its reservation) is then counted at least once.
    pub fn reserve(
        &self,
        amount: u64,
        held: impl Fn() -> u64,
        (limit, allowed): (&'static str, u64),
        what: impl FnOnce(u64, u64) -> String,
    ) -> ServiceResult<Reservation> {
        let mut seen = (0, 0);
        self.0
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |reserved| {
                seen = (held(), reserved);
                (seen.0.saturating_add(reserved).saturating_add(amount) <= allowed).then_some(reserved + amount)
            })
            .map_err(|_| ServiceError::Limit {
                what: what(seen.0, seen.1),
                requested: seen.0.saturating_add(seen.1).saturating_add(amount),
                limit,
                allowed,
            })?;
        Ok(Reservation { pending: Arc::clone(&self.0), amount })
    }
}

/// One running operation; it ends when dropped.
#[derive(Debug)]
pub struct Running {
    /// The counter it holds one of.
    running: Arc<AtomicU32>,
}

impl Drop for Running {
    fn drop(&mut self) {
        self.running.fetch_sub(1, Ordering::AcqRel);
    }
}

impl Quotas {
    /// No operation running; a full second of rays allowed.
    pub fn new(rays_per_second: u64) -> Quotas {
        Quotas {
            running: Arc::default(),
            rays: Mutex::new((rays_per_second as f64, Instant::now())),
            buffer_bytes_coming: Pending::default(),
            buffers_coming: Pending::default(),
            accels_coming: Pending::default(),
            accel_bytes_coming: Pending::default(),
        }
    }

    /// Operations running now.
    pub fn running(&self) -> u32 {
        self.running.load(Ordering::Acquire)
    }

    /// Starts an operation, unless `limit` are running (RESOURCE_EXHAUSTED naming `max_concurrent_operations`).
    pub fn start(&self, limit: u32) -> ServiceResult<Running> {
        let now = self.running.fetch_add(1, Ordering::AcqRel) + 1;
        let running = Running { running: Arc::clone(&self.running) };
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
            // The allowance spent (a second's, and the debt a large batch ran into), and this batch.
            let asked = ((rate - tokens) as u64).saturating_add(rays);
            return Err(ServiceError::Limit {
                what: format!(
                    "rays asked for within a second, this batch's {rays} included (the allowance refills in {:.0} ms)",
                    -tokens / rate * 1e3
                ),
                requested: asked,
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
        // 1,000 rays of the second's allowance and the 4,000 of the debt were spent: with this one, 5,001 (or a few
        // fewer, as the allowance refilled while the test ran).
        let asked: u64 = error.split(": ").nth(1).and_then(|s| s.split(' ').next()?.parse().ok()).expect(&error);
        assert!((4990..=5001).contains(&asked), "{error}");
        assert!(error.contains("this batch's 1 included"), "{error}");
        assert!(quotas.take_rays(u64::MAX, 0).is_ok(), "0 is no limit");
    }

    #[test]
    fn amounts_in_progress_stay_reserved_until_they_end() {
        let pending = Pending::default();
        let limit = ("max_total_buffer_bytes", 100);
        let what = |held, reserved| format!("{held} held, {reserved} being uploaded");
        let first = pending.reserve(60, || 30, limit, what).unwrap();
        let error = pending.reserve(20, || 30, limit, what).unwrap_err().to_string();
        assert!(
            error.contains("30 held, 60 being uploaded") && error.contains("max_total_buffer_bytes = 100"),
            "{error}"
        );
        let second = pending.reserve(10, || 30, limit, what).unwrap();
        assert_eq!(pending.get(), 70);
        drop((first, second));
        assert_eq!(pending.get(), 0);
        pending.reserve(70, || 30, limit, what).unwrap();
        assert_eq!(pending.get(), 0, "a reservation not kept is released at once");
    }

    #[test]
    fn what_is_held_is_read_after_what_is_reserved() {
        // An operation ends while another reserves: the reading of what is held sees the state before it ends, and
        // the ending moves its accel from reserved to held. Read in the other order, neither would count it.
        let pending = Pending::default();
        let limit = ("max_accels", 1);
        let ending = std::cell::RefCell::new(Some(pending.reserve(1, || 0, limit, |_, _| String::new()).unwrap()));
        let held = std::cell::Cell::new(0);
        let read_then_end = || {
            let before = held.get();
            if let Some(reservation) = ending.borrow_mut().take() {
                held.set(1);
                drop(reservation);
            }
            before
        };
        let error = pending.reserve(1, read_then_end, limit, |h, r| format!("{h} held, {r} coming")).unwrap_err();
        assert!(error.to_string().contains("0 held, 1 coming"), "{error}");
        assert_eq!((held.get(), pending.get()), (1, 0));
    }
}
