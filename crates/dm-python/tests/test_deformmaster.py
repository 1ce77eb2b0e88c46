"""The deformmaster package against the Rust tools: bundles round-trip
through the Rust reader, stepping from Python equals dm-sim's rollout
bitwise, renders, material control, errors, the GIL, Ctrl-C, fitting as
dm-fit fits and planning as dm-plan plans, the Gymnasium env, the example
script, and `device="cuda"` under the driver's emulator."""

import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

import deformmaster as dm
from conftest import REPO, run_tool


def hand_path(bundle):
    return np.stack([bundle.hand_anchors(t) for t in range(1, bundle.frame_count)])


def test_bundle_round_trips_through_the_rust_reader(tiny, tmp_path):
    bundle = dm.read_bundle(tiny["scene"])
    images = [bundle.images(c) for c in range(bundle.camera_count)]
    copy = dm.write_bundle(tmp_path / "copy", bundle.meta, bundle.tracks, bundle.particles, images)
    again = dm.read_bundle(tmp_path / "copy")
    assert again.meta == bundle.meta == copy.meta
    for group in ("tracks", "particles"):
        ours, theirs = getattr(bundle, group), getattr(again, group)
        assert ours.keys() == theirs.keys()
        for key in ours:
            assert ours[key].dtype == theirs[key].dtype, key
            assert np.array_equal(ours[key], theirs[key]), key
    for c in range(bundle.camera_count):
        written = again.images(c)
        for key, array in images[c].items():
            assert np.array_equal(array, written[key], equal_nan=key == "depth"), (c, key)
    # The npy files are the same bytes as the ones dm-synth wrote.
    for name in ("tracks/object_points.npy", "particles/surface_points.npy"):
        assert (tiny["scene"] / name).read_bytes() == (tmp_path / "copy" / name).read_bytes()
    # dm-sim (Rust) reads the Python-written bundle.
    run_tool("dm-sim", tmp_path / "copy", "--residual", "none", "--frames", "3", "--out", tmp_path / "s")


def test_write_bundle_refuses_bad_input_and_keeps_what_exists(tiny, tmp_path):
    bundle = dm.read_bundle(tiny["scene"])
    images = [bundle.images(c) for c in range(bundle.camera_count)]
    meta = bundle.meta
    bad = json.loads(json.dumps(meta))
    bad["cameras"][1]["fx"] = "wide"
    with pytest.raises(dm.BundleError, match=r"bundle\.json.*cameras\[1\]\.fx"):
        dm.write_bundle(tmp_path / "bad", bad, bundle.tracks, bundle.particles, images)
    short = [dict(images[0], rgb=images[0]["rgb"][:, :-1])] + images[1:]
    with pytest.raises(dm.BundleError, match=r"images\[0\]\[\"rgb\"\]"):
        dm.write_bundle(tmp_path / "short", meta, bundle.tracks, bundle.particles, short)
    tracks = dict(bundle.tracks)
    del tracks["hand_points"]
    with pytest.raises(dm.BundleError, match="hand_points"):
        dm.write_bundle(tmp_path / "missing", meta, tracks, bundle.particles, images)
    assert not any(tmp_path.iterdir()), "a refused write left files behind"
    # An existing bundle is replaced only when asked.
    target = tmp_path / "existing"
    shutil.copytree(tiny["scene"], target)
    before = (target / "bundle.json").read_bytes()
    with pytest.raises(dm.BundleError):
        dm.write_bundle(target, meta, bundle.tracks, bundle.particles, images)
    assert (target / "bundle.json").read_bytes() == before
    dm.write_bundle(target, meta, bundle.tracks, bundle.particles, images, overwrite=True)


def test_stepping_from_python_equals_dm_sim_bitwise(tiny):
    bundle = dm.read_bundle(tiny["scene"])
    model = dm.load_model(tiny["model"])
    reference = np.load(tiny["sim"] / "rollout.npy")
    sim = model.simulation(bundle.hand_anchors(0))
    assert np.array_equal(sim.positions, reference[0])
    for t in range(1, bundle.frame_count):
        sim.step(bundle.hand_anchors(t))
        assert np.array_equal(sim.positions, reference[t]), f"frame {t}"
    assert sim.frame == bundle.frame_count - 1
    # Many frames in one call, and the in-process rollout, give the same.
    many = model.simulation(bundle.hand_anchors(0)).step_many(hand_path(bundle))
    assert np.array_equal(many, reference[1:])
    assert np.array_equal(model.rollout(bundle), reference)
    # The per-frame metrics are dm-sim's.
    summary = json.loads((tiny["sim"] / "summary.json").read_text())
    errors = model.frame_errors(bundle, reference)
    assert np.allclose(errors["track_m"], summary["per_frame_track_error_m"], rtol=0, atol=0)


