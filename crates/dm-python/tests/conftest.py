"""A tiny scene, its fitted model (with splats) and dm-sim's rollout of it,
made once per session by the workspace's own binaries: `make test` runs
pytest after `cargo test --workspace`, which builds them in target/debug
(DM_BIN_DIR points elsewhere, e.g. target/release)."""

import os
import pathlib
import subprocess

import pytest

REPO = pathlib.Path(__file__).resolve().parents[3]
BIN_DIR = pathlib.Path(os.environ.get("DM_BIN_DIR", REPO / "target" / "debug"))


def run_tool(name, *args):
    tool = BIN_DIR / name
    if not tool.is_file():
        raise FileNotFoundError(
            f"{tool} is missing: build the workspace first (cargo test --workspace) or set DM_BIN_DIR"
        )
    done = subprocess.run([str(tool), *map(str, args)], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{name} failed:\n{done.stderr}")
    return done


@pytest.fixture(scope="session")
def tiny(tmp_path_factory):
    """Paths of the tiny scene, its model and dm-sim's output."""
    root = tmp_path_factory.mktemp("tiny")
    scene, model, sim = root / "scene", root / "model", root / "sim"
    run_tool(
        "dm-synth", "--preset", "rope", "--seed", "5", "--frames", "14",
        "--width", "48", "--height", "36", "--truth-particles", "2000",
        "--tracks", "60", "--bundle-particles", "800",
        "--out", scene, "--truth", root / "truth.json",
    )
    run_tool(
        "dm-fit", scene, "--out", model, "--iters", "2", "--stage2-iters", "1",
        "--gain-evals", "4", "--patches", "8", "--residual", "none",
        "--rgb-iters", "1",
    )
    run_tool("dm-sim", scene, "--model-dir", model, "--out", sim)
    return {"root": root, "scene": scene, "model": model, "sim": sim}
