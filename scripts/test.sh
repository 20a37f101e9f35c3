#!/usr/bin/env bash
# The project's test command (README "Run the tests"). Installs what the tests need, then runs
# the whole suite. Safe to re-run. `--deps-only` installs the system packages and stops (.ci/run
# calls it before clippy, which needs them too).
set -euo pipefail
cd "$(dirname "$0")/.."

# System packages the build and tests need. The model and CLI crates need none beyond the Rust
# toolchain; later issues (V4L2, GUI backends) add theirs here.
# * polar-camera-aravis links libaravis (libaravis-dev; its aravis-0.8.pc also requires
#   libusb-1.0, which libaravis-dev does not pull in).
# * Its tests run Aravis's fake GigE Vision camera, arv-fake-gv-camera-0.8, which Debian 12
#   ships in aravis-tools (aravis-tools-cli has arv-tool-0.8 only).
# * The GUI's screenshot tour runs polarimeter-gui under Xvfb (xvfb-run needs xauth) with
#   Mesa's software OpenGL; winit loads the X11 client libraries at run time. xdotool sends
#   the real pointer and keyboard events of scripts/gui_real_input.py.
# * polar-camera-uvc (nokhwa) builds its Linux V4L2 bindings with bindgen, which loads libclang
#   (libclang-dev); only that crate, and the CLI's `uvc` feature, need it.
# * The station's TLS test makes a self-signed certificate with the openssl command; its status
#   page is tested in headless Chromium (Debian's chromium).
APT_PACKAGES=(libaravis-dev libusb-1.0-0-dev aravis-tools-cli aravis-tools libclang-dev
  xvfb xauth libgl1-mesa-dri libegl1 libgl1 libx11-xcb1 libxcursor1 libxrandr2 libxi6
  libxkbcommon-x11-0 openssl chromium xdotool)
