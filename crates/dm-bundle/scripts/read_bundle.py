#!/usr/bin/env python3
"""Read a DeformMaster scene bundle v1 with numpy + PIL only (see docs/bundle.md).

Usage: python3 read_bundle.py BUNDLE_DIR

Prints a summary and checks the basic shape contract. Documentation value only:
the Rust tests do not depend on it.
"""
import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image


def load_bundle(root):
    root = Path(root)
    meta = json.loads((root / "bundle.json").read_text())
    assert meta["format"] == "deformmaster-bundle" and meta["version"] == 1
    tracks = {name: np.load(root / "tracks" / f"{name}.npy") for name in (
        "object_points", "object_visibility", "object_motion_valid", "hand_points", "hand_visibility")}
    particles = {name: np.load(root / "particles" / f"{name}.npy") for name in (
        "surface_points", "surface_colors", "interior_points", "interior_colors")}
    return meta, tracks, particles


def load_frame(root, camera_name, frame):
    """RGB (H,W,3) uint8, depth (H,W) float32 metres with NaN = none, masks (H,W) bool."""
    view = Path(root) / "views" / camera_name
    name = f"{frame:05d}.png"
    rgb = np.asarray(Image.open(view / "rgb" / name).convert("RGB"))
    depth_mm = np.asarray(Image.open(view / "depth" / name)).astype(np.float32)
    depth_m = np.where(depth_mm > 0, depth_mm / 1000.0, np.nan).astype(np.float32)
    mask_object = np.asarray(Image.open(view / "mask_object" / name)) > 127
    mask_hand = np.asarray(Image.open(view / "mask_hand" / name)) > 127
    return rgb, depth_m, mask_object, mask_hand


def project(camera, points_world):
    """(K,3) world metres -> (K,2) pixels (u right, v down) and (K,) camera depth."""
    world_to_camera = np.asarray(camera["world_to_camera"], dtype=np.float64)
    p = points_world @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    u = camera["fx"] * p[:, 0] / p[:, 2] + camera["cx"]
    v = camera["fy"] * p[:, 1] / p[:, 2] + camera["cy"]
    return np.stack([u, v], axis=1), p[:, 2]


def main():
    root = Path(sys.argv[1])
    meta, tracks, particles = load_bundle(root)
    T = meta["frame_count"]
    T_, N, _ = tracks["object_points"].shape
    M = tracks["hand_points"].shape[1]
    assert T_ == T and tracks["object_visibility"].shape == (T, N)
    assert tracks["object_points"].dtype == np.float32 and tracks["object_visibility"].dtype == np.bool_
    print(f"{root}: {meta['category']} object, T={T} frames at {meta['fps']} fps, N={N} points, M={M} anchors")
    print(f"  split train={meta['split']['train']} test={meta['split']['test']}, up={meta['up_axis']}")
    print(f"  particles: {len(particles['surface_points'])} surface, {len(particles['interior_points'])} interior")
    for hand in meta["hands"]:
        start, end = hand["anchor_range"]
        print(f"  hand {hand['name']}: hand_points[:, {start}:{end}]")
    for camera in meta["cameras"]:
        rgb, depth_m, mask_object, mask_hand = load_frame(root, camera["name"], 0)
        assert rgb.shape == (camera["height"], camera["width"], 3)
        uv, z = project(camera, tracks["object_points"][0].astype(np.float64))
        print(f"  camera {camera['name']}: {camera['width']}x{camera['height']}, "
              f"{np.isfinite(depth_m).mean():.0%} depth coverage, {mask_object.mean():.0%} object pixels, "
              f"{(z > 0).sum()}/{N} frame-0 points in front")


if __name__ == "__main__":
    main()