def test_a_residual_network_steps_as_in_dm_sim(tiny, tmp_path):
    run_tool("dm-sim", tiny["scene"], "--residual", "pgnd", "--frames", "5", "--out", tmp_path)
    bundle = dm.read_bundle(tiny["scene"])
    model = dm.Model.from_bundle(bundle, residual="pgnd")
    assert model.has_residual
    frames = model.simulation(bundle.hand_anchors(0)).step_many(hand_path(bundle)[:4])
    assert np.array_equal(frames, np.load(tmp_path / "rollout.npy")[1:])


def test_state_and_tracked_points(tiny):
    bundle = dm.read_bundle(tiny["scene"])
    model = dm.load_model(tiny["model"])
    sim = model.simulation(bundle.hand_anchors(0))
    sim.step(bundle.hand_anchors(1))
    n = model.particle_count
    assert sim.positions.shape == (n, 3) and sim.positions.dtype == np.float32
    assert sim.velocities.shape == (n, 3) and np.isfinite(sim.velocities).all()
    f = sim.deformation_gradients
    assert f.shape == (n, 3, 3)
    assert np.allclose(np.linalg.det(f), 1.0, atol=0.2)
    ids = model.track_particles(bundle)
    assert ids.shape == (bundle.tracks["object_points"].shape[1],) and (ids >= 0).all()
    assert np.array_equal(sim.points(ids), sim.positions[ids])
    assert np.array_equal(sim.hands, bundle.hand_anchors(1))
    with pytest.raises(ValueError, match="outside"):
        sim.points(np.array([n]))
    # The Chamfer term of the metrics at the first frame.
    first = model.simulation(bundle.hand_anchors(0))
    visible = bundle.tracks["object_visibility"][0]
    observed = bundle.tracks["object_points"][0][visible]
    errors = model.frame_errors(bundle, model.rollout(bundle, frames=2))
    assert first.chamfer_to(observed) == pytest.approx(errors["chamfer_m"][0], rel=1e-12)


def test_renders_with_the_splats_and_with_particles(tiny):
    bundle = dm.read_bundle(tiny["scene"])
    model = dm.load_model(tiny["model"])
    assert model.has_splats
    camera = bundle.camera(0)
    for follow in (True, False):
        sim = model.simulation(bundle.hand_anchors(0), follow_splats=follow)
        for t in range(1, 4):
            sim.step(bundle.hand_anchors(t))
        view = sim.render(camera)
        h, w = camera["height"], camera["width"]
        assert view["rgb"].shape == (h, w, 3) and view["rgb"].dtype == np.uint8
        assert view["depth"].shape == (h, w) and view["mask"].shape == (h, w)
        mask = view["mask"]
        assert 0.001 < mask.mean() < 0.9, f"object covers {mask.mean():.3f} of the image"
        # Depth is defined on the object and lies near the particles' depth.
        depth = view["depth"][mask]
        assert np.isfinite(depth).all()
        r = np.asarray(camera["world_to_camera"])
        z = sim.positions.astype(np.float64) @ r[2, :3] + r[2, 3]
        assert z.min() - 0.05 < np.median(depth) < z.max() + 0.05
        # The observed object mask and the render mostly agree.
        observed = bundle.mask(0, 3)
        overlap = (observed & mask).sum() / max((observed | mask).sum(), 1)
        assert overlap > 0.4, f"IoU with the observed mask {overlap:.2f}"
    with pytest.raises(dm.ModelError, match="splats"):
        dm.Model.from_bundle(bundle).simulation(bundle.hand_anchors(0), follow_splats=True)
    camera = dm.look_at((0.6, 0.0, 0.3), (0.0, 0.0, 0.05), width=64, height=48)
    assert sim.render(camera)["rgb"].shape == (48, 64, 3)


