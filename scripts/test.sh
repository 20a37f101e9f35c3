#!/usr/bin/env bash
# The project's test command (README "Run the tests"). Installs what the tests need, then runs
# the whole suite. Safe to re-run.
set -euo pipefail
cd "$(dirname "$0")/.."

# System packages the tests need. The model and CLI crates need none beyond the Rust toolchain;
# later issues (aravis, V4L2, GUI backends) add theirs here.
APT_PACKAGES=()
if ((${#APT_PACKAGES[@]})); then
  missing=()
  for p in "${APT_PACKAGES[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
  if ((${#missing[@]})); then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq && $SUDO apt-get install -y -qq "${missing[@]}"
  fi
fi

# The firmware protocol must build for a Cortex-M4F without std (thumbv7em-none-eabihf).
rustup target add thumbv7em-none-eabihf >/dev/null
cargo build -p polar-firmware-protocol --target thumbv7em-none-eabihf --locked

# Optimised tests: the property and quadrature tests evaluate the model ~1e7 times.
cargo test --workspace --release --locked
