"""A station on the simulated rig, started as a user starts it (`polarimeter station serve`),
with keys of every scope made by `polarimeter station key create`; the tests talk to it with
httpx only over loopback."""

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import httpx
import pytest

ROOT = Path(__file__).resolve().parents[2]
BIN = os.environ.get("POLARIMETER_BIN", str(ROOT / "target" / "release" / "polarimeter"))
SIM_RIG = ROOT / "examples" / "rigs" / "sim.toml"


def cli(*args, check=True, timeout=60):
    """Runs the command line; its completed process."""
    p = subprocess.run([BIN, *map(str, args)], capture_output=True, text=True,
                       stdin=subprocess.DEVNULL, timeout=timeout)
    if check and p.returncode != 0:
        raise AssertionError(f"{args}: exit {p.returncode}: {p.stderr}")
    return p


class Station:
    """One station process and its keys."""

    def __init__(self, tmp: Path, extra: str = ""):
        self.dir = tmp
        self.config = tmp / "station.toml"
        self.config.write_text(
            f'listen = "127.0.0.1:0"\ndata_dir = "data"\nrig = "{SIM_RIG}"\n'
            f"reserve_mb = 64\nauto_resume = 3\n{extra}")
        self.keys = {}
        self.proc = None
        self.url = None

    def key(self, name, scopes, *more):
        out = cli("station", "key", "create", "--config", self.config, "--scope", scopes,
                  "--note", name, *more)
        k = json.loads(out.stdout)
        self.keys[name] = k
        return k

    def start(self):
        self.log = open(self.dir / "serve.err", "a")
        # The simulated rig's pseudo-terminal links go under TMPDIR: a SIGKILL leaves them
        # in the test's directory, not in /tmp.
        tmp = self.dir / "tmp"
        tmp.mkdir(exist_ok=True)
        self.proc = subprocess.Popen([BIN, "station", "serve", "--config", str(self.config)],
                                     stdout=subprocess.PIPE, stderr=self.log,
                                     stdin=subprocess.DEVNULL, text=True,
                                     env=dict(os.environ, TMPDIR=str(tmp)))
        line = self.proc.stdout.readline()
        assert line, f"the station did not start: {(self.dir / 'serve.err').read_text()}"
        self.url = json.loads(line)["listening"]
        return self

    def stop(self, sig=signal.SIGTERM, timeout=90):
        if self.proc and self.proc.poll() is None:
            self.proc.send_signal(sig)
            self.proc.wait(timeout=timeout)
        if self.proc:
            self.proc.stdout.close()
            self.log.close()
        self.proc = None

    def client(self, name=None, **kw):
        headers = {}
        if name:
            headers["Authorization"] = f"Bearer {self.keys[name]['key']}"
        return httpx.Client(base_url=self.url, headers=headers, timeout=30, **kw)

    def wait(self, predicate, what, timeout_s=120, name="admin"):
        """Polls the status until `predicate(status)`; the status."""
        deadline = time.monotonic() + timeout_s
        with self.client(name) as c:
            while time.monotonic() < deadline:
                s = c.get("/api/v1/status").json()
                if predicate(s):
                    return s
                time.sleep(0.2)
        raise AssertionError(f"timed out waiting for {what}: {s}")

    def history(self):
        with self.client("admin") as c:
            return c.get("/api/v1/history").json()["items"]

    def wait_history(self, n, timeout_s=180):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            h = self.history()
            if len(h) >= n:
                return h
            time.sleep(0.3)
        raise AssertionError(f"timed out waiting for {n} history entries: {self.history()}")


@pytest.fixture
def station(tmp_path):
    st = Station(tmp_path)
    st.key("admin", "admin")
    st.key("queue", "queue")
    st.key("other", "queue,control")
    st.key("read", "read")
    st.start()
    yield st
    st.stop()


def plan_text(name="capture"):
    return (ROOT / "examples" / "plans" / f"{name}.toml").read_text()


def timelapse(count=4, interval_s=2, name="tl"):
    """A time-lapse long enough to pause, abort and kill."""
    return (f'name = "{name}"\nkind = "time-lapse"\n[time-lapse]\nangles_deg = [0, 60, 120]\n'
            f"exposure_us = 250\ninterval_s = {interval_s}\ncount = {count}\n")
