#!/usr/bin/env python3
"""Compares rayd's engine with Embree on the same triangles and the same rays, and prints one table.

    python3 bench/compare_embree.py            # from anywhere; needs cargo and Python 3.11

On first use it creates bench/.venv and installs embreex (Embree 4 for Python) and numpy into it, then runs
itself again with that interpreter. For every case it runs `cargo run --release --example trace_mesh ... --export
DIR` (rays: origin_tmin_direction_tmax, hits: t_triid_u_v), traces the exported rays against the exported
triangles with Embree, and compares ray by ray. A ray agrees when both tracers miss, or both hit the same
primitive, or both hit at distances within a relative 1e-4 (ties between triangles that share an edge or overlap).
The script exits with status 1 when fewer than 99.99% of a case's rays agree, and lists the rays that do not.

Speed: embreex's `EmbreeScene.run` loops over `rtcIntersect1` (closest hit) or `rtcOccluded1` (any hit) in one
thread (it keeps the GIL, so Python threads do not help); rayd is therefore timed with every thread (rayon's
default) and with RAYON_NUM_THREADS=1, and the 1-thread figures are the like-for-like comparison. Trace times are
medians of --repeat runs and exclude scene builds, which are reported apart (Embree builds with all its TBB
threads). The 1-thread timings run in --rounds rounds, rayd then Embree in each, for closest and any hit; the ratio
reported is the median of the rounds' ratios, with their range, so that a machine whose speed drifts (a shared
host) biases neither side. rayd's `any` query writes the `bitmask` hit format, one bit a ray (hit or miss: what
Embree's occlusion query answers; until 2026-11-27 it wrote 16-byte `t_triid_u_v` records, 1–5% slower on camera
rays), and its answers are checked against Embree's occlusion ray by ray.

Embree from C: embreex's loop costs time of its own around each `rtcIntersect1`, and Embree's 16-wide packets
(`rtcIntersect16`, `rtcOccluded16`) are not in embreex. So bench/embree_packets.c (compiled here with gcc against the
Embree library inside the embreex wheel) times, in the same rounds and over the same exported rays, on one thread
and then on --threads threads (default 2; rayd is timed on as many right before it): Embree's single-ray calls in a
C loop, packets of 16 consecutive rays (the order rayd gets them in) and, for camera rays, packets of 4×4 pixel
tiles (Embree's best case), each with its hit/miss agreement with rayd checked. rayd's
own packets are 16 consecutive rays where the CPU has AVX-512, 8 where it has AVX2.

Builds: each scene is then built --builds times by each side, fresh every time, and the medians compared: rayd with
`PREFER_FAST_BUILD` and with its default preset, on every thread and on one; Embree (its default, medium quality)
on all its TBB threads (embreex cannot limit them). An Embree build is timed from creating the scene to its commit
(the first, one-ray query).
"""

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
VENV = BENCH / ".venv"
VENV_PYTHON = VENV / "bin" / "python"
PACKAGES = ["embreex==4.4.0.post1", "numpy"]
MESHES = Path(os.environ.get("RAYD_MESHES", "/work/shared/data/meshes"))
ALL_MESHES = ["stanford-bunny", "ogre", "nefertiti", "beast", "cow", "teapot", "fandisk", "spot"]
REQUIRED_AGREEMENT = 99.99  # percent of rays, every case
TIE_TOLERANCE = 1e-4  # relative |Δt| under which two different primitives count as a tie
CAMERA_WIDTH = 1024  # trace_mesh's camera image width (its default), for Embree's 4×4 tiles
PACKET_HARNESS = VENV / "embree_packets"


