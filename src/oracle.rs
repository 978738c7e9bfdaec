//! The brute-force intersector: every ray against every triangle, no acceleration structure. It shares the
//! triangle test, the acceptance rules and the hit collection with the backends, so it is the oracle that tests
//! compare them with.

use crate::error::Result;
use crate::geometry::{GatheredTriangles, is_degenerate};
use crate::intersect::PreparedRay;
use crate::query::{InstanceScope, Query, TraceOutput, TraceStats, TriangleCandidate, consider_triangle, trace_batch};

/// Traces `rays` against every triangle of `triangles` (static: at their first key's positions, whatever the rays'
/// times). `any` queries report the first hit in input order.
pub fn trace(triangles: &GatheredTriangles, query: &Query, rays: &[u8], out: TraceOutput<'_>) -> Result<TraceStats> {
    let hittable: Vec<usize> = (0..triangles.len()).filter(|&i| !is_degenerate(&triangles.corners(i)[0])).collect();
    trace_batch(
        query,
        rays,
        out,
        u64::MAX,
        || (),
        |_, rays, collectors, stats| {
            for (ray, collector) in rays.iter().zip(collectors) {
                let ray = PreparedRay::from_traced(ray);
                for &i in &hittable {
                    stats.triangle_tests += 1;
                    let id = triangles.refs[i];
                    let candidate = TriangleCandidate {
                        corners: &triangles.corners(i)[0],
                        id,
                        mask: triangles.mask(i),
                        geometry_flags: triangles.geometry_flags[id.geom_id as usize],
                    };
                    consider_triangle(&ray, &candidate, &InstanceScope::WORLD, collector);
                    if collector.done() {
                        break;
                    }
                }
            }
        },
    )
}
