"""The rayd contract from outside Rust.

Python stubs that grpcio-tools generated from proto/ build a two-triangle quad with BuildAccel and trace hand-made
rays with TraceBatch; the hits, decoded with numpy by the layouts of formats.proto, must be the known triangles,
distances and barycentrics. Prints one line, `contract ok: ...`, and exits 0; any mismatch exits non-zero.

Usage: contract_test.py --address HOST:PORT --stubs DIR   (DIR holds rayd/v1/*_pb2*.py)
"""

import argparse
import sys

import grpc
import numpy as np

# RAY_FORMAT_ORIGIN_TMIN_DIRECTION_TMAX, 32 bytes: 0 origin.xyz | 12 tmin | 16 direction.xyz | 28 tmax.
RAY = np.dtype([("origin", "<f4", 3), ("tmin", "<f4"), ("direction", "<f4", 3), ("tmax", "<f4")])
# HIT_FORMAT_T_TRIID_U_V, 16 bytes: 0 t f32 | 4 prim_id i32 | 8 u f32 | 12 v f32.
HIT = np.dtype([("t", "<f4"), ("prim_id", "<i4"), ("u", "<f4"), ("v", "<f4")])
# Added to the triangles' indices in the prim_ids that hits report.
PRIMITIVE_INDEX_OFFSET = 10


def expect(condition, message):
    """Exits non-zero with `message` unless `condition` holds."""
    if not condition:
        sys.exit(f"contract FAILED: {message}")


def quad_input(pb):
    """The unit square in the plane z = 0 as triangles 10 (0,0)(1,0)(1,1) and 11 (0,0)(1,1)(0,1), inline."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype="<f4")
    indices = np.array([[0, 1, 2], [0, 2, 3]], dtype="<u4")
    triangles = pb.accels.TriangleInput(
        vertices=pb.accels.DataSource(inline=vertices.tobytes()),
        vertex_format=pb.formats.VERTEX_FORMAT_FLOAT3,
        indices=pb.accels.DataSource(inline=indices.tobytes()),
        index_format=pb.formats.INDEX_FORMAT_UINT32X3,
        primitive_index_offset=PRIMITIVE_INDEX_OFFSET,
    )
    return pb.accels.BuildInput(triangles=triangles)


def rays_and_expected_hits():
    """Hand-made rays and the hit records they must give: (t, prim_id, u, v), a miss being (-1, -1, 0, 0)."""
    inf = np.float32(np.inf)
    rays = np.array(
        [
            ((0.75, 0.25, 2), 0, (0, 0, -1), inf),  # triangle 10 at t = 2; (0.75, 0.25) = 0.5·v1 + 0.25·v2
            ((0.25, 0.75, 2), 0, (0, 0, -2), inf),  # triangle 11; t is in units of the direction's length
            ((2, 2, 2), 0, (0, 0, -1), inf),  # beside the quad
            ((0.75, 0.25, 2), 0, (0, 0, -1), 1.5),  # stops short of it
            ((0.75, 0.25, -1), 0, (0, 0, 1), inf),  # from below: back faces are hit without culling
            ((0.75, 0.25, 2), 2.5, (0, 0, -1), inf),  # starts past it
        ],
        dtype=RAY,
    )
    hits = np.array(
        [(2, 10, 0.5, 0.25), (1, 11, 0.25, 0.5), (-1, -1, 0, 0), (-1, -1, 0, 0), (1, 10, 0.5, 0.25), (-1, -1, 0, 0)],
        dtype=HIT,
    )
    return rays, hits


class Stubs:
    """The generated modules, imported from the directory grpcio-tools wrote them to."""

    def __init__(self, directory):
        sys.path.insert(0, directory)
        from rayd.v1 import accels_pb2, devices_pb2, formats_pb2, service_pb2_grpc, trace_pb2

        self.accels, self.devices, self.formats, self.trace = accels_pb2, devices_pb2, formats_pb2, trace_pb2
        self.service = service_pb2_grpc


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--address", required=True, help="rayd's gRPC address, HOST:PORT")
    parser.add_argument("--stubs", required=True, help="directory of the generated rayd/v1 modules")
    args = parser.parse_args()
    pb = Stubs(args.stubs)
    rayd = pb.service.RaydStub(grpc.insecure_channel(args.address))

    devices = rayd.ListDevices(pb.devices.ListDevicesRequest()).devices
    expect(devices[0].id == "cpu:0", f"the first device is {devices[0].id!r}")
    info = rayd.BuildAccel(pb.accels.BuildAccelRequest(name="quad", inputs=[quad_input(pb)]))
    expect((info.name, info.triangle_count, info.geometry_count) == ("quad", 2, 1), f"accel {info}")
    box = [(v.x, v.y, v.z) for v in (info.bounds.min, info.bounds.max)]
    expect(box == [(0, 0, 0), (1, 1, 0)], f"bounds {box}")

    rays, expected = rays_and_expected_hits()
    query = pb.trace.TraceQuery(
        accel=pb.accels.AccelRef(name="quad"),
        query=pb.formats.QUERY_TYPE_CLOSEST,
        ray_format=pb.formats.RAY_FORMAT_ORIGIN_TMIN_DIRECTION_TMAX,
        hit_format=pb.formats.HIT_FORMAT_T_TRIID_U_V,
    )
    reply = rayd.TraceBatch(pb.trace.TraceBatchRequest(query=query, rays_inline=rays.tobytes()))
    hits = np.frombuffer(reply.hits, dtype=HIT)
    expect(len(hits) == len(rays), f"{len(reply.hits)} hit bytes for {len(rays)} rays")
    expect(np.array_equal(hits["prim_id"], expected["prim_id"]), f"prim_ids {hits['prim_id']}")
    for field in ("t", "u", "v"):
        expect(np.allclose(hits[field], expected[field], rtol=0, atol=1e-6), f"{field} {hits[field]}")
    hit_count = int(np.count_nonzero(expected["t"] >= 0))
    expect((reply.stats.rays, reply.stats.rays_hit) == (len(rays), hit_count), f"stats {reply.stats}")

    try:
        rayd.TraceBatch(pb.trace.TraceBatchRequest(query=query, rays_inline=rays.tobytes()[:-1]))
        expect(False, "a ray buffer one byte short was accepted")
    except grpc.RpcError as error:
        expect(error.code() == grpc.StatusCode.INVALID_ARGUMENT, f"{error.code()}: {error.details()}")
        expect("rays" in error.details(), f"the message {error.details()!r} names the rays")

    print(f"contract ok: {len(rays)} rays, {hit_count} hits, prim_ids {hits['prim_id'].tolist()}")


if __name__ == "__main__":
    main()
