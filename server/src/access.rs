//! Who is calling: the tenant and role that a request's API key names (`authorization: Bearer <key>`, compared in
//! constant time with every configured key), or the single default tenant of a server without configured tenants;
//! and the refusal of calls beyond a key's role.

use std::sync::Arc;

use subtle::ConstantTimeEq;
use tonic::{Request, Status};

use crate::config::Role;
use crate::tenant::Tenant;

/// The tenants of a server and how callers reach them.
#[derive(Debug)]
pub struct Tenants {
    /// Every configured key, with its role and tenant.
    keys: Vec<(String, Role, Arc<Tenant>)>,
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

    /// The tenant `request` acts for, if its key's role allows `call`, which needs `needs`: UNAUTHENTICATED
    /// without a key or with an unknown one, PERMISSION_DENIED when the role is not enough.
    pub fn caller<T>(&self, request: &Request<T>, call: &str, needs: Role) -> Result<Arc<Tenant>, Status> {
        if let Some(tenant) = &self.open {
            return Ok(Arc::clone(tenant));
        }
        let header = request.metadata().get("authorization").and_then(|v| v.to_str().ok());
        let Some(presented) = header.and_then(|h| h.strip_prefix("Bearer ")) else {
            return Err(Status::unauthenticated("authorization: an `authorization: Bearer <key>` header is required"));
        };
        // Every key is compared, whichever matches, so the time taken says nothing about the keys.
        let mut found = None;
        for (key, role, tenant) in &self.keys {
            if bool::from(key.as_bytes().ct_eq(presented.as_bytes())) {
                found = Some((*role, tenant));
            }
        }
        let Some((role, tenant)) = found else {
            return Err(Status::unauthenticated("authorization: the key is not known"));
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
