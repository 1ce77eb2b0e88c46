"""What stepping a fitted model from Python costs against dm-sim.

    python benches/python/step_overhead.py MODEL_DIR BUNDLE --dm-sim target/release/dm-sim

Runs, alternately, dm-sim's rollout of the bundle's hand track (its
summary's `seconds`: the rollout alone, without reading files) and the
same rollout from Python, stepped one frame per call and all frames in one
`step_many` call, each timed around the stepping only. Prints one JSON
line: the medians over --repeats runs and the ratios to dm-sim.
"""

import argparse
import json
import statistics
import subprocess
import tempfile
import time

import numpy as np

import deformmaster as dm


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model")
    parser.add_argument("bundle")
    parser.add_argument("--dm-sim", default="target/release/dm-sim")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()

    bundle = dm.read_bundle(args.bundle)
    model = dm.load_model(args.model)
    path = np.stack([bundle.hand_anchors(t) for t in range(1, bundle.frame_count)])
    reference = None
    times = {"dm_sim_s": [], "python_step_s": [], "python_step_many_s": []}
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory() as out:
            subprocess.run(
                [args.dm_sim, args.bundle, "--model-dir", args.model, "--out", out],
                check=True, capture_output=True,
            )
            times["dm_sim_s"].append(json.load(open(f"{out}/summary.json"))["seconds"])
            reference = np.load(f"{out}/rollout.npy")

        sim = model.simulation(bundle.hand_anchors(0))
        start = time.perf_counter()
        for hands in path:
            sim.step(hands)
        times["python_step_s"].append(time.perf_counter() - start)
        stepped = sim.positions

        sim = model.simulation(bundle.hand_anchors(0))
        start = time.perf_counter()
        many = sim.step_many(path)
        times["python_step_many_s"].append(time.perf_counter() - start)

    medians = {k: statistics.median(v) for k, v in times.items()}
    print(json.dumps({
        "frames": len(path),
        "particles": model.particle_count,
        "repeats": args.repeats,
        **{k: round(v, 4) for k, v in medians.items()},
        "step_over_dm_sim": round(medians["python_step_s"] / medians["dm_sim_s"], 4),
        "step_many_over_dm_sim": round(medians["python_step_many_s"] / medians["dm_sim_s"], 4),
        "bitwise_equal": bool(np.array_equal(stepped, reference[-1]) and np.array_equal(many, reference[1:])),
        "runs": {k: [round(x, 4) for x in v] for k, v in times.items()},
    }))


if __name__ == "__main__":
    main()
