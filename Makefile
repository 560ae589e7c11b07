# citystream: `make run` and `make test` set everything up on a fresh
# Debian 12 machine (as root), then build and run. Both are idempotent.

CARGO ?= cargo
OUT ?= out/run
# Empty: the default city (data/city, created by the first run).
CITY ?=
export XDG_RUNTIME_DIR ?= /tmp/citystream-xdg-runtime

.PHONY: all setup build run window test check fmt clippy doc embed loops docpaths bench fuzz-long gpu-check gpu-check-pack

all: build

setup:
	@mkdir -p "$(XDG_RUNTIME_DIR)" && chmod 700 "$(XDG_RUNTIME_DIR)"
	@bash tools/scripts/setup.sh

build: setup
	$(CARGO) build --release --workspace --bins

run: build
	./target/release/flythrough $(if $(CITY),--dataset "$(CITY)") --clock fixed --bind-latency desktop --out $(OUT)
	./target/release/citystream report --run $(OUT) --name adaptive --out $(OUT)
	@echo "frames, summary.json, frames.csv, table.md and charts in $(OUT)"

# The flythrough in a window on the default city (or CITY): needs a display.
window: build
	./target/release/flythrough --window $(if $(CITY),--dataset "$(CITY)") --width 1280 --height 720

# Then the sparse cache's tests again with mip tails, which every GPU has and
# lavapipe has not: forced per layer and single (CITYSTREAM_FORCE_MIP_TAIL,
# docs/REAL_GPU.md). Two tests are left out of the single run, their scenario
# not arising there: with a single tail every layer's coarse levels are bound
# from the start, so stream_frames' view-larger-than-the-budget row fits its
# budget; and lavapipe's synthetic single tail for the ring test's 64 layers
# takes 36 MiB (9 blocks a layer, where a GPU's single tail is one block), more
# than its 8 MB budget, which the flythrough refuses with a clear error.
TAIL_TESTS = -p citystream-tests --test sparse_residency --test texture_cache --test vulkan_binder \
	--test stream_frames -p citystream-flythrough --test flythrough_cli
test: setup
	$(CARGO) test --workspace
	CITYSTREAM_FORCE_MIP_TAIL=3 $(CARGO) test $(TAIL_TESTS)
	CITYSTREAM_FORCE_MIP_TAIL=3,single $(CARGO) test $(TAIL_TESTS) -- \
		--skip a_view_larger_than_the_budget_settles_without_reloading \
		--skip the_ring_evicting_a_textures_own_layer_does_not_fail_the_texture

fmt:
	$(CARGO) fmt --all -- --check

clippy: setup
	$(CARGO) clippy --workspace --all-targets -- -D warnings

doc: setup
	RUSTDOCFLAGS="-D warnings" $(CARGO) doc --workspace --no-deps

# The engine library alone, as an embedder builds it (the flythrough lives in tools/flythrough).
embed:
	$(CARGO) check -p citystream-engine --lib

# Import loops between the modules of a crate (cargo refuses loops between crates).
loops:
	python3 tools/scripts/module-loops.py .

# Every API path the embedding guides name resolves in the sources.
docpaths:
	python3 tools/scripts/doc-paths.py .

check: fmt clippy doc embed loops docpaths

bench: setup
	$(CARGO) bench --workspace

# The long fuzz campaign (docs/TOOLS.md, "Fuzzing"): every harness, FUZZ_INPUTS inputs each, in an
# optimised build that keeps overflow checks and debug assertions (a wrapped subtraction
# that would panic in a debug build counts as a finding). Scratch files go to FUZZ_OUT;
# tmpfs makes the dataset harness several times faster.
FUZZ_INPUTS ?= 1000000
FUZZ_SEED ?= 1
FUZZ_OUT ?= $(if $(wildcard /dev/shm),/dev/shm/citystream-fuzz,out/fuzz)
fuzz-long:
	CARGO_PROFILE_RELEASE_OVERFLOW_CHECKS=true CARGO_PROFILE_RELEASE_DEBUG_ASSERTIONS=true \
		$(CARGO) run --release --target-dir target/fuzz -p citystream-testing --bin fuzz -- \
		--inputs $(FUZZ_INPUTS) --seed $(FUZZ_SEED) --out $(FUZZ_OUT)

# The GPU check (docs/REAL_GPU.md). gpu-check-pack builds the release binaries and the
# bind_cost bench and downloads the Vulkan loader and validation layer packages into
# .gpu-check/, the folder carried to a GPU machine without a toolchain or network;
# gpu-check runs the check there (or here, on lavapipe, from target/release) within
# GPU_CHECK_BUDGET_S seconds (default 540) and writes its summary into $OUT (default
# out/gpu-check). It builds nothing: on the GPU machine there is no cargo.
gpu-check:
	bash tools/scripts/gpu-check.sh

gpu-check-pack: setup
	bash tools/scripts/gpu-check-pack.sh
