"""Roll out a fitted world model under a scripted hand motion and plot it.

    python examples/python/rollout.py out/demo/model out/demo/scene --out rollout.png

The hands first follow the recorded clip's first frame, then lift by
--lift-m over half the clip and hold: an action the model was not fitted
on. The plot shows the object's height over time under the scripted and
the recorded motion, the recorded rollout's track error per frame, and
renders of the scripted rollout's first and last frames.
"""

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import deformmaster as dm


def crop(view, margin=12):
    """The render cropped to the object's mask, with a margin."""
    rows, cols = np.nonzero(view["mask"])
    if len(rows) == 0:
        return view["rgb"]
    top, left = max(rows.min() - margin, 0), max(cols.min() - margin, 0)
    return view["rgb"][top : rows.max() + margin, left : cols.max() + margin]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", help="model directory (dm-fit's output)")
    parser.add_argument("bundle", help="the scene bundle the model was fitted on")
    parser.add_argument("--out", default="rollout.png", help="the plot (PNG)")
    parser.add_argument("--lift-m", type=float, default=0.08, help="how far the hands lift")
    args = parser.parse_args()

    bundle = dm.read_bundle(args.bundle)
    model = dm.load_model(args.model)
    frames = bundle.frame_count
    axis = bundle.meta["up_axis"]  # "+z", "-y", ...
    up = np.zeros(3)
    up["xyz".index(axis[1])] = 1.0 if axis[0] == "+" else -1.0

    # Scripted: lift every hand along the up axis over the first half, then hold.
    start = bundle.hand_anchors(0)
    ramp = np.clip(np.arange(1, frames) / (frames // 2), 0.0, 1.0)
    scripted = start[None] + ramp[:, None, None] * args.lift_m * up[None, None]
    sim = model.simulation(start, follow_splats=model.has_splats)
    camera = bundle.camera(0)
    first_view = crop(sim.render(camera))
    lifted = np.concatenate([sim.positions[None], sim.step_many(scripted)])
    last_view = crop(sim.render(camera))

    recorded = model.rollout(bundle)
    errors = model.frame_errors(bundle, recorded)
    t = np.arange(frames) * model.frame_dt

    fig, axes = plt.subplots(2, 2, figsize=(10, 7))
    axes[0, 0].plot(t, (lifted @ up).mean(axis=1), label="scripted lift")
    axes[0, 0].plot(t, (recorded @ up).mean(axis=1), label="recorded hands")
    axes[0, 0].set(xlabel="time (s)", ylabel="mean particle height (m)", title="object height")
    axes[0, 0].legend()
    axes[0, 1].plot(t, 1e3 * errors["track_m"])
    test = bundle.meta["split"]["test"]
    axes[0, 1].axvspan(t[test[0]], t[min(test[1], frames) - 1], color="0.9", label="held-out frames")
    axes[0, 1].set(xlabel="time (s)", ylabel="track error (mm)", title="recorded action: error per frame")
    axes[0, 1].legend()
    axes[1, 0].imshow(first_view)
    axes[1, 0].set_title("scripted: first frame")
    axes[1, 1].imshow(last_view)
    axes[1, 1].set_title(f"scripted: frame {frames - 1}")
    for ax in axes[1]:
        ax.axis("off")
    fig.suptitle(f"{model!r}", fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out, dpi=100)
    print(f"wrote {args.out}: lifted {1e3 * args.lift_m:.0f} mm, object rose "
          f"{1e3 * ((lifted[-1] - lifted[0]) @ up).mean():.0f} mm")


if __name__ == "__main__":
    main()
