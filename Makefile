# DeformMaster — two commands on a fresh machine:
#   make demo   set up, build, synthesise a scene, roll out its world model, summarise
#   make test   set up, build and run every test
SHELL := /bin/bash
.DEFAULT_GOAL := demo
CARGO ?= cargo
OUT ?= out/demo
PRESET ?= toy
SEED ?= 7

.PHONY: setup build demo test bench clean

# Everything the project needs beyond the Rust toolchain of the machine.
# (Later stages add Debian/PyPI packages here: opencv, onnxruntime, ...)
setup:
	@command -v $(CARGO) >/dev/null || { echo "error: cargo not found; install Rust (rustup) first" >&2; exit 1; }
	@$(CARGO) --version

build: setup
	$(CARGO) build --release --workspace --bins

# A short fit keeps the demo to a few minutes on 2 cores; see dm-fit --help.
DEMO_FIT ?= --iters 3 --stage2-iters 1 --gain-evals 4

demo: build
	@rm -rf $(OUT) && mkdir -p $(OUT)
	./target/release/dm-synth --preset $(PRESET) --seed $(SEED) --out $(OUT)/scene --truth $(OUT)/scene.truth.json
	./target/release/dm-sim $(OUT)/scene --out $(OUT)/untrained
	./target/release/dm-fit $(OUT)/scene --out $(OUT)/model $(DEMO_FIT)
	./target/release/dm-sim $(OUT)/scene --model-dir $(OUT)/model --out $(OUT)/sim
	@echo
	@echo "== DeformMaster demo summary =="
	@echo "scene bundle : $(OUT)/scene   (truth kept outside: $(OUT)/scene.truth.json)"
	@python3 -c 'import json,sys; t=json.load(open("$(OUT)/scene.truth.json")); u=json.load(open("$(OUT)/untrained/summary.json")); f=json.load(open("$(OUT)/sim/summary.json")); r=json.load(open("$(OUT)/model/fit_report.json")); print("truth        : E %.3g Pa, nu %.2f" % (t["material"]["E_pa"], t["material"]["nu"])); print("fitted       : E %.3g Pa, nu %.2f, kp %.3g, kd %.3g (%.0f s)" % (r["material"]["E_median_pa"], r["material"]["nu_median"], r["dca"]["kp"], r["dca"]["kd"], r["seconds"])); print("track error  : held-out %.1f mm untrained -> %.1f mm fitted" % (1e3*u["track_error_m"]["test"], 1e3*f["track_error_m"]["test"]))' || true
	@echo "model        : $(OUT)/model (model.json, fit_report.json)"
	@echo "pictures     : $(OUT)/sim/preview.png  $(OUT)/untrained/preview.png  $(OUT)/model/loss_curve.png"

test: setup
	$(CARGO) test --workspace

bench: build
	./target/release/dm-bench mpm --particles 100000 --grid 32 --experts nh
	./target/release/dm-bench mpm --particles 100000 --grid 32 --experts moce

clean:
	rm -rf out target
