#!/usr/bin/env python3
"""Writes the benches' tiled scene as a `rayctl scene` file: every shared mesh scaled to a unit cube and placed on a
grid 1.25 units apart, whole cycles of the eight meshes until at least a million triangles (24 placements,
1,166,823 triangles), as `Mesh::tiled` does, each placement an instance of its mesh's accel.

    python3 bench/tiled_scene.py MESH_DIR OUT.json

Mesh paths in the file are relative to OUT.json's folder: put (or link) the meshes in `meshes/` beside it.
"""

import json
import math
import sys

MESHES = ["beast", "cow", "fandisk", "nefertiti", "ogre", "spot", "stanford-bunny", "teapot"]
MIN_TRIANGLES = 1_000_000
SPACING = 1.25


def bounds_and_triangles(path):
    """The box of every `v` line and the triangle count of the `f` lines (fans) of an OBJ file."""
    lo, hi, triangles = [math.inf] * 3, [-math.inf] * 3, 0
    with open(path) as obj:
        for line in obj:
            if line.startswith("v "):
                p = [float(x) for x in line.split()[1:4]]
                lo = [min(a, b) for a, b in zip(lo, p)]
                hi = [max(a, b) for a, b in zip(hi, p)]
            elif line.startswith("f "):
                triangles += len(line.split()) - 3
    return lo, hi, triangles


def main():
    mesh_dir, out = sys.argv[1], sys.argv[2]
    info = {name: bounds_and_triangles(f"{mesh_dir}/{name}.obj") for name in MESHES}
    per_cycle = sum(t for _, _, t in info.values())
    copies = -(-MIN_TRIANGLES // per_cycle) * len(MESHES)
    side = math.ceil(math.sqrt(copies))
    instances = []
    for copy in range(copies):
        name = MESHES[copy % len(MESHES)]
        lo, hi, _ = info[name]
        scale = 1.0 / max(h - l for l, h in zip(lo, hi))
        middle = [(l + h) / 2 for l, h in zip(lo, hi)]
        centre = [(copy % side) * SPACING, 0.0, (copy // side) * SPACING]
        t = [centre[i] - middle[i] * scale for i in range(3)]
        instances.append({"mesh": name, "transform": [scale, 0, 0, t[0], 0, scale, 0, t[1], 0, 0, scale, t[2]]})
    scene = {"meshes": {name: f"meshes/{name}.obj" for name in MESHES}, "instances": instances}
    with open(out, "w") as f:
        json.dump(scene, f, indent=1)
    print(f"{copies} placements, {per_cycle * copies // len(MESHES)} triangles")


if __name__ == "__main__":
    main()