def test_material_as_in_the_playground(tiny):
    bundle = dm.read_bundle(tiny["scene"])
    model = dm.load_model(tiny["model"])
    sim = model.simulation(bundle.hand_anchors(0))
    sim.step(bundle.hand_anchors(1))
    before = sim.substeps_per_frame
    sim.set_material(e_scale=8.0, nu=0.4, damping=2.0)
    assert sim.material == {"e_scale": 8.0, "nu": 0.4, "damping": 2.0}
    assert sim.substeps_per_frame > before, "a stiffer material needs a finer substep"
    sim.step(bundle.hand_anchors(2))
    assert np.isfinite(sim.positions).all()
    for kwargs in ({"e_scale": 0.0}, {"nu": 0.5}, {"damping": -1.0}, {"e_scale": float("nan")}):
        with pytest.raises(ValueError):
            sim.set_material(**kwargs)


def test_errors_name_file_and_field(tiny, tmp_path):
    with pytest.raises(dm.BundleError, match="nowhere"):
        dm.read_bundle(tmp_path / "nowhere")
    broken = tmp_path / "model"
    shutil.copytree(tiny["model"], broken)
    record = json.loads((broken / "model.json").read_text())
    record["physics"]["dt"] = "soon"
    (broken / "model.json").write_text(json.dumps(record))
    with pytest.raises(dm.DeformMasterError, match=r"model\.json.*physics\.dt"):
        dm.load_model(broken)
    bundle = dm.read_bundle(tiny["scene"])
    sim = dm.load_model(tiny["model"]).simulation(bundle.hand_anchors(0))
    with pytest.raises(ValueError, match="hands"):
        sim.step(np.zeros((len(bundle.hand_anchors(0)) + 1, 3)))
    bad = bundle.hand_anchors(1)
    bad[0, 1] = np.nan
    with pytest.raises(ValueError, match="not finite"):
        sim.step(bad)
    with pytest.raises(ValueError, match="camera 9"):
        bundle.rgb(9, 0)
    # A hand thrown across the scene in one frame: reported, not a crash.
    far = bundle.hand_anchors(1) + 50.0
    with pytest.raises(dm.SimulationError):
        sim.step(far)
    model = dm.load_model(tiny["model"])
    with pytest.raises(dm.ModelError, match="device"):
        model.simulation(bundle.hand_anchors(0), device="tpu")
    with pytest.raises(dm.ModelError, match="device"):
        model.rollout(bundle, frames=2, device="tpu")


# Largest position difference, metres, between the CPU and the GPU after a
# few frames of the tiny rope: both run in f32 but add up in another order;
# 3e-8 m here.
GPU_POSITION_TOLERANCE_M = 1e-5

# The CUDA driver's emulator (crates/dm-cuda/emulator), which `cargo test
# --workspace` builds; NVRTC must be on LD_LIBRARY_PATH (`make test` puts
# it there).
EMULATOR = pathlib.Path(
    os.environ.get("DM_CUDA_EMULATOR", REPO / "target" / "tmp" / "cuda-emulator" / "libcuda.so")
)


