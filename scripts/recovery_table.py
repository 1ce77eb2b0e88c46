#!/usr/bin/env python3
"""Material-recovery table for docs/RESULTS.md.

For each preset: synthesise a scene with a homogeneous material, fit it,
roll out the untrained and the fitted model, and tabulate truth vs fitted
material and the held-out errors. Usage (from the repository root, after
`cargo build --release --workspace --bins`):

    python3 scripts/recovery_table.py OUT_DIR [--action stretch] [--frames 72] [--seed 5]

The fit is physics only (`--residual none`): this table is about what the
material and actuator stages recover.
"""
import argparse
import json
import pathlib
import subprocess
import time

BIN = pathlib.Path("target/release")


def run(*args):
    subprocess.run([str(a) for a in args], check=True, stdout=subprocess.DEVNULL)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=pathlib.Path)
    ap.add_argument("--frames", type=int, default=72)
    ap.add_argument("--action", default="stretch", choices=["lift", "push", "stretch", "twist"])
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--fit", default="--residual none")
    ap.add_argument("--reuse", action="store_true", help="only tabulate existing outputs")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for preset in ["rope", "cloth", "toy"]:
        scene, model = a.out / preset, a.out / f"{preset}_model"
        if not a.reuse:
            run(BIN / "dm-synth", "--preset", preset, "--seed", a.seed, "--action", a.action,
                "--homogeneous", "--frames", a.frames, "--out", scene)
            run(BIN / "dm-fit", scene, "--out", model, *a.fit.split())
            run(BIN / "dm-sim", scene, "--residual", "none", "--out", a.out / f"{preset}_u")
            run(BIN / "dm-sim", scene, "--model-dir", model, "--out", a.out / f"{preset}_f")
        truth = json.loads((a.out / f"{preset}.truth.json").read_text())
        report = json.loads((model / "fit_report.json").read_text())
        untrained = json.loads((a.out / f"{preset}_u" / "summary.json").read_text())
        fitted = json.loads((a.out / f"{preset}_f" / "summary.json").read_text())
        e_t, nu_t = truth["material"]["E_pa"], truth["material"]["nu"]
        e_f, nu_f = report["material"]["E_median_pa"], report["material"]["nu_median"]
        c_u, c_f = untrained["chamfer_m"]["test"], fitted["chamfer_m"]["test"]
        rows.append(
            f"| {preset} | {e_t:.3g} | {e_f:.3g} ({100 * (e_f / e_t - 1):+.0f} %) | {nu_t:.2f} | {nu_f:.2f} "
            f"({nu_f - nu_t:+.2f}) | {1e3 * c_u:.1f} → {1e3 * c_f:.1f} mm ({c_u / c_f:.1f}×) | "
            f"{1e3 * untrained['track_error_m']['test']:.1f} → {1e3 * fitted['track_error_m']['test']:.1f} mm | "
            f"{report['seconds']:.0f} s |"
        )
    print("| preset | truth E (Pa) | fitted E | truth ν | fitted ν | held-out Chamfer untrained → fitted | held-out track | fit time |")
    print("|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