def ensure_venv():
    """Runs this script inside bench/.venv, creating it and installing the packages first if needed."""
    if Path(sys.prefix).resolve() == VENV.resolve():
        return
    if not VENV_PYTHON.exists():
        print(f"creating {VENV} and installing {' '.join(PACKAGES)} ...", file=sys.stderr)
        subprocess.run([sys.executable, "-m", "venv", str(VENV)], check=True)
        subprocess.run([str(VENV_PYTHON), "-m", "pip", "install", "--quiet", *PACKAGES], check=True)
    os.execv(str(VENV_PYTHON), [str(VENV_PYTHON), __file__, *sys.argv[1:]])


ensure_venv()

import numpy as np  # noqa: E402  (available only inside the venv)
from embreex import mesh_construction, rtcore_scene  # noqa: E402


def cases():
    """(name, trace_mesh arguments) of every case."""
    bunny = ["--mesh", str(MESHES / "stanford-bunny.obj")]
    tiled = [arg for name in ALL_MESHES for arg in ("--mesh", str(MESHES / f"{name}.obj"))] + ["--tiled", "1000000"]
    uneven = bunny + ["--slivers", "256"]
    return [
        ("bunny camera", bunny + ["--rays", "camera"]),
        ("bunny random", bunny + ["--rays", "random"]),
        ("tiled camera", tiled + ["--rays", "camera"]),
        ("tiled random", tiled + ["--rays", "random"]),
        ("uneven camera", uneven + ["--rays", "camera"]),
        ("uneven random", uneven + ["--rays", "random"]),
    ]


def run_rayd(args, repeat, threads=None, export=None):
    """Runs the trace_mesh example and returns its JSON report."""
    command = ["cargo", "run", "--quiet", "--release", "--example", "trace_mesh", "--", *args, "--repeat", str(repeat)]
    if export is not None:
        command += ["--export", str(export)]
    env = dict(os.environ)
    if threads is not None:
        env["RAYON_NUM_THREADS"] = str(threads)
    output = subprocess.run(command, cwd=ROOT, env=env, check=True, capture_output=True, text=True).stdout
    return json.loads(output.strip().splitlines()[-1])


def load_export(directory):
    """The exported scene, rays and rayd hits as numpy arrays."""
    vertices = np.fromfile(directory / "vertices.f32", dtype="<f4").reshape(-1, 3)
    indices = np.fromfile(directory / "indices.u32", dtype="<u4").reshape(-1, 3)
    # origin_tmin_direction_tmax: origin xyz, tmin, direction xyz, tmax (32 bytes).
    rays = np.fromfile(directory / "rays.bin", dtype="<f4").reshape(-1, 8)
    # t_triid_u_v: t f32, prim id i32, u f32, v f32 (16 bytes); a miss has t = -1 and prim id -1.
    hits = np.fromfile(directory / "hits.bin", dtype="<f4").reshape(-1, 4)
    return vertices, indices, rays, hits


def load_hit_bits(directory, rays):
    """The exported rayd hits of a `bitmask` trace of `rays` rays, a bool a ray (bit i of byte i / 8, least
    significant first)."""
    bits = np.unpackbits(np.fromfile(directory / "hits.bin", dtype=np.uint8), bitorder="little")
    return bits[:rays].astype(bool)


def build_embree(vertices, indices, origins, directions):
    """Builds an Embree scene (committed by a first one-ray query); returns (scene, build ms)."""
    start = time.perf_counter()
    scene = rtcore_scene.EmbreeScene()
    mesh_construction.TriangleMesh(scene, vertices, indices.astype(np.int32))
    scene.run(origins[:1], directions[:1])  # the scene is committed (built) on its first run
    return scene, (time.perf_counter() - start) * 1e3