if ((${#APT_PACKAGES[@]})); then
  missing=()
  for p in "${APT_PACKAGES[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
  if ((${#missing[@]})); then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}"
  fi
fi
if [ "${1:-}" = "--deps-only" ]; then exit 0; fi

# Python packages the tests use, in a venv of their own (target/py-venv), pinned in
# scripts/requirements.txt and reinstalled when that file changes; the tests find the venv's
# python through POLARIMETER_PYTHON:
# * zarr-python 3, xarray and xxhash read runs back from the outside (scripts/check_run.py,
#   scripts/zarr_interop.py; crates/engine/tests/store.rs, tests/tests/runs/crash_safety.rs,
#   crates/cli/tests/integration/crash.rs);
# * public client libraries (pylablib, thorlabs_elliptec, roesel's elliptec) drive the
#   simulated Elliptec and FW102C/FW212C devices (tests/tests/hil/conformance_elliptec.rs).
PY_VENV=target/py-venv
REQUIREMENTS=scripts/requirements.txt
[ -x "$PY_VENV/bin/python" ] || python3 -m venv "$PY_VENV"
if ! cmp -s "$REQUIREMENTS" "$PY_VENV/requirements.installed"; then
  "$PY_VENV/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps -r "$REQUIREMENTS"
  cp "$REQUIREMENTS" "$PY_VENV/requirements.installed"
fi
export POLARIMETER_PYTHON="$PWD/$PY_VENV/bin/python"

# The firmware protocol must build for a Cortex-M4F without std (thumbv7em-none-eabihf).
rustup target add thumbv7em-none-eabihf >/dev/null
cargo build -p polar-firmware-protocol --target thumbv7em-none-eabihf --locked

# Optimised tests: the property and quadrature tests evaluate the model ~1e7 times. The
# hardware-in-the-loop binary (tests/tests/hil.rs, every test named `hil::...`) mostly waits on
# simulated stages moving at their real speeds, so it runs apart with 8 tests at a time; the
# rest run one per core. Both commands build the same workspace, so nothing is built twice.
cargo test --workspace --release --locked -- --skip hil::
cargo test --workspace --release --locked --test hil -- --test-threads 8

# The Python package (crates/python) as a user installs it: `pip install ./crates/python`
# (maturin, through pip's isolated build) into a fresh venv with the pinned test requirements,
# then its pytest suite (every model function against the command line, the estimator against
# polanalyser, open_run on finished, continuous and killed runs, runs driven from Python and
# interrupted by SIGINT) and examples/python/tour.py,
# run as a user runs it: stdin closed, in a scratch directory, under a time limit.
PKG_VENV=target/py-pkg-venv
rm -rf "$PKG_VENV" && python3 -m venv "$PKG_VENV"
"$PKG_VENV/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps \
  -r crates/python/tests/requirements.txt
"$PKG_VENV/bin/python" -m pip install --quiet --disable-pip-version-check ./crates/python
POLARIMETER_BIN="$PWD/target/release/polarimeter" timeout 900 \
  "$PKG_VENV/bin/python" -m pytest -q -p no:cacheprovider crates/python/tests </dev/null
# The station from outside (tests/station): `station serve` on the simulated rig driven by
# httpx (pinned in tests/station/requirements.txt, added to the same venv) and an SSE reader:
# queue, run control, history, the security matrix, TLS, health, and the kill campaign (20
# SIGKILLs, every run then checked by `acquire check` and zarr-python), and uploads to moto's
# S3 server (pinned in tests/station/moto-requirements.txt, in a venv of its own: botocore
# wants an older python-dateutil than the test venv's) read back by zarr-python via obstore.
"$PKG_VENV/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps \
  -r tests/station/requirements.txt
MOTO_VENV=target/moto-venv
rm -rf "$MOTO_VENV" && python3 -m venv "$MOTO_VENV"
"$MOTO_VENV/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps \
  -r tests/station/moto-requirements.txt
POLARIMETER_BIN="$PWD/target/release/polarimeter" MOTO_SERVER="$PWD/$MOTO_VENV/bin/moto_server" \
  timeout 900 "$PKG_VENV/bin/python" -m pytest -q -p no:cacheprovider tests/station </dev/null
rm -rf target/python-tour && mkdir -p target/python-tour
ROOT="$PWD"
(cd target/python-tour && timeout 600 "$ROOT/$PKG_VENV/bin/python" "$ROOT/examples/python/tour.py" \
  </dev/null)

# The GUI end to end under Xvfb: run the default plan on the simulated devices, then save a
# PNG of each tab (live view, devices, planner, rooftop) and of the live camera and live
# polarimetry. It fails if the run fails, a tab cannot be drawn or a PNG cannot be written.
# docs/gui/ holds the committed shots. The binary is the one `cargo test --workspace` built for
# the GUI's own tests (`cargo run -p polar-gui` would build it again with other features).
rm -rf target/gui-screenshots target/gui-runs && mkdir -p target/gui-runs
xvfb-run -a -s "-screen 0 1400x900x24" \
  target/release/polarimeter-gui --simulate --out target/gui-runs \
  --screenshots target/gui-screenshots

# The GUI as a user drives it: real X pointer and keyboard events (xdotool) on the window at
# 900x650 under Xvfb: connect, an exposure typed below the camera's minimum, live polarimetry,
# a run paused, resumed and aborted while it runs, the log's last line brought into view with
# the wheel, the left panel dragged narrower. One line per step with its time.
timeout 600 python3 scripts/gui_real_input.py --bin target/release/polarimeter-gui </dev/null

# The file schemas judged by jsonschema: every example plan, rig, scene and camera validates, and
# bad plans are refused.
"$POLARIMETER_PYTHON" scripts/check_plan_schema.py --bin target/release/polarimeter

# Every command the README's tour and the examples' headers show, run as a new user runs them:
# stdin closed, in a scratch directory holding a copy of examples/, each under a time limit;
# any failure, hang or file left in the temporary directory fails the tests. It prints one line
# per command (exit status, seconds, command).
# Up to three commands run at once, each after the earlier ones it shares a file, a folder or
# the serial devices with.
python3 scripts/readme_tour.py --bin target/release/polarimeter --scratch target/readme-tour \
  --limit-s 600 --jobs 3
