//! Scale-out by scene: which rayd node holds an accel.
//!
//! A scene is every accel whose name starts with the same part before the first `.`: `farm`, `farm.cow`,
//! `farm.cow.motion`, `farm.1` (what `build_scene` and `load_accel` make) are all scene `farm`. An instance accel can
//! only place accels of its own node, so a scene never spans nodes.
//!
//! Two ways to reach the right node, one per deployment (they place scenes differently, do not mix them):
//! - **Through a proxy** (Envoy, ring-hash load balancing): every accel-scoped call of a [`Client`] carries the
//!   header [`ROUTE_HEADER`]` = `[`route_key`]`(accel)`, and the proxy hashes it to a node.
//! - **By the client itself**: a [`Router`] connects to every node (e.g. the per-pod DNS names of a StatefulSet's
//!   headless Service) and picks one per scene with rendezvous hashing ([`Ring`]).
//!
//! The tenant is not part of the key: the client does not know it (its token implies it, and a tenant's several
//! keys must reach the same node). Same-named scenes of two tenants share a node, each still seeing only its own.

use tonic::metadata::{Ascii, MetadataValue};

use crate::client::{Client, ClientOptions};
use crate::error::{Error, Result};

/// The request header that names the scene a call is for; the proxy hashes its value.
pub const ROUTE_HEADER: &str = "x-rayd-accel";

/// The routing key of accel `accel`: its scene (the name up to the first `.`), with bytes outside visible ASCII and
/// `%` written as `%XX` so that it is a valid header value. `None` for an empty name.
pub fn route_key(accel: &str) -> Option<String> {
    let scene = accel.split('.').next().unwrap_or_default();
    if scene.is_empty() {
        return None;
    }
    let mut key = String::with_capacity(scene.len());
    for byte in scene.bytes() {
        if byte.is_ascii_graphic() && byte != b'%' {
            key.push(char::from(byte));
        } else {
            key.push_str(&format!("%{byte:02X}"));
        }
    }
    Some(key)
}

/// [`route_key`] as a ready-made header value.
pub(crate) fn route_header(accel: &str) -> Option<MetadataValue<Ascii>> {
    route_key(accel).map(|key| key.parse().expect("route keys are visible ASCII"))
}

/// Rendezvous (highest random weight) hashing over a fixed list of nodes: a key goes to the node with the highest
/// [`score`](Ring::score). Adding one node to N moves only the keys the new node wins (≈ 1/(N+1) of them, all to
/// it); removing one moves only its own keys, spread over the others. The same list gives the same placement in
/// every process: the hash is FNV-1a 64 of `node`, a 0xFF byte and `key`, through the splitmix64 finalizer.
#[derive(Debug, Clone)]
pub struct Ring {
    /// The nodes' stable names (URLs); their order does not matter.
    nodes: Vec<String>,
}

impl Ring {
    /// A ring over `nodes`, named by something stable across restarts (a StatefulSet pod's DNS name, not its IP).
    pub fn new(nodes: impl IntoIterator<Item = impl Into<String>>) -> Ring {
        Ring { nodes: nodes.into_iter().map(Into::into).collect() }
    }

    /// The nodes, as given.
    pub fn nodes(&self) -> &[String] {
        &self.nodes
    }

    /// The index in [`Ring::nodes`] of the node that holds `key` (a [`route_key`]); `None` when there are no nodes.
    pub fn node_for(&self, key: &str) -> Option<usize> {
        (0..self.nodes.len()).max_by_key(|&i| (Ring::score(&self.nodes[i], key), std::cmp::Reverse(i)))
    }

    /// The weight of `key` on `node`.
    pub fn score(node: &str, key: &str) -> u64 {
        const OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
        const PRIME: u64 = 0x0100_0000_01b3;
        let bytes = node.bytes().chain([0xFF]).chain(key.bytes());
        let fnv = bytes.fold(OFFSET, |hash, byte| (hash ^ u64::from(byte)).wrapping_mul(PRIME));
        splitmix64(fnv)
    }
}

/// The splitmix64 finalizer: spreads FNV's weak low bits over the whole word.
fn splitmix64(mut x: u64) -> u64 {
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^ (x >> 31)
}