def test_device_cuda_steps_rolls_out_and_runs_the_env_as_the_cpu_under_the_emulator(tiny, tmp_path):
    if not EMULATOR.is_file():
        raise FileNotFoundError(
            f"{EMULATOR} is missing: cargo test --workspace builds it, or set DM_CUDA_EMULATOR"
        )
    script = """
import sys
import numpy as np
import deformmaster as dm
scene, model_dir, out = sys.argv[1:]
bundle = dm.read_bundle(scene)
model = dm.load_model(model_dir)
sims = {d: model.simulation(bundle.hand_anchors(0), device=d) for d in ("cpu", "cuda")}
assert [sim.device for sim in sims.values()] == ["cpu", "cuda"]
for t in range(1, 4):
    for sim in sims.values():
        sim.step(bundle.hand_anchors(t))
points, particles = model.goal("move", bundle)
# MPPI only: Adam's first step is ±1 step per knot whatever the gradient's
# size, so a gradient near 0 could step either way on the two devices.
plans = {d: sim.plan(points, particles, horizon=3, knots=1, samples=2, iterations=1,
                     gradient_iters=0) for d, sim in sims.items()}
assert [p["record"]["options"]["device"] for p in plans.values()] == ["cpu", "cuda"]
from deformmaster.env import TwinEnv
envs = {d: TwinEnv(model, bundle, max_steps=3, device=d) for d in ("cpu", "cuda")}
seen = {}
for d, env in envs.items():
    env.reset(seed=1)
    assert env._sim.device == d, (env._sim.device, d)
    for _ in range(3):
        seen[d], *_ = env.step(np.full(env.action_space.shape, 0.004, np.float32))
np.savez(out, cpu=sims["cpu"].positions, gpu=sims["cuda"].positions,
         rollout_cpu=model.rollout(bundle, frames=4), rollout_gpu=model.rollout(bundle, frames=4, device="cuda"),
         env_cpu=seen["cpu"], env_gpu=seen["cuda"],
         plan_cpu=plans["cpu"]["planned"], plan_gpu=plans["cuda"]["planned"],
         hands_cpu=plans["cpu"]["hands"], hands_gpu=plans["cuda"]["hands"])
"""
    out = tmp_path / "positions.npz"
    # The driver is chosen when the process starts: the GPU runs in a child.
    env = dict(os.environ, LD_PRELOAD=str(EMULATOR))
    done = subprocess.run(
        [sys.executable, "-c", script, str(tiny["scene"]), str(tiny["model"]), str(out)],
        env=env, capture_output=True, text=True,
    )
    assert done.returncode == 0, done.stderr
    saved = np.load(out)
    assert saved["rollout_gpu"].shape == saved["rollout_cpu"].shape
    pairs = ("cpu", "gpu"), ("rollout_cpu", "rollout_gpu"), ("env_cpu", "env_gpu"), \
        ("plan_cpu", "plan_gpu"), ("hands_cpu", "hands_gpu")
    for cpu, gpu in pairs:
        difference = np.abs(saved[cpu].astype(np.float64) - saved[gpu]).max()
        assert difference <= GPU_POSITION_TOLERANCE_M, (cpu, difference)


def test_the_gil_is_released_while_stepping(tiny):
    bundle = dm.read_bundle(tiny["scene"])
    model = dm.load_model(tiny["model"])
    sim = model.simulation(bundle.hand_anchors(0))
    # The scene's path ten times over: long enough that the timing below
    # is not at the mercy of a fast machine.
    path = np.concatenate([hand_path(bundle)] * 10)
    ticks = 0
    worker = threading.Thread(target=sim.step_many, args=(path,))
    start = time.perf_counter()
    worker.start()
    while worker.is_alive():
        ticks += 1
        time.sleep(0)
    elapsed = time.perf_counter() - start
    worker.join()
    assert elapsed > 0.05, f"the rollout took only {elapsed:.3f} s; the test needs a longer one"
    # With the GIL held for the whole call the loop would run once or twice.
    assert ticks > 100, f"main thread ran {ticks} times in {elapsed:.2f} s"
    assert sim.frame == len(path)
    # A second thread stepping the same simulation is refused, not blocked.
    busy = threading.Thread(target=sim.step_many, args=(path,))
    busy.start()
    time.sleep(0.01)
    if busy.is_alive():
        with pytest.raises(dm.SimulationError, match="another thread"):
            sim.step(bundle.hand_anchors(0))
    busy.join()


# The fixture's dm-fit options (conftest.py), as keywords.
TINY_FIT = {
    "iters": 2, "stage2_iters": 1, "gain_evals": 4, "patches": 8, "residual": "none",
    "rgb_iters": 1,
}


def test_fitting_from_python_equals_dm_fit_and_resumes(tiny, tmp_path):
    messages = []
    report = dm.fit(dm.read_bundle(tiny["scene"]), tmp_path / "model", progress=messages.append, **TINY_FIT)
    reference = (tiny["model"] / "model.json").read_bytes()
    assert (tmp_path / "model" / "model.json").read_bytes() == reference
    assert report == json.loads((tmp_path / "model" / "fit_report.json").read_text())
    assert report["material"]["E_median_pa"] > 0
    assert any(m.startswith("Material1") for m in messages), messages[:5]
    # Paused after two steps, then resumed: the same model.
    assert dm.fit(tiny["scene"], tmp_path / "paused", stop_after=2, **TINY_FIT) is None
    assert not (tmp_path / "paused" / "model.json").exists()
    dm.fit(tiny["scene"], tmp_path / "paused", resume=True, **TINY_FIT)
    assert (tmp_path / "paused" / "model.json").read_bytes() == reference


