#!/usr/bin/env python3
"""What dm-fit's residual check makes of a suite's residual variants.

Reads a suite's `suite.json` (dm-eval --suite OUT) whose residual variants ran
with the check off (`--residual-min-gain 0`) beside a `none` variant, and
applies the check as dm-fit does: a network is kept only if it lowers the
training split's Track error by at least MIN_GAIN against `none`; otherwise
the fit is the `none` fit. Prints per scene the held-out Track error each
variant ends with, then their geometric means against `none` and the first
variant. Usage:

    python3 scripts/residual_check_outcome.py OUT/suite.json fresh continued [--min-gain 0.17]
"""
import argparse
import json
import math


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("suite_json")
    ap.add_argument("variants", nargs="+")
    ap.add_argument("--min-gain", type=float, default=0.17)
    args = ap.parse_args()
    runs = {}
    for run in json.load(open(args.suite_json))["runs"]:
        if run["status"] != "ok":
            raise SystemExit(f"{run['scene']} / {run['variant']}: {run['status']}")
        runs[(run["scene"], run["variant"])] = run
    scenes = sorted({scene for scene, _ in runs})
    rows = []
    print("held-out Track (mm) after the check; (gain on the training split, kept or dropped)\n")
    print("| scene | none | " + " | ".join(args.variants) + " |")
    print("|---|---:|" + "---:|" * len(args.variants))
    for scene in scenes:
        none = runs[(scene, "none")]
        cells, row = [], [none["test"]["track"]]
        for variant in args.variants:
            run = runs[(scene, variant)]
            gain = 1.0 - run["train"]["track"] / none["train"]["track"]
            kept = gain >= args.min_gain
            held_out = (run if kept else none)["test"]["track"]
            row.append(held_out)
            cells.append(f"{1e3 * held_out:.2f} ({100 * gain:.1f} %, {'kept' if kept else 'dropped'})")
        rows.append(row)
        print(f"| {scene} | {1e3 * none['test']['track']:.2f} | " + " | ".join(cells) + " |")

    def geomean_change(i, j):
        return 100 * (math.exp(sum(math.log(r[j] / r[i]) for r in rows) / len(rows)) - 1)

    print()
    for j, variant in enumerate(args.variants, start=1):
        line = f"{variant}: {geomean_change(0, j):+.1f} % against none"
        if j > 1:
            better = sum(r[j] < r[1] for r in rows)
            worse = sum(r[j] > r[1] for r in rows)
            line += (
                f", {geomean_change(1, j):+.1f} % against {args.variants[0]}"
                f" (lower on {better}, higher on {worse}, the same on {len(rows) - better - worse} of {len(rows)})"
            )
        print(line)


if __name__ == "__main__":
    main()
