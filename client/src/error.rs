//! The client's one error type, and the gRPC code each error reports as.

use tonic::Code;

/// What can go wrong in a client call or a local step before or after it.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The server answered a call with a gRPC status (or the transport under the call failed).
    #[error("{}", .0.message())]
    Status(#[from] tonic::Status),
    /// The server could not be reached or the URL is unusable.
    #[error("cannot connect to {url}: {reason}")]
    Connect {
        /// The URL that was tried.
        url: String,
        /// Why, with every cause in the chain.
        reason: String,
    },
    /// A mesh file could not be read or holds no triangles.
    #[error(transparent)]
    Mesh(#[from] rayd_engine::mesh::LoadError),
    /// A local file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The operating system's reason.
        source: std::io::Error,
    },
    /// The request is wrong before anything is sent (the message names the field and the rule).
    #[error("{0}")]
    InvalidArgument(String),
    /// A buffer the call needs here (rays made on this side, hits or a reduction received) is more than this
    /// process can allocate: refused, where allocating it would abort the process.
    #[error("{what} take {bytes} bytes, more than this process can allocate")]
    Memory {
        /// What the buffer would hold ("the hits of 1000 rays").
        what: String,
        /// Its size (saturated at `u64::MAX`).
        bytes: u64,
    },
    /// The server's answer breaks the contract (a wrong length, chunks out of order).
    #[error("the server broke the contract: {0}")]
    Protocol(String),
    /// A stream operation failed (the server's status for it).
    #[error("operation {operation}: {}", .status.message())]
    Operation {
        /// The operation's id in its stream.
        operation: u64,
        /// Why it failed.
        status: tonic::Status,
    },
    /// Operations of a stream failed since the last synchronize (at least one), in operation order.
    #[error("{} operation(s) failed: {}", .0.len(), .0.iter().map(|(id, s)| format!("operation {id}: {}", s.message())).collect::<Vec<_>>().join("; "))]
    Operations(Vec<(u64, tonic::Status)>),
}

/// The client's result type.
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    /// The gRPC code this error is reported as: the server's own for [`Error::Status`], the nearest one otherwise.
    pub fn code(&self) -> Code {
        match self {
            Error::Status(status) => status.code(),
            Error::Connect { .. } => Code::Unavailable,
            Error::Mesh(_) | Error::InvalidArgument(_) => Code::InvalidArgument,
            Error::Io { source, .. } => match source.kind() {
                std::io::ErrorKind::NotFound => Code::NotFound,
                std::io::ErrorKind::PermissionDenied => Code::PermissionDenied,
                std::io::ErrorKind::StorageFull | std::io::ErrorKind::QuotaExceeded => Code::ResourceExhausted,
                _ => Code::Unknown,
            },
            Error::Memory { .. } => Code::ResourceExhausted,
            Error::Protocol(_) => Code::Internal,
            Error::Operation { status, .. } => status.code(),
            Error::Operations(failed) => failed.first().map_or(Code::Unknown, |(_, status)| status.code()),
        }
    }

    /// An [`Error::Io`] for `path`.
    pub fn io(path: &std::path::Path, source: std::io::Error) -> Error {
        Error::Io { path: path.display().to_string(), source }
    }
}

/// `error` and every error under it, joined with ": " (transport errors keep their detail in the chain); a cause
/// whose text is already there (some errors repeat their source) is left out.
pub(crate) fn chain(error: &dyn std::error::Error) -> String {
    let mut text = error.to_string();
    let mut cause = error.source();
    while let Some(inner) = cause {
        let more = inner.to_string();
        if !text.contains(&more) {
            text.push_str(": ");
            text.push_str(&more);
        }
        cause = inner.source();
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An error with a message and an optional cause.
    #[derive(Debug)]
    struct Layer(&'static str, Option<Box<Layer>>);

    impl std::fmt::Display for Layer {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            f.write_str(self.0)
        }
    }

    impl std::error::Error for Layer {
        fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
            self.1.as_deref().map(|e| e as _)
        }
    }

    #[test]
    fn chain_joins_causes_once_each() {
        let refused = Layer("connection refused", None);
        let error = Layer(
            "transport error",
            Some(Box::new(Layer("tcp connect", Some(Box::new(Layer("tcp connect", Some(Box::new(refused)))))))),
        );
        assert_eq!(chain(&error), "transport error: tcp connect: connection refused");
    }

    #[test]
    fn codes_follow_the_kind_of_failure() {
        assert_eq!(Error::from(tonic::Status::not_found("x")).code(), Code::NotFound);
        assert_eq!(Error::Connect { url: String::new(), reason: String::new() }.code(), Code::Unavailable);
        let missing = std::io::Error::from(std::io::ErrorKind::NotFound);
        assert_eq!(Error::io(std::path::Path::new("f"), missing).code(), Code::NotFound);
        assert_eq!(Error::Protocol(String::new()).code(), Code::Internal);
        assert_eq!(Error::Memory { what: String::new(), bytes: 0 }.code(), Code::ResourceExhausted);
    }
}