def test_fitting_refuses_bad_options_and_pauses_on_the_callbacks_error(tiny, tmp_path):
    with pytest.raises(ValueError, match="--iter"):
        dm.fit(tiny["scene"], tmp_path / "a", iter=2)
    with pytest.raises(ValueError, match="--residual"):
        dm.fit(tiny["scene"], tmp_path / "b", residual="quadratic")
    with pytest.raises(dm.BundleError, match="nowhere"):
        dm.fit(tmp_path / "nowhere", tmp_path / "c", **TINY_FIT)

    def impatient(message):
        raise KeyError("enough")

    with pytest.raises(KeyError, match="enough"):
        dm.fit(tiny["scene"], tmp_path / "d", progress=impatient, **TINY_FIT)
    # Paused after its first step, checkpointed, and resumable.
    assert (tmp_path / "d" / "checkpoint.json").is_file()
    assert not (tmp_path / "d" / "model.json").exists()
    dm.fit(tiny["scene"], tmp_path / "d", resume=True, **TINY_FIT)
    assert (tmp_path / "d" / "model.json").read_bytes() == (tiny["model"] / "model.json").read_bytes()


# A short search: the test is about the call, not the plan's quality.
SHORT_PLAN = {
    "horizon": 6, "samples": 4, "iterations": 2, "gradient_iters": 2, "settle_frames": 0,
}


def test_planning_from_python_equals_dm_plan(tiny, tmp_path):
    plant = tiny["root"] / "truth.json"
    run_tool(
        "dm-plan", tiny["model"], "--bundle", tiny["scene"], "--goal", "straighten",
        "--plant", plant, "--horizon", "6", "--samples", "4", "--iterations", "2",
        "--gradient-iters", "2", "--settle-frames", "0", "--no-video", "--out", tmp_path / "cli",
    )
    calls = []
    result = dm.plan(
        dm.load_model(tiny["model"]), dm.read_bundle(tiny["scene"]), "straighten",
        out=tmp_path / "py", progress=lambda *call: calls.append(call), plant=plant,
        **SHORT_PLAN,
    )
    cli = tmp_path / "cli"
    for key, name in (("hands", "actions"), ("planned", "planned"), ("executed", "executed")):
        reference = np.load(cli / f"{name}.npy")
        assert result[key].dtype == reference.dtype, key
        assert np.array_equal(result[key], reference), key
        assert np.array_equal(np.load(tmp_path / "py" / f"{name}.npy"), reference), name
    assert np.array_equal(result["goal"], np.load(cli / "goal.npy")[0])
    record = json.loads((cli / "plan.json").read_text())
    for key in ("planned", "executed", "start", "rollouts", "actions", "history", "plant"):
        assert result["record"][key] == record[key], key
    assert result["record"]["options"]["plant"] == str(plant)
    assert result["frame_dt"] > 0
    stages = {stage for stage, _, _ in calls}
    assert {"MPPI", "gradient", "execute"} <= stages, stages
    assert all(0 <= done <= total for _, done, total in calls)


def test_planning_refuses_bad_options_and_passes_on_the_callbacks_error(tiny):
    with pytest.raises(ValueError, match="--horizn"):
        dm.plan(tiny["model"], tiny["scene"], "straighten", horizn=6)
    with pytest.raises(ValueError, match="--samples"):
        dm.plan(tiny["model"], tiny["scene"], "straighten", samples="many")
    with pytest.raises(dm.BundleError, match="nowhere"):
        dm.plan(tiny["model"], tiny["scene"].parent / "nowhere", "straighten", **SHORT_PLAN)
    with pytest.raises(ValueError, match="directory"):
        dm.plan(dm.Model.from_bundle(dm.read_bundle(tiny["scene"])), tiny["scene"], "straighten")

    def interrupted(stage, done, total):
        raise KeyError("stop here")

    with pytest.raises(KeyError, match="stop here"):
        dm.plan(tiny["model"], tiny["scene"], "straighten", progress=interrupted, **SHORT_PLAN)


