//! What the engine, run in the test's own process, makes of the shared bunny: the bytes that end-to-end tests
//! compare the service's answers with. Needs `mod common;` beside it.
#![allow(dead_code)] // Each end-to-end test file uses its own part of it.

use std::sync::{Arc, OnceLock};

use rayd_engine::accel::{AccelInfo, BuildOptions};
use rayd_engine::format::RayFormat;
use rayd_engine::geometry::BuildInput;
use rayd_engine::mesh::{Mesh, PackedMesh};
use rayd_engine::query::{Query, TraceOutput, TraceStats};
use rayd_engine::raygen::Camera;
use rayd_engine::{Accel, Context, Device};

use crate::common::shared_mesh;

/// Triangles of `shared/data/meshes/stanford-bunny.obj`.
pub const BUNNY_TRIANGLES: u64 = 69451;

/// The bunny, its build-input bytes, and its accel built in this process with the default options.
pub struct Bunny {
    /// The mesh as loaded.
    pub mesh: Mesh,
    /// Float3 vertices and u32×3 indices: the bytes sent to the service.
    pub packed: PackedMesh,
    /// The CPU context that owns the accel.
    context: Context,
    /// The accel every expected answer comes from.
    accel: Arc<Accel>,
}

/// An in-process answer: exactly what the engine wrote.
#[derive(Debug)]
pub struct Expected {
    /// Hit records.
    pub hits: Vec<u8>,
    /// Counts (`all` and `count`), else empty.
    pub counts: Vec<u8>,
    /// What the engine did.
    pub stats: TraceStats,
}

impl Expected {
    /// Asserts that an answer of the service (its hit and count bytes, and its statistics' `(rays, rays_hit)`) is
    /// this one, byte for byte.
    pub fn assert_answer(&self, hits: &[u8], counts: &[u8], (rays, rays_hit): (u64, u64), what: &str) {
        assert_same_bytes(hits, &self.hits, &format!("{what}: hits"));
        assert_same_bytes(counts, &self.counts, &format!("{what}: counts"));
        assert_eq!((rays, rays_hit), (self.stats.rays, self.stats.rays_hit), "{what}: rays traced and rays hit");
    }
}

/// The bunny, loaded and built once per test process.
pub fn bunny() -> &'static Bunny {
    static BUNNY: OnceLock<Bunny> = OnceLock::new();
    BUNNY.get_or_init(|| {
        let mesh = shared_mesh("stanford-bunny");
        let packed = mesh.pack();
        let context = Context::new(Device::cpu());
        let accel = context
            .build_accel(&[BuildInput::Triangles(packed.input())], &BuildOptions::default())
            .expect("the bunny builds in process");
        Bunny { mesh, packed, context, accel }
    })
}

impl Bunny {
    /// What the in-process accel reports (size, counts, bounds).
    pub fn info(&self) -> &AccelInfo {
        self.accel.info()
    }

    /// The rays of a `width`×`height` camera framing the bunny, row by row, packed in `format`.
    pub fn camera_rays(&self, format: RayFormat, width: u32, height: u32) -> Vec<u8> {
        let (lo, hi) = self.mesh.bounds();
        Camera::framing(lo, hi, width, height).rays(format)
    }

    /// Traces `rays` in process.
    pub fn trace(&self, query: &Query, rays: &[u8]) -> Expected {
        let layout = query.output_layout(rays.len()).expect("a valid query");
        let (mut hits, mut counts) = (vec![0u8; layout.hits], vec![0u8; layout.counts]);
        let stats = self
            .context
            .trace(&self.accel, query, rays, TraceOutput { hits: &mut hits, counts: &mut counts })
            .expect("the in-process trace succeeds");
        Expected { hits, counts, stats }
    }
}

/// Asserts equal bytes, reporting the first difference instead of printing both buffers.
pub fn assert_same_bytes(actual: &[u8], expected: &[u8], what: &str) {
    assert_eq!(actual.len(), expected.len(), "{what}: byte length");
    if let Some(i) = actual.iter().zip(expected).position(|(a, e)| a != e) {
        let end = (i + 16).min(actual.len());
        panic!("{what}: first difference at byte {i}: {:?}, expected {:?}", &actual[i..end], &expected[i..end]);
    }
}
