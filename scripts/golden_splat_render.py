#!/usr/bin/env python3
"""Golden reference render for dm-splat.

An independent, deliberately plain implementation of the same equations as
crates/dm-splat (EWA projection as in 3DGS, 16x16 tile membership, front-to-back
compositing with the 1/255 alpha threshold, the 0.99 alpha clamp and the 1e-4
transmittance stop), evaluated per pixel by brute force: for every pixel, every
Gaussian whose 3-sigma square touches the pixel's tile, sorted by (depth, index).

Writes fixtures/golden/splat_render.json: the configuration (camera, settings,
Gaussians) and the expected image and alpha. The Rust test
crates/dm-splat/tests/golden.rs reads the configuration from the same file.

    python3 scripts/golden_splat_render.py          # numpy only
"""

import json
import math
import os

import numpy as np

TILE = 16
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
CLAMP_MARGIN = 0.3

WIDTH, HEIGHT = 40, 32


def look_at(eye, target, up, width, height, fov_deg):
    """OpenCV-axes camera (x right, y down, z forward) looking at target."""
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up / np.linalg.norm(up))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rot = np.stack([right, down, forward])
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = -rot @ eye
    focal = 0.5 * height / math.tan(math.radians(fov_deg) / 2)
    return dict(width=width, height=height, fx=focal, fy=focal,
                cx=width / 2, cy=height / 2, world_to_camera=m.tolist())