def test_planning_from_a_live_simulation_starts_where_it_is(tiny):
    bundle = dm.read_bundle(tiny["scene"])
    model = dm.load_model(tiny["model"])
    sim = model.simulation(bundle.hand_anchors(0))
    sim.step_many(hand_path(bundle)[:6])
    points, particles = model.goal("move", bundle)
    assert points.shape == (len(particles), 3)
    before = sim.chamfer_to(points)
    calls = []
    plan = sim.plan(
        points, particles, progress=lambda *call: calls.append(call),
        horizon=10, samples=4, iterations=2, gradient_iters=2,
    )
    assert sim.frame == 6, "planning does not advance the simulation"
    assert plan["hands"].shape == (11,) + sim.hands.shape
    assert np.array_equal(plan["hands"][0], sim.hands)
    assert np.array_equal(plan["planned"][0], sim.positions[plan["planned_particles"]])
    record = plan["record"]
    assert record["options"]["horizon"] == 10 and record["options"]["device"] == "cpu"
    assert record["planned"]["final_chamfer_m"] < record["start"]["final_chamfer_m"]
    assert {"MPPI", "gradient"} <= {stage for stage, _, _ in calls}
    sim.step_many(plan["hands"][1:])
    after = sim.chamfer_to(points)
    assert after < 0.8 * before, (before, after)
    # In the model's own world (exact), the plan is what the simulation does.
    exact = sim.plan(points, particles, exact=True, horizon=4, samples=2, iterations=1, gradient_iters=1)
    assert np.array_equal(sim.step_many(exact["hands"][1:]), exact["planned"][1:])
    # Each of the bundle's hands moved as one: its anchors keep their offsets.
    ranges = bundle.hand_ranges
    assert ranges[0][0] == 0 and ranges[-1][1] == len(sim.hands)
    rigid = sim.plan(points, particles, rigid_hands=ranges, horizon=4, samples=2, iterations=1,
                     gradient_iters=1)
    moved = rigid["hands"] - rigid["hands"][0]
    assert np.abs(moved).max() > 0
    for start, end in ranges:
        assert np.allclose(moved[:, start:end], moved[:, start:start + 1], atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="rigid_hands"):
        sim.plan(points, particles, rigid_hands=[(0, 1)], horizon=4, samples=2, iterations=1)
    with pytest.raises(ValueError, match="--plant"):
        sim.plan(points, particles, plant="truth.json")
    with pytest.raises(ValueError, match="goal"):
        sim.plan(points[:, :2])
    with pytest.raises(ValueError, match="particles"):
        sim.plan(points, particles[:-1], horizon=4, samples=2, iterations=1)
    with pytest.raises(ValueError, match="particles"):
        sim.plan(points, -np.ones_like(particles))
    with pytest.raises(ValueError, match="knit"):
        model.goal("knit", bundle)


def interrupt_soon():
    """Ctrl-C to this process in 0.1 s, as a terminal or notebook sends it;
    the timer's `sent` holds when it was sent (perf_counter)."""
    sent = []

    def send():
        sent.append(time.perf_counter())
        os.kill(os.getpid(), signal.SIGINT)

    timer = threading.Timer(0.1, send)
    timer.sent = sent
    timer.start()
    return timer


