"""The station client (polarimeter.station) against a real station on the simulated rig:
submit and wait, the queue and validation, the event stream with change ids, refusals as
StationError with the status and field, and health."""

from __future__ import annotations

import json
import subprocess
import threading

import pytest

from conftest import BIN, EXAMPLES

import polarimeter
from polarimeter import Station, StationError


@pytest.fixture
def station(tmp_path):
    cfg = tmp_path / "station.toml"
    cfg.write_text(f'listen = "127.0.0.1:0"\ndata_dir = "data"\n'
                   f'rig = "{EXAMPLES / "rigs" / "sim.toml"}"\nreserve_mb = 64\n')
    subprocess.run([str(BIN), "station", "key", "create", "--config", str(cfg), "--scope",
                    "queue,control", "--key-out", str(tmp_path / "key")], check=True,
                   capture_output=True)
    (tmp_path / "tmp").mkdir()
    p = subprocess.Popen([str(BIN), "station", "serve", "--config", str(cfg)],
                         stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                         stdin=subprocess.DEVNULL, text=True,
                         env={"TMPDIR": str(tmp_path / "tmp"), "PATH": "/usr/bin:/bin"})
    url = json.loads(p.stdout.readline())["listening"]
    yield Station(url, key_file=tmp_path / "key"), tmp_path
    p.terminate()
    try:
        p.wait(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
        p.stdout.close()


def test_submit_wait_and_the_event_stream(station):
    st, tmp = station
    assert st.health()["ok"]
    events: list[dict] = []

    def listen():
        for e in st.events():
            events.append(e)
            if e["kind"] == "run.state" and e["data"]["state"] == "done":
                return

    t = threading.Thread(target=listen, daemon=True)
    t.start()
    forecast = st.validate(EXAMPLES / "plans" / "capture.toml")[0]["forecast"]
    assert forecast["frames"] == 16 and forecast["bytes"] > 0
    ids = st.submit(EXAMPLES / "plans" / "capture.toml")
    (entry,) = st.wait(ids, timeout_s=180)
    assert entry["exit"] == "done" and entry["item"]["id"] == ids[0]
    t.join(timeout=30)
    assert events[0]["kind"] == "hello"
    change_ids = [e["id"] for e in events[1:]]
    assert change_ids == sorted(change_ids) and len(set(change_ids)) == len(change_ids)
    assert any(e["kind"] == "run.progress" for e in events)
    # The run opens as one Dataset, as any run does.
    import xarray as xr

    ds = polarimeter.open_run(tmp / "data" / entry["run_dir"])
    assert isinstance(ds, xr.Dataset) and ds.sizes["frame"] == 16


def test_refusals_name_the_status_and_field(station):
    st, _ = station
    with pytest.raises(StationError) as e:
        st.submit("name = 'x'\nkind = 'time-lapse'\n[time-lapse]\nangles_deg = [0, 60, 120]\n"
                  "exposure_us = -1\ninterval_s = 1\ncount = 1\n")
    assert e.value.status == 400 and e.value.field == "plan"
    assert "exposure_us" in e.value.message
    with pytest.raises(StationError) as e:
        st.submit(EXAMPLES / "plans" / "capture.toml", schedule={"sun_above_deg": 100})
    assert e.value.status == 400 and e.value.field == "schedule.sun_above_deg"
    with pytest.raises(StationError) as e:
        st.pause()
    assert e.value.status == 409
    with pytest.raises(StationError) as e:
        Station(st.url, key="pst_000000000000_" + "0" * 64).status()
    assert e.value.status == 401
    with pytest.raises(StationError) as e:
        Station("http://127.0.0.1:1").status()
    assert e.value.status == 0
    with pytest.raises(FileNotFoundError):
        st.submit(EXAMPLES / "plans" / "missing.toml")
