//! The one place where failures become gRPC statuses.

use rayd_engine::ErrorKind;
use tonic::{Code, Status};

/// Everything a call can fail with.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// The engine refused the request.
    #[error(transparent)]
    Engine(#[from] rayd_engine::Error),
    /// A request field is missing or malformed.
    #[error("{field}: {rule}")]
    Invalid {
        /// The field, as named in the contract (`query.ray_format`).
        field: String,
        /// What is wrong with it.
        rule: String,
    },
    /// An object that does not exist for this tenant.
    #[error("{}{what} {} not found", field_prefix(field, what), quoted(name))]
    NotFound {
        /// `accel`, `buffer` or `device`.
        what: &'static str,
        /// The name, handle or id asked for.
        name: String,
        /// The request's field that named it (`inputs[0].instances.children[2]`), or empty where the object was
        /// not looked up for a field ([`ServiceError::in_field`] adds it).
        field: String,
    },
    /// A name that is taken.
    #[error("{what} {} already exists", quoted(name))]
    AlreadyExists {
        /// `accel` or `buffer`.
        what: &'static str,
        /// The name.
        name: String,
    },
    /// An object in the wrong state for the request (e.g. the product of a stream operation that failed).
    #[error("{0}")]
    Precondition(String),
    /// The gRPC layer refused a message (too large, malformed, or the peer went away); its status is kept.
    #[error("{}", .0.message())]
    Transport(Status),
    /// The data directory could not be written or read; the request changed nothing.
    #[error("{what} in the data directory failed: {source}")]
    Storage {
        /// What was being done (`storing accel "bunny"`).
        what: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The caller went away (its deadline passed, it cancelled, its connection was cut, or the stream whose operation
    /// it was ended) before what the call made was kept, or before the call changed anything: what it says was not
    /// kept or not done.
    #[error("the caller went away: {0}")]
    CallerGone(String),
    /// A bug: something that must not fail did (a panic caught at the edge of a worker's task).
    #[error("internal error: {0}")]
    Internal(String),
    /// A configured limit.
    #[error("{what}: {requested} exceeds limits.{limit} = {allowed}")]
    Limit {
        /// What was asked for.
        what: String,
        /// The amount asked for.
        requested: u64,
        /// The limit's key in the configuration.
        limit: &'static str,
        /// The configured value.
        allowed: u64,
    },
}

impl ServiceError {
    /// The same error, a NOT_FOUND naming the request's field `field` that named the missing object.
    pub fn in_field(self, field: &str) -> Self {
        match self {
            ServiceError::NotFound { what, name, .. } => ServiceError::NotFound { what, name, field: field.into() },
            other => other,
        }
    }

    /// A failure of the data directory.
    pub fn storage(what: String, source: std::io::Error) -> Self {
        ServiceError::Storage { what, source }
    }

    /// A malformed field.
    pub fn invalid(field: impl Into<String>, rule: impl Into<String>) -> Self {
        ServiceError::Invalid { field: field.into(), rule: rule.into() }
    }

    /// Checks `requested <= allowed` for the limit named `limit`.
    pub fn check_limit(
        what: impl FnOnce() -> String,
        requested: u64,
        limit: &'static str,
        allowed: u64,
    ) -> Result<(), Self> {
        if requested > allowed {
            return Err(ServiceError::Limit { what: what(), requested, limit, allowed });
        }
        Ok(())
    }
}

/// The most characters of a request's string that a message shows.
const QUOTED_CHARS: usize = 64;

/// `text` (a name or an id from a request) quoted for a message: whole up to 64 characters, else its first 64 and
/// its length, so that a huge string in a request never makes a huge message (or log line).
pub fn quoted(text: &str) -> String {
    match text.char_indices().nth(QUOTED_CHARS) {
        None => format!("{text:?}"),
        Some((end, _)) => format!("{:?}… ({} bytes)", &text[..end], text.len()),
    }
}

impl From<ServiceError> for Status {
    fn from(error: ServiceError) -> Status {
        let code = match &error {
            ServiceError::Engine(e) => match e.kind() {
                ErrorKind::InvalidArgument => Code::InvalidArgument,
                ErrorKind::NotFound => Code::NotFound,
                ErrorKind::FailedPrecondition => Code::FailedPrecondition,
                ErrorKind::ResourceExhausted => Code::ResourceExhausted,
                ErrorKind::Unavailable => Code::Unavailable,
            },
            ServiceError::Invalid { .. } => Code::InvalidArgument,
            ServiceError::NotFound { .. } => Code::NotFound,
            ServiceError::AlreadyExists { .. } => Code::AlreadyExists,
            ServiceError::Limit { .. } => Code::ResourceExhausted,
            ServiceError::Precondition(_) => Code::FailedPrecondition,
            ServiceError::Transport(status) => status.code(),
            ServiceError::Storage { source, .. } => storage_code(source.kind()),
            ServiceError::CallerGone(_) => Code::Cancelled,
            ServiceError::Internal(_) => Code::Internal,
        };
        Status::new(code, error.to_string())
    }
}

/// `field: ` naming where a missing object of kind `what` was asked for, or nothing for no field or one that the
/// message names anyway (`accel: accel "x" not found` says it twice).
fn field_prefix(field: &str, what: &str) -> String {
    if field.is_empty() || field == what { String::new() } else { format!("{field}: ") }
}

/// The status of a failed read or write of the data directory: full (RESOURCE_EXHAUSTED) and read-only or
/// forbidden (FAILED_PRECONDITION) are the operator's to fix; anything else is INTERNAL.
fn storage_code(kind: std::io::ErrorKind) -> Code {
    use std::io::ErrorKind::*;
    match kind {
        StorageFull | QuotaExceeded | FileTooLarge => Code::ResourceExhausted,
        ReadOnlyFilesystem | PermissionDenied => Code::FailedPrecondition,
        _ => Code::Internal,
    }
}

/// The result type of the service's logic.
pub type ServiceResult<T> = Result<T, ServiceError>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_devices_failures_get_the_codes_the_contract_names() {
        let status = |error: rayd_engine::Error| Status::from(ServiceError::Engine(error));
        let full = status(rayd_engine::Error::DeviceMemory {
            device: "wgpu:0".into(),
            what: "uploading an accel",
            detail: "Out of Memory".into(),
        });
        assert_eq!(full.code(), Code::ResourceExhausted);
        assert_eq!(full.message(), "wgpu:0 ran out of memory uploading an accel: Out of Memory");
        let lost = status(rayd_engine::Error::DeviceLost { device: "wgpu:1".into(), detail: "Unknown: reset".into() });
        assert_eq!(lost.code(), Code::Unavailable);
        assert_eq!(lost.message(), "wgpu:1 was lost (Unknown: reset); the next call opens it anew");
    }
}