@pytest.fixture
def ctrl_c_raises():
    """SIGINT raising KeyboardInterrupt, as in a terminal or notebook:
    Python leaves SIGINT ignored when it starts with it ignored (a
    background job of a non-interactive shell)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_ctrl_c_stops_long_calls(tiny, tmp_path, ctrl_c_raises):
    bundle = dm.read_bundle(tiny["scene"])
    sim = dm.load_model(tiny["model"]).simulation(bundle.hand_anchors(0))
    # Seconds of stepping even on a fast machine; the interrupt comes first.
    path = np.concatenate([hand_path(bundle)] * 50)
    timer = interrupt_soon()
    start = time.perf_counter()
    try:
        sim.step_many(path)
        finished = time.perf_counter()
    except KeyboardInterrupt:
        finished = None
    timer.join()
    assert finished is None, (
        f"step_many ran all {sim.frame} frames in {finished - start:.3f} s; "
        f"Ctrl-C sent at {[t - start for t in timer.sent]} s"
    )
    stopped_at = sim.frame
    assert stopped_at < len(path)
    sim.step(path[stopped_at])
    assert sim.frame == stopped_at + 1
    timer = interrupt_soon()
    with pytest.raises(KeyboardInterrupt):
        dm.fit(tiny["scene"], tmp_path / "fit", **dict(TINY_FIT, iters=5000))
    timer.join()
    # Paused at a step's end: checkpointed, no model yet.
    assert (tmp_path / "fit" / "checkpoint.json").is_file()
    assert not (tmp_path / "fit" / "model.json").exists()
    timer = interrupt_soon()
    with pytest.raises(KeyboardInterrupt):
        dm.plan(
            tiny["model"], tiny["scene"], "straighten", out=tmp_path / "plan",
            **dict(SHORT_PLAN, iterations=500),
        )
    timer.join()
    # Stopped inside the search: nothing was written.
    assert not (tmp_path / "plan").exists()
    points, particles = dm.load_model(tiny["model"]).goal("move", bundle)
    timer = interrupt_soon()
    with pytest.raises(KeyboardInterrupt):
        sim.plan(points, particles, iterations=500, samples=4, horizon=6)
    timer.join()
    # A rollout of a long clip: the tiny one played forwards and back.
    frames = bundle.frame_count
    order = np.concatenate([np.r_[0:frames, frames - 2 : 0 : -1]] * 30)
    meta = dict(bundle.meta, frame_count=len(order),
                split={"train": [0, len(order) - 5], "test": [len(order) - 5, len(order)]})
    long_clip = dm.write_bundle(
        tmp_path / "long", meta, {k: v[order] for k, v in bundle.tracks.items()},
        bundle.particles,
        [{k: v[order] for k, v in bundle.images(c).items()} for c in range(bundle.camera_count)],
    )
    timer = interrupt_soon()
    with pytest.raises(KeyboardInterrupt):
        dm.load_model(tiny["model"]).rollout(long_clip)
    timer.join()


def test_gymnasium_env_passes_check_env(tiny):
    from gymnasium.utils.env_checker import check_env

    from deformmaster.env import TwinEnv

    env = TwinEnv(tiny["model"], tiny["scene"], max_steps=5, hand_jitter_m=0.002)
    check_env(env, skip_render_check=True)
    first, info = env.reset(seed=3)
    again, info_again = env.reset(seed=3)
    assert np.array_equal(first, again) and np.array_equal(info["hands"], info_again["hands"])
    _, info_other = env.reset(seed=4)
    assert not np.array_equal(info["hands"], info_other["hands"])
    env.reset(seed=3)
    assert info["chamfer_m"] > 0
    rewards = []
    for _ in range(5):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample() * 0)
        rewards.append(reward)
        assert env.observation_space.contains(obs)
        assert not terminated
    assert truncated and np.isfinite(rewards).all()
    images = TwinEnv(
        tiny["model"], tiny["scene"], max_steps=3, image_observation=True, render_mode="rgb_array"
    )
    check_env(images)
    obs, _ = images.reset(seed=0)
    assert obs["image"].shape == images.observation_space["image"].shape


def test_example_script_writes_its_plot(tiny, tmp_path):
    out = tmp_path / "rollout.png"
    done = subprocess.run(
        [sys.executable, str(REPO / "examples/python/rollout.py"),
         str(tiny["model"]), str(tiny["scene"]), "--out", str(out)],
        capture_output=True, text=True,
    )
    assert done.returncode == 0, done.stderr
    assert out.stat().st_size > 10_000


def test_the_control_loop_example_writes_its_plot(tiny, tmp_path):
    out = tmp_path / "mpc.png"
    done = subprocess.run(
        [sys.executable, str(REPO / "examples/python/mpc.py"),
         str(tiny["model"]), str(tiny["scene"]), "--goal", "move", "--out", str(out),
         "--frames", "8", "--every", "4", "--samples", "4", "--iterations", "1",
         "--gradient-iters", "1", "--rigid-hands"],
        capture_output=True, text=True,
    )
    assert done.returncode == 0, done.stderr
    assert "re-planned 2 times" in done.stdout, done.stdout
    assert out.stat().st_size > 10_000
