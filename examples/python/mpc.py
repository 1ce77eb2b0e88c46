"""Bring an object to a goal shape by re-planning from its simulation every
few frames (model-predictive control), against one plan carried out open
loop, and plot both.

    python examples/python/mpc.py out/demo/model out/demo/scene --out mpc.png

The goal is one of the named shapes of the object's category (docs/plan.md),
due at frame --frames. Every --every frames the hands' motion is planned
again from where the simulation is, over the frames still left; the open
loop plans once and carries the whole plan out. Every hand anchor moves on
its own, or with --rigid-hands each of the bundle's hands moves its anchors
together (a gripper's fingers; translation only). The plot shows the Chamfer
distance to the goal per frame for both, and the object's last frame.
"""

import argparse
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import deformmaster as dm

DEFAULT_GOALS = {"linear": "straighten", "planar": "fold", "volumetric": "place"}


def carry_out(sim, hands, points):
    """Steps `sim` along `hands` ((K, H, 3)); the Chamfer to `points` after each frame."""
    distances = []
    for to in hands:
        sim.step(to)
        distances.append(sim.chamfer_to(points))
    return distances


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", help="model directory (dm-fit's output)")
    parser.add_argument("bundle", help="the scene bundle the model was fitted on")
    parser.add_argument("--goal", help="a named goal shape (default: the category's first)")
    parser.add_argument("--frames", type=int, default=60, help="frames until the goal is due")
    parser.add_argument("--every", type=int, default=20, help="frames carried out between plans")
    parser.add_argument("--samples", type=int, default=10, help="MPPI samples per iteration")
    parser.add_argument("--iterations", type=int, default=3, help="MPPI iterations per plan")
    parser.add_argument("--gradient-iters", type=int, default=3, help="gradient steps per plan")
    parser.add_argument("--rigid-hands", action="store_true",
                        help="move each of the bundle's hands as one rigid hand")
    parser.add_argument("--exact", action="store_true",
                        help="plan in the model's own world, not the coarse one (slower)")
    parser.add_argument("--out", default="mpc.png", help="the plot (PNG)")
    args = parser.parse_args()

    bundle = dm.read_bundle(args.bundle)
    model = dm.load_model(args.model)
    goal = args.goal or DEFAULT_GOALS[bundle.meta["category"]]
    points, particles = model.goal(goal, bundle)
    search = dict(samples=args.samples, iterations=args.iterations,
                  gradient_iters=args.gradient_iters, exact=args.exact,
                  rigid_hands=bundle.hand_ranges if args.rigid_hands else None)

    clock = time.perf_counter()
    mpc = model.simulation(bundle.hand_anchors(0))
    start = mpc.chamfer_to(points)
    mpc_distances, plan_frames = [start], []
    for done in range(0, args.frames, args.every):
        plan = mpc.plan(points, particles, horizon=args.frames - done, **search)
        plan_frames.append(done)
        mpc_distances += carry_out(mpc, plan["hands"][1 : args.every + 1], points)
    mpc_seconds = time.perf_counter() - clock

    clock = time.perf_counter()
    open_loop = model.simulation(bundle.hand_anchors(0))
    plan = open_loop.plan(points, particles, horizon=args.frames, **search)
    open_distances = [start] + carry_out(open_loop, plan["hands"][1:], points)
    open_seconds = time.perf_counter() - clock
    planned = plan["record"]["planned"]["final_chamfer_m"]

    t = np.arange(args.frames + 1) * model.frame_dt
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    axes[0].plot(t, 1e3 * np.array(mpc_distances), label=f"re-planned every {args.every} frames")
    axes[0].plot(t, 1e3 * np.array(open_distances), label="planned once (open loop)")
    for frame in plan_frames:
        axes[0].axvline(frame * model.frame_dt, color="0.85", zorder=0)
    axes[0].set(xlabel="time (s)", ylabel="Chamfer to the goal (mm)", title=f"goal: {goal}")
    axes[0].legend()
    camera = bundle.camera(0)
    axes[1].imshow(mpc.render(camera)["rgb"])
    axes[1].set_title(f"re-planned: frame {args.frames}")
    axes[1].axis("off")
    fig.tight_layout()
    fig.savefig(args.out, dpi=100)
    print(f"wrote {args.out}: goal {goal}, Chamfer {1e3 * start:.1f} mm at the start; "
          f"re-planned {len(plan_frames)} times: {1e3 * mpc_distances[-1]:.1f} mm ({mpc_seconds:.1f} s); "
          f"open loop: {1e3 * open_distances[-1]:.1f} mm, planned {1e3 * planned:.1f} "
          f"({open_seconds:.1f} s)")


if __name__ == "__main__":
    main()