/// Client-side routing: one [`Client`] per node and a [`Ring`] that picks the node of each scene.
#[derive(Debug, Clone)]
pub struct Router {
    /// Which node holds which scene.
    ring: Ring,
    /// One connection per node, in the ring's order.
    clients: Vec<Client>,
}

impl Router {
    /// Connects to every node of `urls` (e.g. `http://rayd-0.rayd-headless:50051`, `http://rayd-1.…`): each must
    /// answer, else the error names it.
    pub async fn connect(urls: &[String], options: ClientOptions) -> Result<Router> {
        if urls.is_empty() {
            return Err(Error::InvalidArgument("router: at least one node URL is needed".into()));
        }
        let mut clients = Vec::with_capacity(urls.len());
        for url in urls {
            clients.push(Client::connect(url, options.clone()).await?);
        }
        Ok(Router { ring: Ring::new(urls.iter().cloned()), clients })
    }

    /// The client of the node that holds accel `accel`'s scene, with [`Client::for_scene`] applied so that buffers
    /// and streams it makes land on that node too. An empty name goes to the first node.
    pub fn client(&self, accel: &str) -> Client {
        let node = route_key(accel).and_then(|key| self.ring.node_for(&key)).unwrap_or(0);
        self.clients[node].for_scene(accel)
    }

    /// Every node's client, in the order of the URLs (for calls that concern all nodes, such as listing accels).
    pub fn clients(&self) -> &[Client] {
        &self.clients
    }

    /// The ring.
    pub fn ring(&self) -> &Ring {
        &self.ring
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_scene_is_the_name_up_to_the_first_dot_written_as_visible_ascii() {
        assert_eq!(route_key("farm").as_deref(), Some("farm"));
        assert_eq!(route_key("farm.cow").as_deref(), Some("farm"));
        assert_eq!(route_key("farm.cow.motion").as_deref(), Some("farm"));
        assert_eq!(route_key("bunny-2/x").as_deref(), Some("bunny-2/x"));
        assert_eq!(route_key("ferme à 50%").as_deref(), Some("ferme%20%C3%A0%2050%25"));
        assert_eq!(route_key(""), None);
        assert_eq!(route_key(".hidden"), None);
        assert!(route_header("ferme à 50%").is_some());
    }

    fn nodes(n: usize) -> Vec<String> {
        (0..n).map(|i| format!("http://rayd-{i}.rayd-headless:50051")).collect()
    }

    fn keys() -> Vec<String> {
        (0..10_000).map(|i| format!("scene-{i}")).collect()
    }

    #[test]
    fn placement_is_stable_and_even() {
        let ring = Ring::new(nodes(5));
        let again = Ring::new(nodes(5).into_iter().rev());
        let mut per_node = [0usize; 5];
        for key in keys() {
            let node = ring.node_for(&key).unwrap();
            assert_eq!(
                ring.nodes()[node],
                again.nodes()[again.node_for(&key).unwrap()],
                "the order of the list changed the placement"
            );
            per_node[node] += 1;
        }
        for count in per_node {
            assert!((1_700..2_300).contains(&count), "uneven placement: {per_node:?}");
        }
        assert_eq!(Ring::new(Vec::<String>::new()).node_for("farm"), None);
    }

    #[test]
    fn adding_one_node_of_n_moves_about_one_nth_of_the_keys_all_to_it() {
        for n in [2, 4, 8] {
            let (before, after) = (Ring::new(nodes(n)), Ring::new(nodes(n + 1)));
            let mut moved = 0usize;
            for key in keys() {
                let (from, to) = (before.node_for(&key).unwrap(), after.node_for(&key).unwrap());
                if from != to {
                    assert_eq!(to, n, "a key moved between two old nodes");
                    moved += 1;
                }
            }
            let expected = keys().len() / (n + 1);
            assert!(moved.abs_diff(expected) < expected / 10, "{n} → {}: {moved} moved, ≈ {expected} expected", n + 1);
        }
    }

    #[test]
    fn removing_a_node_moves_only_its_keys() {
        let (before, after) = (Ring::new(nodes(5)), Ring::new(nodes(5).into_iter().filter(|n| !n.contains("-2."))));
        for key in keys() {
            let from = &before.nodes()[before.node_for(&key).unwrap()];
            let to = &after.nodes()[after.node_for(&key).unwrap()];
            assert!(from == to || from.contains("-2."), "{key} moved from a node that stayed");
        }
    }
}
