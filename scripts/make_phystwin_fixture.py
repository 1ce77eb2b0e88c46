#!/usr/bin/env python3
"""Writes the tiny synthetic PhysTwin case and the unpickler test pickles.

    python3 scripts/make_phystwin_fixture.py --out fixtures

creates
    fixtures/phystwin_tiny/           a PhysTwin case (method.md section 10)
    fixtures/phystwin_bad/*.pkl       malformed stand-ins for final_data.pkl
    fixtures/pickles/*.pkl            numpy pickles for every dtype, order and protocol

Only numpy and the standard library are needed (PNGs are encoded here with
zlib). Every value follows a closed formula that the Rust tests
(crates/dm-numpy/tests/, crates/dm-phystwin/tests/) recompute, so they
check the import value by value; change a formula here and there together. The output is deterministic.
"""

import argparse
import json
import math
import pickle
import shutil
import struct
import zlib
from pathlib import Path

import numpy as np

CAMERAS = 3
FRAMES = 5
WIDTH, HEIGHT = 32, 24
OBJECT_POINTS = 24
CONTROLLER_POINTS = 30
SURFACE_POINTS = 10
INTERIOR_POINTS = 4
FPS = 30
OBJECT_MASK_ID, HAND_MASK_ID = 0, 1


def write_png(path, pixels):
    """8-bit greyscale (H, W) or RGB (H, W, 3) PNG, no filtering."""
    pixels = np.ascontiguousarray(pixels, dtype=np.uint8)
    height, width = pixels.shape[:2]
    colour_type = 2 if pixels.ndim == 3 else 0
    rows = b"".join(b"\x00" + pixels[y].tobytes() for y in range(height))

    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 8, colour_type, 0, 0, 0)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows, 9))
        + chunk(b"IEND", b"")
    )


