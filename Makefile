# citystream: `make run` and `make test` set everything up on a fresh
# Debian 12 machine (as root), then build and run. Both are idempotent.

CARGO ?= cargo
OUT ?= out/run
# Empty: the default city (data/city, created by the first run).
CITY ?=
export XDG_RUNTIME_DIR ?= /tmp/citystream-xdg-runtime

.PHONY: all setup build run window test check fmt clippy doc embed bench fuzz-long

all: build

setup:
	@mkdir -p "$(XDG_RUNTIME_DIR)" && chmod 700 "$(XDG_RUNTIME_DIR)"
	@bash scripts/setup.sh

build: setup
	$(CARGO) build --release --workspace --bins

run: build
	./target/release/flythrough $(if $(CITY),--dataset "$(CITY)") --clock fixed --bind-latency desktop --out $(OUT)
	./target/release/citystream report --run $(OUT) --name adaptive --out $(OUT)
	@echo "frames, summary.json, frames.csv, table.md and charts in $(OUT)"

# The flythrough in a window on the default city (or CITY): needs a display.
window: build
	./target/release/flythrough --window $(if $(CITY),--dataset "$(CITY)") --width 1280 --height 720

test: setup
	$(CARGO) test --workspace

fmt:
	$(CARGO) fmt --all -- --check

clippy: setup
	$(CARGO) clippy --workspace --all-targets -- -D warnings

doc: setup
	RUSTDOCFLAGS="-D warnings" $(CARGO) doc --workspace --no-deps

# The engine library alone, as an embedder builds it (the flythrough lives in tools/).
embed:
	$(CARGO) check -p citystream-engine --lib

check: fmt clippy doc embed

bench: setup
	$(CARGO) bench --workspace

# The long fuzz campaign (README, "Fuzzing"): every harness, FUZZ_INPUTS inputs each, in an
# optimised build that keeps overflow checks and debug assertions (a wrapped subtraction
# that would panic in a debug build counts as a finding). Scratch files go to FUZZ_OUT;
# tmpfs makes the dataset harness several times faster.
FUZZ_INPUTS ?= 1000000
FUZZ_SEED ?= 1
FUZZ_OUT ?= $(if $(wildcard /dev/shm),/dev/shm/citystream-fuzz,out/fuzz)
fuzz-long:
	CARGO_PROFILE_RELEASE_OVERFLOW_CHECKS=true CARGO_PROFILE_RELEASE_DEBUG_ASSERTIONS=true \
		$(CARGO) run --release --target-dir target/fuzz -p citystream-tools --bin fuzz -- \
		--inputs $(FUZZ_INPUTS) --seed $(FUZZ_SEED) --out $(FUZZ_OUT)
