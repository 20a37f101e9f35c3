"""The kill campaign: SIGKILL the station at 20 seeded random moments (during sets, between
items, right after queue edits), restart it each time, and check that every item it accepted
ran exactly once to the end, the queue and history are whole, and every run is whole: the
run check passes, zarr-python opens it, and its counted frames are exactly the plan's."""

import json
import random
import signal
import time

import httpx
import numpy as np
import zarr

from conftest import Station, cli, plan_text, timelapse

KILLS = 20


def test_kills_at_random_moments_lose_and_duplicate_nothing(tmp_path):
    rng = random.Random(20261206)
    st = Station(tmp_path)
    st.key("admin", "admin")
    st.start()
    accepted = {}
    plans = [timelapse(count=3, interval_s=1, name="a"), plan_text("capture"),
             timelapse(count=4, interval_s=1, name="b")]

    def submit(text):
        try:
            with st.client("admin") as c:
                r = c.post("/api/v1/queue", json={"plan": text})
            if r.status_code == 201:
                for i in r.json()["ids"]:
                    accepted[i] = r.json()
        except httpx.HTTPError:
            pass  # killed while answering: the item may or may not be queued, never twice

    for p in plans:
        submit(p)
    crash_resumes_seen = 0
    for k in range(KILLS):
        time.sleep(rng.uniform(0.1, 2.5))
        if k % 4 == 0:
            submit(timelapse(count=2, interval_s=1, name=f"k{k}"))
        st.stop(signal.SIGKILL)
        st.start()
    # Let everything finish.
    deadline = time.monotonic() + 400
    while time.monotonic() < deadline:
        with st.client("admin") as c:
            s = c.get("/api/v1/status").json()
        if s["queued"] == 0 and s["current"] is None:
            break
        time.sleep(0.5)
    history = st.history()
    st.stop()
    ids = [h["item"]["id"] for h in history]
    assert len(ids) == len(set(ids)), f"an item ran twice: {ids}"
    assert set(accepted) <= set(ids), f"accepted items lost: {set(accepted) - set(ids)}"
    for h in history:
        assert h["exit"] == "done", h
        crash_resumes_seen += h["crash_resumes"]
        run = st.dir / "data" / h["run_dir"]
        check = json.loads(cli("acquire", "check", run, timeout=120).stdout)
        assert check["ok"] and check["finished"], (h["run_dir"], check)
        g = zarr.open_group(str(run / "run.zarr"), mode="r")
        counted = int(np.asarray(g["frames/accepted"][:]).sum())
        assert counted == h["item"]["forecast"]["frames"], (h["run_dir"], counted)
    assert crash_resumes_seen >= 1, "some kill landed during a run"
    print(f"{KILLS} kills: {len(history)} items done, {crash_resumes_seen} resumed after a crash")
