//! The bearer token sent with every call.

use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::Interceptor;
use tonic::{Request, Status};

use crate::error::{Error, Result};

/// Adds `authorization: Bearer <token>` to every request when a token was given.
#[derive(Debug, Clone, Default)]
pub struct Auth {
    /// The ready-made header value, checked once at connect time; `None` sends no header.
    header: Option<MetadataValue<Ascii>>,
}

impl Auth {
    /// An interceptor for `token` (`None` sends nothing). Fails if the token is not printable ASCII.
    pub fn new(token: Option<&str>) -> Result<Auth> {
        let header = token
            .map(|token| {
                format!("Bearer {token}")
                    .parse()
                    .map_err(|_| Error::InvalidArgument("token: must be printable ASCII".into()))
            })
            .transpose()?;
        Ok(Auth { header })
    }
}

impl Interceptor for Auth {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some(header) = &self.header {
            request.metadata_mut().insert("authorization", header.clone());
        }
        Ok(request)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn token_becomes_a_bearer_header_and_none_sends_nothing() {
        let request = Auth::new(Some("s3cret")).unwrap().call(Request::new(())).unwrap();
        assert_eq!(request.metadata().get("authorization").unwrap(), "Bearer s3cret");
        let request = Auth::new(None).unwrap().call(Request::new(())).unwrap();
        assert!(request.metadata().get("authorization").is_none());
        assert_eq!(Auth::new(Some("bad\ntoken")).unwrap_err().code(), tonic::Code::InvalidArgument);
    }
}