def object_points():
    t = np.arange(FRAMES)[:, None]
    n = np.arange(OBJECT_POINTS)[None, :]
    x = -0.05 + 0.02 * (n % 6) + 0.0 * t
    y = -0.03 + 0.02 * (n // 6) + 0.0 * t
    z = -0.02 - 0.01 * t - 0.001 * n
    return np.stack([x, y, z], axis=-1).astype(np.float32)


def object_colors():
    t = np.arange(FRAMES)[:, None]
    n = np.arange(OBJECT_POINTS)[None, :]
    r = n / OBJECT_POINTS + 0.0 * t
    g = t / FRAMES + 0.0 * n
    b = np.full_like(r, 0.5)
    return np.stack([r, g, b], axis=-1).astype(np.float32)


def visibilities():
    t = np.arange(FRAMES)[:, None]
    n = np.arange(OBJECT_POINTS)[None, :]
    return (n + t) % 5 != 0


def motions_valid():
    t = np.arange(FRAMES)[:, None]
    n = np.arange(OBJECT_POINTS)[None, :]
    return (n * t) % 4 != 1


def controller_points():
    t = np.arange(FRAMES)[:, None]
    m = np.arange(CONTROLLER_POINTS)[None, :]
    x = 0.1 + 0.001 * m + 0.0 * t
    y = 0.002 * m + 0.0 * t
    z = -0.05 - 0.01 * t + 0.0 * m
    return np.stack([x, y, z], axis=-1).astype(np.float64)


def surface_points():
    k = np.arange(SURFACE_POINTS)
    return np.stack([-0.05 + 0.01 * k, np.full(SURFACE_POINTS, 0.05), np.full(SURFACE_POINTS, -0.02)], axis=-1)


def interior_points():
    k = np.arange(INTERIOR_POINTS)
    return np.stack([0.01 * k, np.zeros(INTERIOR_POINTS), np.full(INTERIOR_POINTS, -0.01)], axis=-1).astype(np.float32)


def camera_to_world(camera):
    """OpenCV camera above the table (world up is -z) looking at the object."""
    angle = 2.0 * math.pi * camera / CAMERAS
    position = np.array([0.3 * math.cos(angle), 0.3 * math.sin(angle), -0.6])
    forward = np.array([0.0, 0.0, -0.03]) - position
    forward /= np.linalg.norm(forward)
    down = np.array([0.0, 0.0, 1.0])
    right = np.cross(down, forward)
    right /= np.linalg.norm(right)
    image_down = np.cross(forward, right)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = right, image_down, forward, position
    return matrix


def intrinsics(camera):
    return [[20.0 + camera, 0.0, WIDTH / 2], [0.0, 21.0 + camera, HEIGHT / 2], [0.0, 0.0, 1.0]]


def colour_image(camera, frame):
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    return np.stack([(x * 7 + frame * 11) % 256, (y * 9 + camera * 40) % 256, (x + y + 3 * frame + camera) % 256], axis=-1)


def depth_image(camera, frame):
    """uint16 millimetres; pixel (0, 0) has no measurement."""
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    depth = (500 + 10 * frame + 100 * camera + 3 * x + 5 * y).astype(np.uint16)
    depth[0, 0] = 0
    return depth


def object_mask(camera, frame):
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    return np.where((x >= 8 + frame) & (x < 20 + frame) & (y >= 6 + camera) & (y < 16), 255, 0)


def hand_mask(camera, frame):
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    return np.where((x >= 24) & (y >= 2 * frame) & (y < 2 * frame + 4 + camera), 1, 0)


def final_data():
    return {
        "object_points": object_points(),
        "object_colors": object_colors(),
        "object_visibilities": visibilities(),
        "object_motions_valid": motions_valid(),
        "controller_mask": np.ones(CONTROLLER_POINTS, dtype=bool),
        "controller_points": controller_points(),
        "surface_points": surface_points(),
        "interior_points": interior_points(),
    }


def write_case(case):
    if case.exists():
        shutil.rmtree(case)
    case.mkdir(parents=True)
    with open(case / "final_data.pkl", "wb") as f:
        pickle.dump(final_data(), f, protocol=4)
    with open(case / "calibrate.pkl", "wb") as f:
        pickle.dump([camera_to_world(c) for c in range(CAMERAS)], f, protocol=5)
    metadata = {
        "intrinsics": [intrinsics(c) for c in range(CAMERAS)],
        "serial_numbers": [f"fixture{c}" for c in range(CAMERAS)],
        "fps": FPS,
        "WH": [WIDTH, HEIGHT],
        "frame_num": FRAMES,
        "start_step": 0,
        "end_step": FRAMES,
    }
    (case / "metadata.json").write_text(json.dumps(metadata, indent=1))
    train_end = int(0.7 * FRAMES)
    (case / "split.json").write_text(json.dumps({"frame_len": FRAMES, "train": [0, train_end], "test": [train_end, FRAMES]}))
    for camera in range(CAMERAS):
        (case / "mask").mkdir(exist_ok=True)
        (case / "mask" / f"mask_info_{camera}.json").write_text(json.dumps({str(OBJECT_MASK_ID): "toy", str(HAND_MASK_ID): "hand"}))
        for frame in range(FRAMES):
            write_png(case / "color" / str(camera) / f"{frame}.png", colour_image(camera, frame))
            depth_dir = case / "depth" / str(camera)
            depth_dir.mkdir(parents=True, exist_ok=True)
            np.save(depth_dir / f"{frame}.npy", depth_image(camera, frame))
            write_png(case / "mask" / str(camera) / str(OBJECT_MASK_ID) / f"{frame}.png", object_mask(camera, frame))
            write_png(case / "mask" / str(camera) / str(HAND_MASK_ID) / f"{frame}.png", hand_mask(camera, frame))


def write_bad(bad):
    """Malformed replacements for final_data.pkl."""
    if bad.exists():
        shutil.rmtree(bad)
    bad.mkdir(parents=True)

    def dump(name, data, protocol=4):
        with open(bad / name, "wb") as f:
            pickle.dump(data, f, protocol=protocol)

    data = final_data()
    del data["object_visibilities"]
    dump("missing_key.pkl", data)
    data = final_data()
    data["object_points"] = data["object_points"].astype(np.complex64)
    dump("wrong_dtype.pkl", data)
    data = final_data()
    data["controller_points"] = data["controller_points"].astype(np.int64)
    dump("int_points.pkl", data)
    data = final_data()
    data["object_points"] = data["object_points"][:, :, :2].copy()
    dump("wrong_shape.pkl", data)
    data = final_data()
    data["object_visibilities"] = data["object_visibilities"][:-1].copy()
    dump("frame_mismatch.pkl", data)
    data = final_data()
    data["object_points"][2, 3, 1] = np.nan
    dump("nan_point.pkl", data)
    full = pickle.dumps(final_data(), protocol=4)
    (bad / "truncated.pkl").write_bytes(full[: len(full) // 2])
    dump("not_a_dict.pkl", [1, 2, 3])


DTYPES = ["f4", "f8", "i4", "i8", "u1", "u2", "b1", "i2", "u4", "u8", "i1"]


def typed_array(code, shape):
    values = np.arange(int(np.prod(shape))).reshape(shape)
    if code == "b1":
        return values % 3 == 0
    if code.startswith("f"):
        return (values * 0.5 - 3.0).astype(code)
    if code.startswith("i"):
        return (values - 5).astype(code)
    return values.astype(code)


def unpickler_payload():
    """Every dtype in C and Fortran order, big-endian, 0-d and empty arrays, scalars."""
    payload = {}
    for code in DTYPES:
        payload[f"{code}_c"] = typed_array(code, (2, 3, 4))
        payload[f"{code}_f"] = np.asfortranarray(typed_array(code, (2, 3, 4)))
    payload["f8_big"] = typed_array("f8", (3, 2)).astype(">f8")
    payload["u2_big_f"] = np.asfortranarray(typed_array("u2", (3, 2)).astype(">u2"))
    payload["f4_empty"] = np.zeros((0, 3), dtype=np.float32)
    payload["f4_0d"] = np.array(2.5, dtype=np.float32)
    payload["scalar_f8"] = np.float64(1.25)
    payload["scalar_i4"] = np.int32(-7)
    payload["scalar_b"] = np.bool_(True)
    payload["py"] = [None, True, False, 3, -300, 70000, 2**40, -(2**62), 1.5, "héllo", b"raw", (1, "two")]
    payload["nested"] = {"list": [typed_array("f4", (2,)), typed_array("f4", (2,))]}
    return payload


def write_pickles(directory):
    if directory.exists():
        shutil.rmtree(directory)
    directory.mkdir(parents=True)
    payload = unpickler_payload()
    for protocol in (2, 3, 4, 5):
        (directory / f"arrays_p{protocol}.pkl").write_bytes(pickle.dumps(payload, protocol=protocol))
    # numpy < 2 names its module numpy.core; protocol 2 spells globals as text lines.
    legacy = pickle.dumps(payload, protocol=2).replace(b"numpy._core", b"numpy.core")
    assert pickle.loads(legacy)["f4_c"].dtype == np.float32
    (directory / "arrays_p2_numpy1.pkl").write_bytes(legacy)
    shared = typed_array("f8", (2, 2))
    (directory / "shared_p4.pkl").write_bytes(pickle.dumps([shared, shared, {"again": shared}], protocol=4))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("fixtures"))
    args = parser.parse_args()
    write_case(args.out / "phystwin_tiny")
    write_bad(args.out / "phystwin_bad")
    write_pickles(args.out / "pickles")


if __name__ == "__main__":
    main()
