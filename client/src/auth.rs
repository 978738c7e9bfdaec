//! The metadata sent with calls: the bearer token with every one, and the routing header with those for a scene.

use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::Interceptor;
use tonic::{Request, Status};

use crate::error::{Error, Result};
use crate::route::{ROUTE_HEADER, route_header};

/// Adds `authorization: Bearer <token>` to every request when a token was given, and
/// [`ROUTE_HEADER`]`: <scene>` when the stub is for one scene.
#[derive(Debug, Clone, Default)]
pub struct Auth {
    /// The ready-made header value, checked once at connect time; `None` sends no header.
    header: Option<MetadataValue<Ascii>>,
    /// The routing header's value, so that a proxy hashing it sends the call to the scene's node; `None` sends none.
    route: Option<MetadataValue<Ascii>>,
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
        Ok(Auth { header, route: None })
    }

    /// The same token, with the routing header of accel `accel`'s scene (for an empty name, the scene it had).
    pub fn routed(&self, accel: &str) -> Auth {
        Auth { header: self.header.clone(), route: route_header(accel).or_else(|| self.route.clone()) }
    }
}

impl Interceptor for Auth {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some(header) = &self.header {
            request.metadata_mut().insert("authorization", header.clone());
        }
        if let Some(route) = &self.route {
            request.metadata_mut().insert(ROUTE_HEADER, route.clone());
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
        assert!(request.metadata().get(ROUTE_HEADER).is_none());
        let request = Auth::new(None).unwrap().call(Request::new(())).unwrap();
        assert!(request.metadata().get("authorization").is_none());
        assert_eq!(Auth::new(Some("bad\ntoken")).unwrap_err().code(), tonic::Code::InvalidArgument);
    }

    #[test]
    fn a_routed_stub_names_the_scene_and_keeps_the_token() {
        let auth = Auth::new(Some("s3cret")).unwrap();
        let request = auth.routed("farm.cow").call(Request::new(())).unwrap();
        assert_eq!(request.metadata().get(ROUTE_HEADER).unwrap(), "farm");
        assert_eq!(request.metadata().get("authorization").unwrap(), "Bearer s3cret");
        let request = auth.routed("farm").routed("").call(Request::new(())).unwrap();
        assert_eq!(request.metadata().get(ROUTE_HEADER).unwrap(), "farm", "an empty name keeps the scene");
        let request = auth.routed("farm").routed("barn.1").call(Request::new(())).unwrap();
        assert_eq!(request.metadata().get(ROUTE_HEADER).unwrap(), "barn", "a named accel's scene wins");
        assert!(auth.routed("").call(Request::new(())).unwrap().metadata().get(ROUTE_HEADER).is_none());
    }
}