def time_embree(scene, origins, directions, repeat, query):
    """Traces the rays `repeat` times with `query` (INTERSECT: closest hit, rtcIntersect1; OCCLUDED: any hit,
    rtcOccluded1); returns (median trace ms, hits of the last run)."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        if query == "INTERSECT":
            hits = scene.run(origins, directions, output=1)
        else:
            hits = scene.run(origins, directions, query=query)
        times.append((time.perf_counter() - start) * 1e3)
    return float(np.median(times)), hits


def embree_build_ms(vertices, indices, builds):
    """Median milliseconds of `builds` fresh Embree builds of the triangles."""
    indices = indices.astype(np.int32)
    origin, direction = np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32)
    times = []
    for _ in range(builds):
        start = time.perf_counter()
        scene = rtcore_scene.EmbreeScene()
        mesh_construction.TriangleMesh(scene, vertices, indices)
        scene.run(origin, direction)  # commits (builds) the scene
        times.append((time.perf_counter() - start) * 1e3)
    return float(np.median(times))


def compare_builds(scenes, builds):
    """Prints rayd's and Embree's build times of each (name, trace_mesh arguments, vertices, indices) scene."""
    print(f"Builds, median of {builds} fresh builds, ms (M triangles/s):")
    header_printed = False
    for name, args, vertices, indices in scenes:
        quick = args + ["--rays", "random", "--count", "1024", "--builds", str(builds)]
        fast = run_rayd(quick + ["--prefer", "fast-build"], 1)
        if not header_printed:
            n = fast["threads"]
            print(f"{'scene':<7} {'tris':>9} {f'fast-build {n} thr':>18} {'fast-build 1 thr':>18} "
                  f"{f'default {n} thr':>18} {'Embree (TBB)':>18} {f'Embree / fast-build {n} thr':>26}")
            header_printed = True
        fast_one = run_rayd(quick + ["--prefer", "fast-build"], 1, threads=1)
        default = run_rayd(quick, 1)
        embree = embree_build_ms(vertices, indices, builds)
        tris = len(indices)
        cell = lambda ms: f"{ms:.1f} ({tris / ms / 1e3:.2f})"
        print(f"{name:<7} {tris:>9} {cell(fast['build_ms']):>18} {cell(fast_one['build_ms']):>18} "
              f"{cell(default['build_ms']):>18} {cell(embree):>18} {embree / fast['build_ms']:>26.2f}")
    print()


def explain(vertices, indices, who, prim, origin, direction):
    """A line on where, in f64, the ray meets triangle `prim`: its barycentrics, the distance of the hit point
    from the nearest edge (also in f32 ulps of the point's coordinates), and how the triangle across that edge
    faces the ray (opposite facing = a fold, which the edge rule may count 0 or 2 times)."""
    corners = vertices[indices[prim]].astype(np.float64)
    o, d = origin.astype(np.float64), direction.astype(np.float64)
    a, b, c = corners
    e1, e2 = b - a, c - a
    p, s = np.cross(d, e2), o - a
    det = e1 @ p
    q = np.cross(s, e1)
    u, v = (s @ p) / det, (d @ q) / det
    t = (e2 @ q) / det
    weights = np.array([1.0 - u - v, u, v])
    k = int(np.argmin(np.abs(weights)))  # the edge opposite corner k is the nearest
    i, j = (k + 1) % 3, (k + 2) % 3
    point = o + t * d
    along = corners[j] - corners[i]
    gap = np.linalg.norm(np.cross(point - corners[i], along)) / np.linalg.norm(along)
    ulp = float(np.spacing(np.float32(np.abs(point).max())))
    ends = indices[prim][[i, j]]
    across = [int(n) for n in np.flatnonzero((indices == ends[0]).any(1) & (indices == ends[1]).any(1)) if n != prim]
    facing = np.sign(np.cross(e1, e2) @ d)
    sides = []
    for n in across:
        na, nb, nc = vertices[indices[n]].astype(np.float64)
        sides.append(f"{n} ({'same' if np.sign(np.cross(nb - na, nc - na) @ d) == facing else 'opposite'} facing)")
    return (f"      f64, {who}'s prim {prim}: t={t:.9g} barycentrics {np.array2string(weights, precision=3)}; "
            f"{gap:.2e} ({gap / ulp:.2f} ulp) from edge {ends.tolist()}, across it: {', '.join(sides) or 'nothing'}")


def compare(vertices, indices, rays, rayd, embree):
    """Agreement figures and the rays that disagree, ray by ray."""
    rayd_t, rayd_prim = rayd[:, 0], rayd[:, 1].view("<i4")
    embree_t, embree_prim = embree["tfar"], embree["primID"]
    rayd_hit, embree_hit = rayd_t >= 0, embree_prim >= 0
    both = rayd_hit & embree_hit
    same_prim = both & (rayd_prim == embree_prim)
    absolute = np.abs(rayd_t[both] - embree_t[both])
    relative = absolute / np.maximum(np.abs(embree_t[both]), 1e-30)
    relative_all = np.zeros(len(rays))
    relative_all[both] = relative
    tie = both & ~same_prim & (relative_all <= TIE_TOLERANCE)
    agree = (rayd_hit == embree_hit) & (~both | same_prim | tie)
    bad = np.flatnonzero(~agree)
    details = []
    for i in bad[:10]:
        line = (f"    ray {i}: origin {rays[i, 0:3].tolist()} direction {rays[i, 4:7].tolist()}\n"
                f"      rayd   t={rayd_t[i]!r} prim={rayd_prim[i]} u={rayd[i, 2]!r} v={rayd[i, 3]!r}\n"
                f"      embree t={embree_t[i]!r} prim={embree_prim[i]} u={embree['u'][i]!r} v={embree['v'][i]!r}")
        for who, prim in (("rayd", rayd_prim[i]), ("embree", embree_prim[i])):
            if prim >= 0:
                line += "\n" + explain(vertices, indices, who, prim, rays[i, 0:3], rays[i, 4:7])
        details.append(line)
    return {
        "hit_rate": 100.0 * rayd_hit.mean(),
        "hit_miss": 100.0 * (rayd_hit == embree_hit).mean(),
        "prim": 100.0 * same_prim.sum() / max(both.sum(), 1),
        "ties": int(tie.sum()),
        "dt_abs": float(absolute.max()) if absolute.size else 0.0,
        "dt_max": float(relative.max()) if relative.size else 0.0,
        "dt_p999": float(np.quantile(relative, 0.999)) if relative.size else 0.0,
        "agree": 100.0 * agree.mean(),
        "disagree": len(bad),
        "details": details,
    }


def build_packet_harness():
    """Compiles bench/embree_packets.c against the embreex wheel's Embree library; False when it cannot."""
    libraries = sorted((Path(__import__("embreex").__file__).parent.parent / "embreex.libs").glob("libembree4*.so*"))
    if not libraries:
        print("no Embree library in the embreex wheel: Embree's packets are not timed", flush=True)
        return False
    command = ["gcc", "-O2", "-pthread", "-o", str(PACKET_HARNESS), str(BENCH / "embree_packets.c"), str(libraries[0]),
               f"-Wl,-rpath,{libraries[0].parent}", "-lm"]
    try:
        subprocess.run(command, check=True)
    except (OSError, subprocess.CalledProcessError) as error:
        print(f"cannot compile the packet harness ({error}): Embree's packets are not timed", flush=True)
        return False
    return True


def embree_packets(export, repeat, query, camera, threads=1):
    """Embree's speeds on `threads` threads over an exported case from the packet harness: single rays, packets of
    16 consecutive rays, 4×4 tiles for a `camera` case (else 0), and each one's hit/miss agreement with rayd."""
    command = [str(PACKET_HARNESS), str(export), str(repeat), query, str(threads)]
    command += [str(CAMERA_WIDTH)] if camera else []
    output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    return json.loads(output.strip().splitlines()[-1])


def interleaved_speeds(args, scene, origins, directions, options, export, packets, camera):
    """Two dicts, each {"closest": [a tuple a round], "any": [...]} of M rays/s: on 1 thread each (rayd, Embree, the
    packet harness's report or None), and on --threads threads each (rayd, the packet harness's report or None).
    In every round rayd then Embree (then, with `packets`, the packet harness over `export`) on 1 thread, then rayd
    and the harness on --threads; the first round's rayd `any` trace (in the `bitmask` hit format, as occlusion)
    exports its hits to `export / "any"`."""
    rays = len(origins)
    speeds, wide = {"closest": [], "any": []}, {"closest": [], "any": []}
    for round in range(options.rounds):
        for query, embree_query in (("closest", "INTERSECT"), ("any", "OCCLUDED")):
            any_export = export / "any" if query == "any" and round == 0 else None
            query_args = args + ["--query", query] + (["--hit-format", "bitmask"] if query == "any" else [])
            rayd = run_rayd(query_args, options.repeat, threads=1, export=any_export)
            embree_ms, _ = time_embree(scene, origins, directions, options.repeat, embree_query)
            packed = embree_packets(export, options.repeat, query, camera) if packets else None
            speeds[query].append((rayd["mrays_per_s"], rays / embree_ms / 1e3, packed))
            rayd = run_rayd(query_args, options.repeat, threads=options.threads)
            packed = embree_packets(export, options.repeat, query, camera, options.threads) if packets else None
            wide[query].append((rayd["mrays_per_s"], packed))
    return speeds, wide


def machine():
    """A line saying where and when this ran."""
    model = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    rustc = subprocess.run(["rustc", "--version"], capture_output=True, text=True).stdout.strip()
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    return (f"machine: {os.cpu_count()} logical CPUs (nproc {len(os.sched_getaffinity(0))}), {model}, "
            f"{platform.system()} {platform.release()}\n"
            f"date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}; load average at start: {load}\n"
            f"{rustc}; embreex {__import__('embreex').__version__} (Embree 4, default scene flags, rtcIntersect1 "
            f"loop, 1 thread); numpy {np.__version__}")


def print_packet_table(rows):
    """Prints rayd's speeds against the packet harness's, per case and query: `rows` are (name, {query: [(rayd M
    rays/s, the harness's report) a round]})."""
    print(f"{'case':<13} {'query':<8} {'rayd':>11} {'Embree 1-ray':>13} {'ratio':>18} {'16 in a row':>12} "
          f"{'ratio':>18} {'4×4 tiles':>10} {'ratio':>18}")
    for name, speeds in rows:
        for query, rounds in speeds.items():
            cells = []
            for way in ("single", "packet", "tile"):
                if not rounds[0][1][f"{way}_mrays_per_s"]:
                    cells += ["–", "–"]
                    continue
                ratios = sorted(r / p[f"{way}_mrays_per_s"] for r, p in rounds)
                cells.append(f"{np.median([p[f'{way}_mrays_per_s'] for _, p in rounds]):.2f}")
                cells.append(f"{np.median(ratios):.2f} ({ratios[0]:.2f}–{ratios[-1]:.2f})")
            print(f"{name:<13} {query:<8} {np.median([r for r, _ in rounds]):>11.2f} {cells[0]:>13} "
                  f"{cells[1]:>18} {cells[2]:>12} {cells[3]:>18} {cells[4]:>10} {cells[5]:>18}")
    print()


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=5, help="timed traces per tracer and case (median reported)")
    parser.add_argument("--keep", type=Path, help="export the buffers into this directory and keep them")
    parser.add_argument("--builds", type=int, default=5, help="fresh builds per builder and scene (median reported)")
    parser.add_argument("--rounds", type=int, default=3,
                        help="rounds of 1-thread timings, rayd then Embree in each (medians reported)")
    parser.add_argument("--threads", type=int, default=2,
                        help="the second thread count rayd and the packet harness are timed on, in every round")
    parser.add_argument("--scene", action="append", choices=sorted({name.split()[0] for name, _ in cases()}),
                        help="run only this scene's cases (repeat for several; default: every scene)")
    options = parser.parse_args()

    print(machine(), flush=True)
    print("building the trace_mesh example ...", flush=True)
    subprocess.run(["cargo", "build", "--quiet", "--release", "--example", "trace_mesh"], cwd=ROOT, check=True)
    packets = build_packet_harness()

    rows, failures, built = [], [], {}
    with tempfile.TemporaryDirectory(prefix="rayd-embree-") as scratch:
        base = options.keep or Path(scratch)
        for name, args in cases():
            if options.scene and name.split()[0] not in options.scene:
                continue
            export = base / name.replace(" ", "-")
            print(f"{name}: rayd (all threads) ...", flush=True)
            rayd_all = run_rayd(args, options.repeat, export=export)
            print(f"{name}: rayd (1 thread) ...", flush=True)
            rayd_one = run_rayd(args, options.repeat, threads=1, export=export / "one-thread")
            vertices, indices, rays, rayd_hits = load_export(export)
            scene_name = name.split()[0]
            if scene_name not in built:
                built[scene_name] = (scene_name, [a for a in args if a not in ("--rays", "camera", "random")],
                                     vertices, indices)
            same = (export / "hits.bin").read_bytes() == (export / "one-thread" / "hits.bin").read_bytes()
            if not same:
                failures.append(f"{name}: rayd's hits differ between 1 thread and {rayd_all['threads']} threads")
            if not (np.all(rays[:, 3] == 0) and np.all(np.isinf(rays[:, 7]))):
                sys.exit(f"{name}: rays must have tmin 0 and tmax +inf (embreex fixes tnear = 0)")
            origins, directions = np.ascontiguousarray(rays[:, 0:3]), np.ascontiguousarray(rays[:, 4:7])
            print(f"{name}: Embree ...", flush=True)
            scene, embree_build = build_embree(vertices, indices, origins, directions)
            embree_ms, embree_hits = time_embree(scene, origins, directions, options.repeat, "INTERSECT")
            result = compare(vertices, indices, rays, rayd_hits, embree_hits)
            print(f"{name}: rayd and Embree, 1 thread each, closest and any hit, {options.rounds} rounds ...",
                  flush=True)
            camera = name.endswith("camera")
            speeds, wide = interleaved_speeds(args, scene, origins, directions, options, export, packets, camera)
            rayd_any = load_hit_bits(export / "any", len(rays))
            _, embree_occluded = time_embree(scene, origins, directions, 1, "OCCLUDED")
            any_agree = 100.0 * np.mean(rayd_any == (np.asarray(embree_occluded) >= 0))
            rows.append((name, len(rays), rayd_all, rayd_one, embree_build, speeds, result, any_agree, wide))
            if result["agree"] < REQUIRED_AGREEMENT:
                failures.append(f"{name}: {result['agree']:.4f}% of rays agree, below {REQUIRED_AGREEMENT}%")
            for query in speeds:
                for *_, packed in speeds[query] + wide[query]:
                    for way in ("single", "packet") + (("tile",) if camera else ()):
                        if packed and packed[f"{way}_agreement"] < REQUIRED_AGREEMENT:
                            failures.append(f"{name}: Embree's {way}s ({query}) agree with rayd on hit/miss for "
                                            f"{packed[f'{way}_agreement']:.4f}% of rays")
            if any_agree < REQUIRED_AGREEMENT:
                failures.append(f"{name}: any hit: {any_agree:.4f}% of rays agree on hit/miss, below "
                                f"{REQUIRED_AGREEMENT}%")
            if result["details"]:
                print(f"{name}: {result['disagree']} rays disagree (first {len(result['details'])}):")
                print("\n".join(result["details"]), flush=True)

    threads = rows[0][2]["threads"]
    print()
    compare_builds(built.values(), options.builds)
    print(f"Agreement (rayd vs Embree, same rays); a tie = different primitives hit at relative |dt| <= "
          f"{TIE_TOLERANCE:g};\n|dt| over rays both hit, absolute (abs) and relative to Embree's t (large only for "
          f"hits at tiny t, from origins next to a surface).")
    print(f"{'case':<13} {'tris':>9} {'rays':>9} {'hit rate':>8} {'hit/miss':>9} {'prim id':>9} {'ties':>5} "
          f"{'max abs':>9} {'max rel':>9} {'p99.9 rel':>9} {'agree':>9}")
    for name, count, rayd_all, _, _, _, r, _, _ in rows:
        print(f"{name:<13} {rayd_all['triangles']:>9} {count:>9} {r['hit_rate']:>7.2f}% {r['hit_miss']:>8.4f}% "
              f"{r['prim']:>8.4f}% {r['ties']:>5} {r['dt_abs']:>9.2e} {r['dt_max']:>9.2e} {r['dt_p999']:>9.2e} {r['agree']:>8.4f}%")
    print("Any hit: hit/miss agreement of rayd's `any` query with Embree's rtcOccluded1: " +
          ", ".join(f"{name} {any_agree:.4f}%" for name, *_, any_agree, _ in rows))
    print()
    print(f"Speed, M rays/s. rayd {threads} thr: closest hit, median of {options.repeat} traces. 1 thread each "
          f"(the like-for-like comparison; embreex runs one thread): {options.rounds} rounds, each timing rayd then "
          f"Embree (median of {options.repeat} traces each), closest hit then any hit; medians over the rounds, "
          f"and the median and range of the rounds' ratios (a round's ratio is immune to the machine slowing down "
          f"between rounds).")
    print(f"{'case':<13} {f'rayd {threads} thr':>12} {'rayd 1 thr':>11} {'Embree 1 thr':>13} {'ratio 1/1':>18} "
          f"{'any: rayd 1 thr':>16} {'Embree 1 thr':>13} {'ratio 1/1':>18} {f'rayd build ms ({threads} thr)':>22} "
          f"{'Embree build ms (TBB)':>22}")
    for name, _, rayd_all, _, embree_build, speeds, _, _, _ in rows:
        cells = []
        for query, width in (("closest", 11), ("any", 16)):
            rounds = speeds[query]
            ratios = sorted(r / e for r, e, _ in rounds)
            cells.append(f"{np.median([r for r, _, _ in rounds]):>{width}.2f} "
                         f"{np.median([e for _, e, _ in rounds]):>13.2f} "
                         f"{f'{np.median(ratios):.2f} ({ratios[0]:.2f}–{ratios[-1]:.2f})':>18}")
        print(f"{name:<13} {rayd_all['mrays_per_s']:>12.2f} {cells[0]} {cells[1]} {rayd_all['build_ms']:>22.1f} "
              f"{embree_build:>22.1f}")
    print()
    if rows and rows[0][5]["closest"][0][2]:
        print(f"Against Embree from C (bench/embree_packets.c, the same Embree library, 1 thread, the same "
              f"{options.rounds} rounds): single rays in a C loop, packets of 16 consecutive rays, 4×4 pixel tiles "
              f"(camera rays); M rays/s, medians over the rounds, and the median and range of the rounds' ratios "
              f"rayd / Embree.")
        print_packet_table([(name, {q: [(r, p) for r, _, p in rounds] for q, rounds in speeds.items()})
                            for name, *_, speeds, _, _, _ in rows])
        print(f"The same on {options.threads} threads each (rayd's rayon pool; the harness's threads taking chunks "
              f"of 1,024 rays from a shared counter), in the same rounds.")
        print_packet_table([(name, wide) for name, *_, wide in rows])
    if failures:
        print("FAIL:\n  " + "\n  ".join(failures))
        sys.exit(1)
    print(f"PASS: every case has >= {REQUIRED_AGREEMENT}% agreement, and rayd's hits are identical on 1 and "
          f"{threads} threads.")


if __name__ == "__main__":
    main()
