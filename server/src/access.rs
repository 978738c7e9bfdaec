//! Who is calling: the tenant and role that a request's API key names (`authorization: Bearer <key>`, its SHA-256
//! digest compared in constant time with every configured key's), or the single default tenant of a server without
//! configured tenants; and the refusal of calls without a known key, before their messages are read, and of calls
//! beyond a key's role.

use std::sync::Arc;

use ring::digest::{SHA256, digest};
use subtle::ConstantTimeEq;
use tonic::{Request, Status};

use crate::config::Role;
use crate::tenant::Tenant;

/// A key's SHA-256 digest: keys of any length are compared as 32 bytes, so the time a comparison takes says nothing
/// of the configured keys' lengths either.
type KeyDigest = [u8; 32];

/// The digest of `key`.
fn key_digest(key: &str) -> KeyDigest {
    digest(&SHA256, key.as_bytes()).as_ref().try_into().expect("SHA-256 digests are 32 bytes")
}

/// The key of an `authorization` value of the Bearer scheme (its name in any case, as HTTP's schemes are), the spaces
/// after the name skipped; none for another scheme or no key.
fn bearer_key(value: &str) -> Option<&str> {
    let (scheme, key) = value.split_once(' ')?;
    let key = key.trim_start_matches(' ');
    (scheme.eq_ignore_ascii_case("bearer") && !key.is_empty()).then_some(key)
}

/// The role and tenant that [`Tenants::admit`] found for a call's key.
#[derive(Debug, Clone)]
struct Admitted(Role, Arc<Tenant>);

/// The tenants of a server and how callers reach them.
#[derive(Debug)]
pub struct Tenants {
    /// Every configured key's digest, with its role and tenant.
    keys: Vec<(KeyDigest, Role, Arc<Tenant>)>,
    /// Without configured tenants: the one tenant every caller acts for, with every role.
    open: Option<Arc<Tenant>>,
}

impl Tenants {
    /// One tenant, no authentication.
    pub fn open(tenant: Arc<Tenant>) -> Tenants {
        Tenants { keys: Vec::new(), open: Some(tenant) }
    }

    /// Configured tenants, reached by their keys.
    pub fn with_keys(keys: Vec<(String, Role, Arc<Tenant>)>) -> Tenants {
        let keys = keys.into_iter().map(|(key, role, tenant)| (key_digest(&key), role, tenant)).collect();
        Tenants { keys, open: None }
    }

    /// Every tenant, once each, in configuration order.
    pub fn all(&self) -> Vec<Arc<Tenant>> {
        let mut all: Vec<Arc<Tenant>> = self.open.iter().cloned().collect();
        for (_, _, tenant) in &self.keys {
            if !all.iter().any(|t| Arc::ptr_eq(t, tenant)) {
                all.push(Arc::clone(tenant));
            }
        }
        all
    }

    /// Lets a call through to its handler only with a known key (any role; every call without configured
    /// tenants): the interceptor ahead of the service, which sees the call's metadata before its messages are
    /// received, decompressed or decoded, so that a caller without a key spends none of the server's memory.
    /// What it found rides on with the request ([`Admitted`]), so that the handler's [`Tenants::caller`] does not
    /// look the key up again.
    pub fn admit(&self, mut request: Request<()>) -> Result<Request<()>, Status> {
        let (role, tenant) = self.authenticate(&request)?;
        let admitted = Admitted(role, Arc::clone(tenant));
        request.extensions_mut().insert(admitted);
        Ok(request)
    }

    /// The role and tenant of `request`'s key (every role, the default tenant, without configured tenants):
    /// UNAUTHENTICATED without a key or with an unknown one.
    fn authenticate<T>(&self, request: &Request<T>) -> Result<(Role, &Arc<Tenant>), Status> {
        if let Some(tenant) = &self.open {
            return Ok((Role::Admin, tenant));
        }
        let header = request.metadata().get("authorization").and_then(|v| v.to_str().ok());
        let Some(presented) = header.and_then(bearer_key) else {
            return Err(Status::unauthenticated("authorization: an `authorization: Bearer <key>` header is required"));
        };
        let presented = key_digest(presented);
        // Every key is compared, whichever matches, so the time taken says nothing about the keys.
        let mut found = None;
        for (key, role, tenant) in &self.keys {
            if bool::from(key.ct_eq(&presented)) {
                found = Some((*role, tenant));
            }
        }
        found.ok_or_else(|| Status::unauthenticated("authorization: the key is not known"))
    }

    /// The tenant `request` acts for, if its key's role allows `call`, which needs `needs`: UNAUTHENTICATED
    /// without a key or with an unknown one, PERMISSION_DENIED when the role is not enough.
    pub fn caller<T>(&self, request: &Request<T>, call: &str, needs: Role) -> Result<Arc<Tenant>, Status> {
        // Admitted by the interceptor (extensions never come from the wire), or, for a request that did not pass it,
        // looked up here.
        let (role, tenant) = match request.extensions().get::<Admitted>() {
            Some(Admitted(role, tenant)) => (*role, tenant),
            None => self.authenticate(request)?,
        };
        if role < needs {
            return Err(Status::permission_denied(format!(
                "{call} needs a {} key; this key's role is {}",
                needs.name(),
                role.name()
            )));
        }
        Ok(Arc::clone(tenant))
    }
}
