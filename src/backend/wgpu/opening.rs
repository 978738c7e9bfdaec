//! When an adapter's device is opened: on first use, anew after it was lost, and again after a refusal once
//! [`REFUSAL_KEPT`] has passed. The rules apart from wgpu, so that they are tested without a GPU.

use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::error::{Error, Result};

/// How long an adapter's refusal to open a device is given to every call before the next call tries again. A
/// refusal may last (an adapter that cannot take the kernel) or pass (the GPU's memory held by another process when
/// rayd first used it); trying again at most this often keeps a lasting one cheap and lets a passing one heal
/// without a restart. The call that tries again opens the device under the adapter's lock: other calls on the
/// adapter wait for it, as they wait for a first opening.
pub const REFUSAL_KEPT: Duration = Duration::from_secs(30);

/// An adapter's device `D`: not opened yet, opened (and perhaps lost since), or refused.
#[derive(Debug, Default)]
pub(super) enum Opening<D> {
    /// Not opened yet.
    #[default]
    Unopened,
    /// Opened.
    Open(Arc<D>),
    /// The adapter refused the device at `at`.
    Refused { error: Error, at: Instant },
}

impl<D> Opening<D> {
    /// The device: the open one unless `lost` says why it was lost, else opened now by `open`. A refusal is given
    /// again until [`REFUSAL_KEPT`] has passed since it, then `open` tries again. A failure to replace a lost device
    /// is UNAVAILABLE naming the loss, and the next call tries again at once (the device was working).
    pub fn get(
        &mut self,
        now: Instant,
        lost: impl FnOnce(&D) -> Option<String>,
        open: impl FnOnce() -> Result<D>,
        name: impl FnOnce() -> String,
    ) -> Result<Arc<D>> {
        let lost = match self {
            Opening::Unopened => None,
            Opening::Refused { error, at } if now.duration_since(*at) < REFUSAL_KEPT => return Err(error.clone()),
            Opening::Refused { .. } => None,
            Opening::Open(current) => match lost(current) {
                None => return Ok(Arc::clone(current)),
                Some(why) => Some(why),
            },
        };
        let Some(why) = lost else {
            let opened = open().map(Arc::new);
            *self = match &opened {
                Ok(device) => Opening::Open(Arc::clone(device)),
                Err(refused) => Opening::Refused { error: refused.clone(), at: now },
            };
            return opened;
        };
        let name = name();
        tracing::warn!(device = name, why, "the device was lost: opening it anew");
        let fresh = Arc::new(open().map_err(|refused| Error::DeviceLost {
            device: name,
            detail: format!("{why}; opening it anew failed: {refused}"),
        })?);
        *self = Opening::Open(Arc::clone(&fresh));
        Ok(fresh)
    }
}

#[cfg(test)]
mod tests {
    use std::cell::Cell;

    use super::*;
    use crate::error::ErrorKind;

    /// A stand-in device: the number of its opening, and why it was lost (if it was).
    #[derive(Debug)]
    struct Fake {
        opening: u32,
        lost: Option<&'static str>,
    }

    /// Opens stand-ins, counting the openings, or refuses.
    struct Adapter {
        openings: Cell<u32>,
        refuse: Cell<bool>,
    }

    impl Adapter {
        fn get(&self, state: &mut Opening<Fake>, now: Instant, lost: Option<&'static str>) -> Result<Arc<Fake>> {
            let open = || {
                self.openings.set(self.openings.get() + 1);
                if self.refuse.get() {
                    return Err(Error::FailedPrecondition("wgpu:0: opening the device failed: out of memory".into()));
                }
                Ok(Fake { opening: self.openings.get(), lost: None })
            };
            state.get(now, |device| device.lost.or(lost).map(str::to_string), open, || "wgpu:0".into())
        }
    }

    #[test]
    fn a_refusal_is_given_again_until_it_has_been_kept_then_the_adapter_is_asked_again() {
        let adapter = Adapter { openings: Cell::new(0), refuse: Cell::new(true) };
        let mut state = Opening::default();
        let start = Instant::now();
        let refused = adapter.get(&mut state, start, None).unwrap_err();
        assert_eq!(refused.kind(), ErrorKind::FailedPrecondition, "{refused}");
        let again = adapter.get(&mut state, start + REFUSAL_KEPT / 2, None).unwrap_err();
        assert_eq!(again.to_string(), refused.to_string());
        assert_eq!(adapter.openings.get(), 1, "the refusal was kept, the adapter not asked again");
        adapter.refuse.set(false);
        let opened = adapter.get(&mut state, start + REFUSAL_KEPT, None).expect("asked again: opened");
        assert_eq!((opened.opening, adapter.openings.get()), (2, 2));
        let shared = adapter.get(&mut state, start + 2 * REFUSAL_KEPT, None).unwrap();
        assert!(Arc::ptr_eq(&opened, &shared), "the open device is shared, not opened again");
    }

    #[test]
    fn a_lost_device_is_opened_anew_and_a_failure_to_is_tried_again_at_once() {
        let adapter = Adapter { openings: Cell::new(0), refuse: Cell::new(false) };
        let mut state = Opening::default();
        let now = Instant::now();
        assert_eq!(adapter.get(&mut state, now, None).unwrap().opening, 1);
        adapter.refuse.set(true);
        let failed = adapter.get(&mut state, now, Some("Hung")).unwrap_err();
        assert_eq!(failed.kind(), ErrorKind::Unavailable, "{failed}");
        assert!(failed.to_string().contains("Hung; opening it anew failed"), "{failed}");
        adapter.refuse.set(false);
        let fresh = adapter.get(&mut state, now, Some("Hung")).expect("tried again at once");
        assert_eq!(fresh.opening, 3);
        assert_eq!(adapter.get(&mut state, now, None).unwrap().opening, 3, "the fresh device is kept");
    }
}
