"""Shared fixtures: the repository, the ``polarimeter`` command (the judge of every model
function: Python must give what the command line gives) and simulated runs."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]
EXAMPLES = REPO / "examples"


def _binary() -> Path:
    path = Path(os.environ.get("POLARIMETER_BIN", REPO / "target" / "release" / "polarimeter"))
    if not path.is_file():
        pytest.exit(f"{path} is missing: build it with `cargo build --release -p polar-cli` "
                    "or set POLARIMETER_BIN", returncode=2)
    return path


BIN = _binary()


def cli(*args: str, cwd: Path | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    """Runs the command with stdin closed, under a time limit."""
    return subprocess.run([str(BIN), *args], stdin=subprocess.DEVNULL, capture_output=True,
                          text=True, timeout=timeout, cwd=cwd)


def cli_json(*args: str, cwd: Path | None = None) -> dict:
    """The command's JSON output; fails the test on a non-zero exit."""
    p = cli(*args, cwd=cwd)
    assert p.returncode == 0, f"polarimeter {' '.join(args)} failed: {p.stderr}"
    return json.loads(p.stdout)


def simulated_run(factory: pytest.TempPathFactory, plan: str) -> Path:
    """A finished run of ``examples/plans/PLAN`` on the simulated rig."""
    out = factory.mktemp("runs") / Path(plan).stem
    p = cli("acquire", "run", str(EXAMPLES / "plans" / plan), "--simulate", "--out", str(out))
    assert p.returncode == 0, p.stderr
    return out


@pytest.fixture(scope="session")
def step_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished step-and-shoot run of examples/plans/capture.toml."""
    return simulated_run(tmp_path_factory, "capture.toml")


@pytest.fixture(scope="session")
def continuous_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished continuous-rotation run of examples/plans/continuous.toml."""
    return simulated_run(tmp_path_factory, "continuous.toml")
