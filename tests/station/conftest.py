"""A station on the simulated rig, started as a user starts it (`polarimeter station serve`),
with keys of every scope made by `polarimeter station key create`; the tests talk to it with
httpx only over loopback."""

import json
import os
import signal
import socket
import subprocess
import time
import urllib.request
from pathlib import Path

import httpx
import pytest

ROOT = Path(__file__).resolve().parents[2]
BIN = os.environ.get("POLARIMETER_BIN", str(ROOT / "target" / "release" / "polarimeter"))
SIM_RIG = ROOT / "examples" / "rigs" / "sim.toml"


# moto's S3 server (tests/station/moto-requirements.txt, in its own venv).
MOTO = os.environ.get("MOTO_SERVER", str(ROOT / "target" / "moto-venv" / "bin" / "moto_server"))
BUCKET, PREFIX = "runs", "roof-1"


def free_port():
    """A free loopback port."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_moto(port, log):
    """moto's S3 server on loopback at `port`, once it answers, with the test bucket made."""
    proc = subprocess.Popen([MOTO, "-H", "127.0.0.1", "-p", str(port)], stdout=log,
                            stderr=log, stdin=subprocess.DEVNULL)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/moto-api/", timeout=1)
            break
        except OSError:
            time.sleep(0.2)
    else:
        proc.kill()
        raise AssertionError("moto_server did not start")
    urllib.request.urlopen(urllib.request.Request(f"http://127.0.0.1:{port}/{BUCKET}",
                                                  method="PUT"), timeout=5)
    return proc


def bucket(port, prefix):
    """The test bucket on moto's server at `port`, under `prefix`, as obstore sees it."""
    from obstore.store import S3Store

    return S3Store(BUCKET, prefix=prefix, endpoint=f"http://127.0.0.1:{port}",
                   region="us-east-1", access_key_id="testing", secret_access_key="testing",
                   virtual_hosted_style_request=False, client_options={"allow_http": True})


def upload_config(port):
    """The station file's [upload] for the test bucket (the secret in s3.secret beside it)."""
    return (f'[upload]\nurl = "s3://{BUCKET}/{PREFIX}"\nendpoint = "http://127.0.0.1:{port}"\n'
            'access_key_id = "testing"\nsecret_access_key_file = "s3.secret"\n')


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
