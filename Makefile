# citystream: `make run` and `make test` set everything up on a fresh
# Debian 12 machine (as root), then build and run. Both are idempotent.

CARGO ?= cargo
OUT ?= out/run
CITY ?= data/small
export XDG_RUNTIME_DIR ?= /tmp/citystream-xdg-runtime

.PHONY: all setup build run test check fmt clippy doc bench

all: build

setup:
	@mkdir -p "$(XDG_RUNTIME_DIR)" && chmod 700 "$(XDG_RUNTIME_DIR)"
	@bash scripts/setup.sh

build: setup
	$(CARGO) build --release --workspace --bins

run: build
	@if [ ! -f "$(CITY)/scene.bin" ]; then \
		echo "generating the default city into $(CITY)"; \
		./target/release/citystream gen --preset small --seed 1 --out "$(CITY)"; \
	fi
	./target/release/flythrough --dataset "$(CITY)" --clock fixed --bind-latency desktop --out $(OUT)
	./target/release/citystream report --run $(OUT) --name adaptive --out $(OUT)
	@echo "frames, summary.json, frames.csv, table.md and charts in $(OUT)"

test: setup
	$(CARGO) test --workspace

fmt:
	$(CARGO) fmt --all -- --check

clippy: setup
	$(CARGO) clippy --workspace --all-targets -- -D warnings

doc: setup
	RUSTDOCFLAGS="-D warnings" $(CARGO) doc --workspace --no-deps

check: fmt clippy doc

bench: setup
	$(CARGO) bench --workspace
