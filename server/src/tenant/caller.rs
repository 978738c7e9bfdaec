//! Whether the caller of a call that makes something is still there to take it.

use tokio_util::sync::{CancellationToken, DropGuard};

use crate::error::{ServiceError, ServiceResult};

/// The caller of a build, copy, load, update or save: gone once its call has ended without the answer (its deadline
/// passed, it cancelled, its connection was cut, or the stream whose operation it was was cancelled). What is made
/// for a caller that has gone is not kept, and work not yet started for it is not started. The default caller never
/// goes.
#[derive(Debug, Clone, Default)]
pub struct Caller(CancellationToken);

impl Caller {
    /// A caller that is there until the guard returned with it is dropped: the call's future holds the guard, so the
    /// caller goes when the server drops the call.
    pub fn watched() -> (Caller, DropGuard) {
        let token = CancellationToken::new();
        (Caller(token.clone()), token.drop_guard())
    }

    /// Whether the caller is still there (a long build asks between its phases).
    pub fn is_there(&self) -> bool {
        !self.0.is_cancelled()
    }

    /// [`ServiceError::CallerGone`] saying what was not kept or not done (`accel "bunny" was not kept`) once the
    /// caller has gone.
    pub fn check(&self, not_done: impl FnOnce() -> String) -> ServiceResult<()> {
        if !self.is_there() {
            let not_done = not_done();
            tracing::info!(not_done, "the caller went away");
            return Err(ServiceError::CallerGone(not_done));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_caller_goes_when_its_guard_is_dropped() {
        let (caller, present) = Caller::watched();
        assert!(caller.check(|| "accel \"a\" was not kept".into()).is_ok());
        drop(present);
        let gone = caller.check(|| "accel \"a\" was not kept".into()).unwrap_err();
        let status = tonic::Status::from(gone);
        assert_eq!(status.code(), tonic::Code::Cancelled);
        assert_eq!(status.message(), "the caller went away: accel \"a\" was not kept");
        assert!(Caller::default().check(String::new).is_ok(), "the default caller never goes");
    }
}
