"""The kill campaign: SIGKILL the station at 20 moments, 16 seeded random ones (during sets,
between items, right after queue edits) and 4 aimed at an upload going, restart it each time,
and check that every item it accepted ran exactly once to the end, the queue and history are
whole, and every run is whole: the run check passes, zarr-python opens it, and its counted
frames are exactly the plan's. The station uploads each finished run to moto's S3 server
meanwhile: every run ends up in the bucket whole (its completion marker lists every file at
the local file's size) and zarr-python counts the same frames there."""

import json
import random
import signal
import time

import httpx
import numpy as np
import obstore
import zarr

from conftest import (PREFIX, Station, bucket, cli, free_port, plan_text, start_moto, timelapse,
                      upload_config)

KILLS = 20


def test_kills_at_random_moments_lose_and_duplicate_nothing(tmp_path):
    rng = random.Random(20261206)
    port = free_port()
    log = open(tmp_path / "moto.log", "w")
    moto = start_moto(port, log)
    (tmp_path / "s3.secret").write_text("testing\n")
    st = Station(tmp_path, extra=upload_config(port))
    st.key("admin", "admin")
    st.start()
    try:
        campaign(st, rng, port)
    finally:
        st.stop()
        moto.terminate()
        moto.wait(timeout=30)
        log.close()


def uploading(st):
    """Whether an upload is going: its attempt counted (saved as it starts), not done, and
    not failed."""
    try:
        return any(h.get("upload", {}).get("state") == "pending"
                   and h["upload"]["attempts"] >= 1 and not h["upload"].get("error")
                   for h in st.history())
    except httpx.HTTPError:
        return False


def campaign(st, rng, port):
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
        if k % 5 == 3:
            # Aimed at an upload: wait (up to 20 s) until one is going.
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and not uploading(st):
                time.sleep(0.01)
        else:
            time.sleep(rng.uniform(0.1, 2.5))
        if k % 4 == 0:
            submit(timelapse(count=2, interval_s=1, name=f"k{k}"))
        st.stop(signal.SIGKILL)
        st.start()
    # Let everything finish, uploads included.
    deadline = time.monotonic() + 400
    while time.monotonic() < deadline:
        with st.client("admin") as c:
            s = c.get("/api/v1/status").json()
        uploaded = all(h["upload"]["state"] == "done" for h in st.history())
        if s["queued"] == 0 and s["current"] is None and uploaded:
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
        # In the bucket: whole (the marker's every file, at the local file's size), and the
        # same frames counted by zarr-python reading from it.
        assert h["upload"]["state"] == "done", h
        remote = bucket(port, f"{PREFIX}/{run.name}")
        marker = json.loads(bytes(obstore.get(remote, "_upload_complete.json").bytes()))
        listed = {o["path"]: o["size"] for batch in obstore.list(remote) for o in batch}
        for f in marker["files"]:
            assert listed[f["key"]] == f["bytes"] == (run / f["key"]).stat().st_size, f
        up = zarr.open_group(zarr.storage.ObjectStore(
            bucket(port, f"{PREFIX}/{run.name}/run.zarr"), read_only=True), mode="r")
        assert int(np.asarray(up["frames/accepted"][:]).sum()) == counted
    assert crash_resumes_seen >= 1, "some kill landed during a run"
    # An attempt is counted when it starts: more than one is an upload a kill cut short
    # (4 kills were aimed at uploads going).
    uploads_cut = sum(h["upload"]["attempts"] > 1 for h in history)
    assert uploads_cut >= 1, "no kill landed during an upload"
    print(f"{KILLS} kills: {len(history)} items done, {crash_resumes_seen} resumed after a crash, "
          f"{len(history)} uploaded ({uploads_cut} taken up again after a kill)")
