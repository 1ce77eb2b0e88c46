#!/usr/bin/env python3
"""Does a base fit's material field absorb a hidden density gradient?
(docs/RESULTS.md, diagnosis.)

For each evaluation scene directory (`diagnose_eval`'s or `oracle_gain`'s
OUT_DIR/hiddenSEED[SUFFIX], holding `scene/`, `scene.truth.json` and the
base fit `model/`), reads the fitted Young's modulus per particle and
reports, along the truth's density axis oriented towards the heavy end,
the correlation of log E with the position and the ratio of the median E
in the heavy third to that in the light third. Scenes with another
effect report the largest such ratio over the world axes (unsigned), as a
control for how much the fitted field varies anyway:

    python3 scripts/material_along_density_axis.py /tmp/s26/eval/hidden10*-p3000

The model's particles are the bundle's surface points followed by its
interior points (dm-model's `WorldModel::from_bundle`).
"""
import json
import pathlib
import sys

import numpy as np


def thirds_ratio(x, youngs):
    """Median E of the top third of `x` (scaled to 0–1) over the bottom third's."""
    x = (x - x.min()) / np.ptp(x)
    return np.median(youngs[x > 2 / 3]) / np.median(youngs[x < 1 / 3])


def main():
    for directory in map(pathlib.Path, sys.argv[1:]):
        particles = directory / "scene" / "particles"
        youngs_path = directory / "model" / "youngs_pa.npy"
        if not youngs_path.is_file():
            print(f"{directory}: no fitted model", file=sys.stderr)
            continue
        points = np.concatenate(
            [np.load(particles / "surface_points.npy"), np.load(particles / "interior_points.npy")]
        ).reshape(-1, 3)
        youngs = np.load(youngs_path)
        if len(points) != len(youngs):
            sys.exit(f"{youngs_path}: {len(youngs)} values for {len(points)} bundle particles")
        truth = json.loads((directory / "scene.truth.json").read_text())
        effect = truth["effect"]
        preset = truth["config"]["preset"]
        if effect and effect["name"] == "density_variation":
            params = effect["params"]
            towards_heavy = points[:, params["axis"]] * (1 if params["heavy_at_max"] else -1)
            corr = np.corrcoef(towards_heavy, np.log(youngs))[0, 1]
            print(
                f"{directory.name}: {preset}, density excess {params['heavy_end_excess']:.2f}: "
                f"corr(towards heavy end, log E) {corr:+.2f}, "
                f"E heavy third / light third {thirds_ratio(towards_heavy, youngs):.2f}"
            )
        else:
            ratios = [
                thirds_ratio(points[:, axis], youngs)
                for axis in range(3)
                if np.ptp(points[:, axis]) > 0.02
            ]
            largest = max(max(r, 1 / r) for r in ratios)
            name = effect["name"] if effect else "none"
            print(f"{directory.name}: {preset}, {name}: largest end-to-end E ratio {largest:.2f}")


if __name__ == "__main__":
    main()
