//! Tenants in the configuration: each with its API keys (Bearer tokens), each key with a role, and optionally its
//! own limits (keys it does not set take the server's `[limits]`).
//!
//! ```toml
//! [[tenants]]
//! name = "acme"
//! keys = [
//!   { key = "acme-pipeline-2f9c0d1e7b6a", role = "write" },
//!   { key = "acme-renderer-8e1a44c09d3f", role = "read" },
//! ]
//! share = 2
//! limits = { max_accels = 100 }
//! ```

use serde::{Deserialize, Serialize};

use super::Limits;

/// The shortest API key accepted.
pub const MIN_KEY_CHARS: usize = 16;

/// What a key may do. Each role may do what the ones before it may.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// Read and trace: list, get, download, trace (into replies or new buffers of its own).
    Read,
    /// Also build, update, copy, destroy, upload, delete, save, load, and open streams.
    Write,
    /// Also server-wide calls.
    Admin,
}

impl Role {
    /// The role's name, as in the configuration.
    pub fn name(self) -> &'static str {
        match self {
            Role::Read => "read",
            Role::Write => "write",
            Role::Admin => "admin",
        }
    }
}

/// One API key.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KeyConfig {
    /// The Bearer token, at least [`MIN_KEY_CHARS`] characters, unique across all tenants.
    pub key: String,
    /// What it may do.
    pub role: Role,
}

/// One tenant.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TenantConfig {
    /// 1 to 64 characters of `[A-Za-z0-9._-]`; also its directory under the data directory.
    pub name: String,
    /// Its keys, at least one; several may be active at once (to rotate them without downtime).
    pub keys: Vec<KeyConfig>,
    /// Its weight in the devices' fair schedulers, 1 to 1000: while several tenants have traces queued on a device,
    /// each is served the device's time (the time its pieces hold a worker) in proportion to its share.
    #[serde(default = "default_share")]
    pub share: u32,
    /// Its limits: the server's `[limits]` with the keys set here replaced (filled in when the configuration is
    /// loaded).
    #[serde(default)]
    pub limits: Limits,
}

/// The share of a tenant that sets none.
fn default_share() -> u32 {
    1
}

/// The largest share.
pub const MAX_SHARE: u32 = 1000;

/// Checks the tenants: valid names, unique without case; shares in range; at least one key each; keys long enough
/// and unique across tenants.
pub fn check(tenants: &[TenantConfig]) -> Result<(), String> {
    let mut keys: Vec<&str> = Vec::new();
    for (i, tenant) in tenants.iter().enumerate() {
        let name = &tenant.name;
        let valid = (1..=64).contains(&name.len())
            && name.bytes().all(|b| b.is_ascii_alphanumeric() || b"._-".contains(&b))
            && name != "."
            && name != "..";
        if !valid {
            return Err(format!("tenants[{i}].name {name:?} must be 1 to 64 characters of [A-Za-z0-9._-]"));
        }
        // Compared without case: the names are directories of the data directory, one on a file system that
        // ignores case (macOS, Windows) for "Acme" and "acme".
        if let Some(other) = tenants[..i].iter().find(|t| t.name.eq_ignore_ascii_case(name)) {
            return Err(format!(
                "tenants[{i}].name {name:?} is used twice ({:?}; names are compared without case)",
                other.name
            ));
        }
        if !(1..=MAX_SHARE).contains(&tenant.share) {
            return Err(format!("tenants[{i}].share = {} must be 1 to {MAX_SHARE}", tenant.share));
        }
        if tenant.keys.is_empty() {
            return Err(format!("tenants[{i}] ({name}) has no keys"));
        }
        for (k, key) in tenant.keys.iter().enumerate() {
            if key.key.chars().count() < MIN_KEY_CHARS {
                return Err(format!("tenants[{i}].keys[{k}] is shorter than {MIN_KEY_CHARS} characters"));
            }
            if keys.contains(&key.key.as_str()) {
                return Err(format!("tenants[{i}].keys[{k}] is also another key (keys must be unique)"));
            }
            keys.push(&key.key);
        }
    }
    Ok(())
}