def quat_to_rot(q):
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def project(cam, settings, mean, log_scale, quat):
    m = np.asarray(cam["world_to_camera"])
    W, t = m[:3, :3], m[:3, 3]
    x, y, z = W @ np.asarray(mean) + t
    if not z > settings["near_plane"]:
        return None
    fx, fy, cx, cy = cam["fx"], cam["fy"], cam["cx"], cam["cy"]
    w, h = cam["width"], cam["height"]
    tan_x, tan_y = 0.5 * w / fx, 0.5 * h / fy
    lx = (-(cx / fx + CLAMP_MARGIN * tan_x), (w - cx) / fx + CLAMP_MARGIN * tan_x)
    ly = (-(cy / fy + CLAMP_MARGIN * tan_y), (h - cy) / fy + CLAMP_MARGIN * tan_y)
    tx = z * min(max(x / z, lx[0]), lx[1])
    ty = z * min(max(y / z, ly[0]), ly[1])
    J = np.array([[fx / z, 0, -fx * tx / z**2], [0, fy / z, -fy * ty / z**2]])
    M = quat_to_rot(quat) @ np.diag(np.exp(log_scale))
    cov2 = J @ W @ (M @ M.T) @ W.T @ J.T + settings["low_pass"] * np.eye(2)
    det = np.linalg.det(cov2)
    if not det > 0:
        return None
    conic = np.linalg.inv(cov2)
    mid = 0.5 * (cov2[0, 0] + cov2[1, 1])
    lam = mid + math.sqrt(max(0.1, mid * mid - det))
    radius = math.ceil(3 * math.sqrt(lam))
    u, v = fx * x / z + cx, fy * y / z + cy
    tiles_x, tiles_y = -(-w // TILE), -(-h // TILE)
    clip = lambda val, n: int(min(max(val, 0), n))  # noqa: E731
    rect = (clip(math.floor((u - radius) / TILE), tiles_x), clip(math.floor((v - radius) / TILE), tiles_y),
            clip(math.ceil((u + radius) / TILE), tiles_x), clip(math.ceil((v + radius) / TILE), tiles_y))
    if rect[0] >= rect[2] or rect[1] >= rect[3]:
        return None
    return dict(mean2d=(u, v), conic=conic, depth=z, rect=rect)


def render(cam, settings, g):
    n = len(g["means"])
    proj = [project(cam, settings, g["means"][i], g["log_scales"][i], g["rotations"][i]) for i in range(n)]
    opacity = [1 / (1 + math.exp(-lo)) for lo in g["opacity_logits"]]
    w, h = cam["width"], cam["height"]
    image = np.zeros((h, w, 3))
    alpha_img = np.zeros((h, w))
    bg = np.asarray(settings["background"])
    stopped_early = [0]
    for py in range(h):
        for px in range(w):
            tx, ty = px // TILE, py // TILE
            cand = [i for i in range(n) if proj[i] is not None
                    and proj[i]["rect"][0] <= tx < proj[i]["rect"][2]
                    and proj[i]["rect"][1] <= ty < proj[i]["rect"][3]]
            cand.sort(key=lambda i: (proj[i]["depth"], i))
            T = 1.0
            colour = np.zeros(3)
            centre = np.array([px + 0.5, py + 0.5])
            for i in cand:
                d = centre - np.asarray(proj[i]["mean2d"])
                power = -0.5 * d @ proj[i]["conic"] @ d
                if power > 0:
                    continue
                a = min(ALPHA_MAX, opacity[i] * math.exp(power))
                if a < ALPHA_MIN:
                    continue
                if T * (1 - a) < T_MIN:
                    stopped_early[0] += 1
                    break
                colour += np.asarray(g["colors"][i]) * a * T
                T *= 1 - a
            image[py, px] = colour + T * bg
            alpha_img[py, px] = 1 - T
    return image, alpha_img, stopped_early[0]


def random_quat(rng):
    q = rng.normal(size=4)
    return (q / np.linalg.norm(q)).tolist()


def configuration():
    rng = np.random.RandomState(7)
    cam = look_at([0.45, -0.55, 0.3], [0.0, 0.0, 0.05], [0, 0, 1], WIDTH, HEIGHT, 45.0)
    settings = dict(background=[0.1, 0.2, 0.3], near_plane=0.01, low_pass=0.3)
    g = dict(means=[], log_scales=[], rotations=[], opacity_logits=[], colors=[])

    def add(mean, log_scale, quat, opacity, colour):
        g["means"].append([float(v) for v in mean])
        g["log_scales"].append([float(v) for v in log_scale])
        g["rotations"].append([float(v) for v in quat])
        g["opacity_logits"].append(float(math.log(opacity / (1 - opacity))))
        g["colors"].append([float(v) for v in colour])

    # A random cloud of anisotropic splats around the target.
    for _ in range(20):
        add(rng.uniform(-0.12, 0.12, 3) + [0, 0, 0.05], np.log(rng.uniform(0.01, 0.06, 3)),
            random_quat(rng), rng.uniform(0.2, 0.9), rng.uniform(0, 1, 3))
    # A stack of nearly opaque splats along the view ray through the target,
    # so some pixels stop early on the transmittance bound.
    eye = np.array([0.45, -0.55, 0.3])
    ray = np.array([0.0, 0.0, 0.05]) - eye
    for k in range(5):
        add(eye + ray * (0.8 + 0.05 * k), np.log([0.03, 0.03, 0.03]), [1, 0, 0, 0], 0.95,
            rng.uniform(0, 1, 3))
    # One opaque enough to hit the 0.99 clamp; one needle; one almost invisible;
    # one behind the camera; one far outside the view (x/z clamp path, culled).
    add([0.05, 0.05, 0.1], np.log([0.02, 0.02, 0.02]), random_quat(rng), 0.999, [1, 1, 1])
    add([-0.05, 0.0, 0.0], np.log([0.08, 0.002, 0.002]), random_quat(rng), 0.8, [0.9, 0.1, 0.1])
    add([0.0, 0.05, 0.0], np.log([0.03, 0.03, 0.03]), random_quat(rng), 0.002, [0, 1, 0])
    add((eye + (eye - np.array([0.0, 0.0, 0.05])) * 0.5).tolist(), np.log([0.05] * 3), [1, 0, 0, 0], 0.9, [1, 0, 1])
    add([3.0, 3.0, 0.0], np.log([0.05] * 3), [1, 0, 0, 0], 0.9, [1, 1, 0])
    return cam, settings, g


def main():
    cam, settings, g = configuration()
    image, alpha, stopped = render(cam, settings, g)
    out = dict(
        description="dm-splat golden render; written by scripts/golden_splat_render.py",
        camera=cam, settings=settings, gaussians=g,
        image=image.reshape(-1, 3).tolist(), alpha=alpha.reshape(-1).tolist(),
    )
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    path = os.path.join(root, "fixtures", "golden", "splat_render.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        json.dump(out, f)
    print(f"wrote {path}: {cam['width']}x{cam['height']}, {len(g['means'])} Gaussians, "
          f"mean alpha {alpha.mean():.3f}, pixels stopped early "
          f"{stopped}, alpha-clamped splat present")


if __name__ == "__main__":
    main()
