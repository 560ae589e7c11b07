# citystream: `make run` and `make test` set everything up on a fresh
# Debian 12 machine (as root), then build and run. Both are idempotent.

CARGO ?= cargo
OUT ?= out/run
# Empty: the default city (data/city, created by the first run).
CITY ?=
export XDG_RUNTIME_DIR ?= /tmp/citystream-xdg-runtime

.PHONY: all setup build run test check fmt clippy doc embed bench

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
