#!/usr/bin/env python3
"""Writes the fuzz seed corpus (fuzz/corpus/) that is not copied from
fixtures/ or written by the tools: tiny OBJ, glTF-binary and PLY meshes,
playground commands, and the pickle and manifest seeds. The bundle and
model seeds come from dm-synth and dm-fit (fuzz/README.md).

    python3 fuzz/make_corpus.py
"""
import json
import pathlib
import shutil
import struct

ROOT = pathlib.Path(__file__).resolve().parent.parent
CORPUS = ROOT / "fuzz" / "corpus"


def write(path, data):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data if isinstance(data, bytes) else data.encode())


def obj():
    return (
        "# a tetrahedron with texture coordinates and normals\n"
        "mtllib none.mtl\no tet\n"
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
        "vt 0 0\nvt 1 0\nvt 0 1\n"
        "vn 0 0 -1\nvn 0 -1 0\nvn -1 0 0\nvn 0.577 0.577 0.577\n"
        "usemtl none\n"
        "f 1/1/1 3/3/1 2/2/1\nf 1/1/2 2/2/2 4/3/2\nf 1/1/3 4/3/3 3/2/3\nf 2/1/4 3/2/4 4/3/4\n"
    )


def glb():
    positions = [0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1]
    indices = [0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3]
    pos = struct.pack("<12f", *positions)
    idx = struct.pack("<12H", *indices)
    binary = pos + idx
    gltf = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(binary)}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": len(pos), "target": 34962},
            {"buffer": 0, "byteOffset": len(pos), "byteLength": len(idx), "target": 34963},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
             "min": [0, 0, 0], "max": [1, 1, 1]},
            {"bufferView": 1, "componentType": 5123, "count": 12, "type": "SCALAR"},
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
        "scene": 0,
    }
    text = json.dumps(gltf).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    chunks = struct.pack("<I4s", len(text), b"JSON") + text + struct.pack("<I4s", len(binary), b"BIN\0") + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def ply_gaussians():
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 3\n"
    header += "".join(f"property float {n}\n" for n in names) + "end_header\n"
    rows = b""
    for i in range(3):
        rows += struct.pack("<17f", 0.1 * i, 0.0, 0.2, 0, 0, 0, 0.5, -0.2, 0.1, 1.0,
                            -4.0, -4.5, -5.0, 1.0, 0.0, 0.0, 0.0)
    return header.encode() + rows


def ply_points():
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 4\n"
    header += "property float x\nproperty float y\nproperty float z\nend_header\n"
    return header.encode() + struct.pack("<12f", 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1)


def main():
    write(CORPUS / "obj" / "tetrahedron.obj", obj())
    write(CORPUS / "glb" / "tetrahedron.glb", glb())
    write(CORPUS / "ply" / "gaussians.ply", ply_gaussians())
    write(CORPUS / "ply" / "points.ply", ply_points())
    commands = [
        {"type": "grab", "hand": 0, "origin": [0, 0, 1], "direction": [0, 0, -1]},
        {"type": "release", "hand": 1},
        {"type": "hand_velocity", "hand": 0, "velocity": [0.1, 0, 0.2]},
        {"type": "material", "e_scale": 2.0, "nu": 0.3, "damping": 5.0},
        {"type": "material", "e_scale": 0.5, "nu": None, "damping": 1.0},
        {"type": "reset"},
        {"type": "record_start"},
    ]
    for i, command in enumerate(commands):
        write(CORPUS / "play-command" / f"{i:02}.json", json.dumps(command))
    for source in sorted((ROOT / "fixtures" / "pickles").glob("*.pkl")) + [
        ROOT / "fixtures" / "phystwin_tiny" / "calibrate.pkl",
        ROOT / "fixtures" / "phystwin_tiny" / "final_data.pkl",
    ]:
        write(CORPUS / "pickle" / source.name, source.read_bytes())
    for source in sorted((ROOT / "models_manifest").glob("*.json")):
        write(CORPUS / "manifest" / source.name, source.read_bytes())


if __name__ == "__main__":
    main()
