"""Tiny textured meshes for dm-prep's shape prior tests.

A 16 x 12 x 8 cm box, each face split into a grid of quads with a random
flat colour per quad (vertices duplicated per quad so colours stay flat:
sharp corners for ORB). Written as OBJ (vertex colours: `v x y z r g b`) and
as GLB (POSITION, COLOR_0, indices in one binary chunk). Python standard
library only; seeded, so the files are reproducible.

Usage: python3 scripts/make_mesh_fixtures.py --out fixtures/meshes
"""

import argparse
import json
import os
import random
import struct

SIZE = (0.16, 0.12, 0.08)  # metres
CELLS = 8  # quads per face side


def box_quads():
    """(corner0, edge_u, edge_v) of each face, outward normal = u x v."""
    sx, sy, sz = (s / 2 for s in SIZE)
    return [
        ((-sx, -sy, sz), (2 * sx, 0, 0), (0, 2 * sy, 0)),  # +z
        ((sx, -sy, -sz), (-2 * sx, 0, 0), (0, 2 * sy, 0)),  # -z
        ((sx, -sy, sz), (0, 0, -2 * sz), (0, 2 * sy, 0)),  # +x
        ((-sx, -sy, -sz), (0, 0, 2 * sz), (0, 2 * sy, 0)),  # -x
        ((-sx, sy, sz), (2 * sx, 0, 0), (0, 0, -2 * sz)),  # +y
        ((-sx, -sy, -sz), (2 * sx, 0, 0), (0, 0, 2 * sz)),  # -y
    ]


def build():
    rng = random.Random(8)
    positions, colors, triangles = [], [], []
    for origin, u, v in box_quads():
        for i in range(CELLS):
            for j in range(CELLS):
                color = [rng.choice([0.05, 0.35, 0.65, 0.95]) for _ in range(3)]
                base = len(positions)
                for a, b in ((i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1)):
                    positions.append(
                        tuple(origin[k] + u[k] * a / CELLS + v[k] * b / CELLS for k in range(3))
                    )
                    colors.append(color)
                triangles += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    return positions, colors, triangles


def write_obj(path, positions, colors, triangles):
    with open(path, "w") as f:
        f.write("# textured box fixture (scripts/make_mesh_fixtures.py)\n")
        for p, c in zip(positions, colors):
            f.write("v %.6f %.6f %.6f %.4f %.4f %.4f\n" % (*p, *c))
        for t in triangles:
            f.write("f %d %d %d\n" % tuple(i + 1 for i in t))


def write_glb(path, positions, colors, triangles):
    pos = b"".join(struct.pack("<3f", *p) for p in positions)
    col = b"".join(struct.pack("<3f", *c) for c in colors)
    idx = b"".join(struct.pack("<3I", *t) for t in triangles)
    blob = pos + col + idx
    mins = [min(p[k] for p in positions) for k in range(3)]
    maxs = [max(p[k] for p in positions) for k in range(3)]
    doc = {
        "asset": {"version": "2.0", "generator": "dm-prep fixture"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "COLOR_0": 1}, "indices": 2}]}],
        "buffers": [{"byteLength": len(blob)}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": len(pos), "target": 34962},
            {"buffer": 0, "byteOffset": len(pos), "byteLength": len(col), "target": 34962},
            {"buffer": 0, "byteOffset": len(pos) + len(col), "byteLength": len(idx), "target": 34963},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(positions), "type": "VEC3", "min": mins, "max": maxs},
            {"bufferView": 1, "componentType": 5126, "count": len(colors), "type": "VEC3"},
            {"bufferView": 2, "componentType": 5125, "count": 3 * len(triangles), "type": "SCALAR"},
        ],
    }
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    blob += b"\0" * (-len(blob) % 4)
    total = 12 + 8 + len(text) + 8 + len(blob)
    with open(path, "wb") as f:
        f.write(struct.pack("<4sII", b"glTF", 2, total))
        f.write(struct.pack("<I4s", len(text), b"JSON") + text)
        f.write(struct.pack("<I4s", len(blob), b"BIN\0") + blob)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="fixtures/meshes")
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    positions, colors, triangles = build()
    write_obj(os.path.join(args.out, "textured_box.obj"), positions, colors, triangles)
    write_glb(os.path.join(args.out, "textured_box.glb"), positions, colors, triangles)
    for name in ("textured_box.obj", "textured_box.glb"):
        print(name, os.path.getsize(os.path.join(args.out, name)), "bytes")


if __name__ == "__main__":
    main()
