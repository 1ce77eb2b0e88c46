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

demo: build
	@rm -rf $(OUT) && mkdir -p $(OUT)
	./target/release/dm-synth --preset $(PRESET) --seed $(SEED) --out $(OUT)/scene --truth $(OUT)/scene.truth.json
	./target/release/dm-sim $(OUT)/scene --out $(OUT)/sim
	@echo
	@echo "== DeformMaster demo summary =="
	@echo "scene bundle : $(OUT)/scene   (truth kept outside: $(OUT)/scene.truth.json)"
	@echo "rollout      : $(OUT)/sim/rollout.npy, $(OUT)/sim/summary.json"
	@echo "pictures     : $(OUT)/sim/preview.png  $(OUT)/scene/views/cam0/rgb/00000.png"

test: setup
	$(CARGO) test --workspace

bench: build
	./target/release/dm-bench mpm --particles 100000 --grid 32 --experts nh
	./target/release/dm-bench mpm --particles 100000 --grid 32 --experts moce

clean:
	rm -rf out target
