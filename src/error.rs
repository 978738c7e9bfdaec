//! The engine's one error type, and the coarse kinds that the service maps to gRPC status codes.

use thiserror::Error;

/// How a caller should treat an [`Error`]; the service maps each kind to one gRPC status code.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ErrorKind {
    /// The request itself is wrong (bad build input, buffer size, format, option).
    InvalidArgument,
    /// A handle names nothing that exists in this context.
    NotFound,
    /// The request is well formed but the object is in the wrong state for it.
    FailedPrecondition,
    /// A size or count exceeds what can be represented or allocated.
    ResourceExhausted,
    /// The device failed or was lost during the call; the same call may succeed if made again.
    Unavailable,
}

/// Every failure the engine reports. Messages name the field, the element and the rule or limit.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum Error {
    /// A triangle build input breaks a rule.
    #[error("build input {input}: {field}{}: {rule}", element.map(|e| format!("[{e}]")).unwrap_or_default())]
    InvalidBuildInput {
        /// Index of the build input (its geometry id).
        input: usize,
        /// The field of the input, e.g. `vertices` or `indices`.
        field: &'static str,
        /// The offending element (vertex, triangle or byte index), where there is one.
        element: Option<u64>,
        /// The rule that was broken.
        rule: String,
    },
    /// A build option or combination of options is invalid.
    #[error("build options: {0}")]
    InvalidBuildOptions(String),
    /// A query parameter is invalid.
    #[error("{field}: {rule}")]
    InvalidQuery {
        /// The parameter, e.g. `max_hits_per_ray`.
        field: &'static str,
        /// The rule that was broken.
        rule: String,
    },
    /// A ray, hit or count buffer has the wrong byte length for the request.
    #[error("{buffer} buffer: {rule}")]
    BufferSize {
        /// Which buffer: `rays`, `hits` or `counts`.
        buffer: &'static str,
        /// What was expected and what was given.
        rule: String,
    },
    /// A handle that names nothing in this context.
    #[error("{what} {id} not found")]
    NotFound {
        /// What kind of object: `accel` or `buffer`.
        what: &'static str,
        /// The handle's value.
        id: u64,
    },
    /// An operation that the object does not allow in its present state or with its build flags.
    #[error("{0}")]
    FailedPrecondition(String),
    /// A build stopped between its phases because it was told not to go on ([`crate::Context::build_accel_while`]).
    #[error("the build was stopped before it ended")]
    Stopped,
    /// A serialized blob is damaged, truncated or inconsistent (what is wrong, and where).
    #[error("blob: {0}")]
    InvalidBlob(String),
    /// A blob cannot be read by this build: another format version, backend layout or byte order.
    #[error("blob {field} is {found}; this build supports {supported}")]
    IncompatibleBlob {
        /// The header field, e.g. `format version`.
        field: &'static str,
        /// The blob's value.
        found: String,
        /// The value this build reads.
        supported: String,
    },
    /// The external accels given with a blob do not match what it refers to.
    #[error("external accels: {0}")]
    InvalidExternal(String),
    /// A size that overflows what the engine can address.
    #[error("{what} needs {requested} {unit}, beyond the limit of {limit}")]
    TooLarge {
        /// What was being sized.
        what: &'static str,
        /// What `requested` and `limit` count: bytes, rays, records, triangles.
        unit: &'static str,
        /// The requested size (saturated).
        requested: u64,
        /// The largest size allowed.
        limit: u64,
    },
    /// A device had no memory left for what a call needed to make on it.
    #[error("{device} ran out of memory {what}: {detail}")]
    DeviceMemory {
        /// The device, e.g. `wgpu:0`.
        device: String,
        /// What was being made, e.g. `uploading an accel`.
        what: &'static str,
        /// The driver's words.
        detail: String,
    },
    /// Rays needed more node visits and triangle tests than a device lets one ray take.
    #[error(
        "{rays} rays of the trace on {device} were stopped past {limit} node visits and triangle tests each, the most \
         a ray may take there (rayd's {setting}; on the CPU, 16 times it a group of 16 rays traced together): \
         nothing stops a walk from outside once it runs, and a longer one would hold the device, or a worker of it, \
         from every other trace"
    )]
    RayWork {
        /// The device, e.g. `wgpu:0`.
        device: String,
        /// Rays that went over (of the trace's first chunk that had any, on a GPU).
        rays: u64,
        /// Node visits and triangle tests a ray may take.
        limit: u32,
        /// The setting of rayd that sets the limit.
        setting: &'static str,
    },
    /// A device was lost during the call (reset, removed or failed); the next call on it opens it anew.
    #[error("{device} was lost ({detail}); the next call opens it anew")]
    DeviceLost {
        /// The device, e.g. `wgpu:0`.
        device: String,
        /// Why, as the driver reported it.
        detail: String,
    },
}

impl Error {
    /// The coarse kind of this error, for mapping to a status code.
    pub fn kind(&self) -> ErrorKind {
        match self {
            Error::InvalidBuildInput { .. }
            | Error::InvalidBuildOptions(_)
            | Error::InvalidQuery { .. }
            | Error::BufferSize { .. }
            | Error::InvalidBlob(_)
            | Error::InvalidExternal(_) => ErrorKind::InvalidArgument,
            Error::NotFound { .. } => ErrorKind::NotFound,
            Error::FailedPrecondition(_) | Error::IncompatibleBlob { .. } | Error::Stopped => {
                ErrorKind::FailedPrecondition
            }
            Error::TooLarge { .. } | Error::DeviceMemory { .. } | Error::RayWork { .. } => ErrorKind::ResourceExhausted,
            Error::DeviceLost { .. } => ErrorKind::Unavailable,
        }
    }
}

/// The engine's result type.
pub type Result<T, E = Error> = std::result::Result<T, E>;
