"""Finished runs pushed to an S3-compatible bucket: moto's server (from PyPI, started here on
loopback) stands for the bucket. A station whose bucket is down at first records the failed
attempts and retries; once the server is up the run goes up whole, the completion marker last,
and zarr-python (through obstore) opens the run from the bucket with the same products and
frames whose XXH3-64 hashes match the run's own record. Retention then removes the uploaded
run's raw frames locally (`frames_days = 0`): the local store still opens, without them, and
says so."""

import json
import time

import numpy as np
import obstore
import xxhash
import zarr

from conftest import (BUCKET, PREFIX, Station, bucket, free_port, plan_text, start_moto,
                      upload_config)

def test_a_finished_run_goes_up_whole_and_retention_removes_its_frames(tmp_path):
    port = free_port()
    (tmp_path / "s3.secret").write_text("testing\n")
    st = Station(tmp_path, extra=upload_config(port) + "[retention]\nframes_days = 0\n")
    st.key("admin", "admin")
    st.start()
    moto = None
    log = open(tmp_path / "moto.log", "w")
    try:
        with st.client("admin") as c:
            assert c.post("/api/v1/queue", json={"plan": plan_text("capture")}).status_code == 201
        (entry,) = st.wait_history(1)
        assert entry["exit"] == "done", entry
        # The bucket is not there yet: attempts fail, are recorded, and the run stays whole.
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            (entry,) = st.history()
            if entry["upload"].get("error"):
                break
            time.sleep(0.3)
        assert entry["upload"]["state"] == "pending" and entry["upload"]["error"], entry
        run = st.dir / "data" / entry["run_dir"]
        assert (run / "run.zarr" / "frames" / "pixels").is_dir(), "kept until uploaded"
        # The server comes up: the retry (within the backoff, 5 s then 10 s) uploads it.
        moto = start_moto(port, log)
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            (entry,) = st.history()
            if entry["upload"]["state"] == "done" and entry.get("removed"):
                break
            time.sleep(0.3)
        assert entry["upload"]["state"] == "done", entry
        name = run.name
        assert entry["upload"]["url"] == f"s3://{BUCKET}/{PREFIX}/{name}"

        remote = bucket(port, f"{PREFIX}/{name}")
        marker = json.loads(bytes(obstore.get(remote, "_upload_complete.json").bytes()))
        listed = {o["path"]: o["size"] for batch in obstore.list(remote) for o in batch}
        for f in marker["files"]:
            assert listed[f["key"]] == f["bytes"], f
        assert "journal.jsonl" in listed and "run.zarr/zarr.json" in listed

        store = zarr.storage.ObjectStore(bucket(port, f"{PREFIX}/{name}/run.zarr"),
                                         read_only=True)
        up = zarr.open_group(store, mode="r")
        pixels = up["frames/pixels"][...]
        assert pixels.shape[0] == 16, pixels.shape
        hashes = up["frames/hash"][...]
        for i in range(pixels.shape[0]):
            assert xxhash.xxh3_64_intdigest(pixels[i].astype("<u2").tobytes()) == int(hashes[i])

        # Retention: the local frames are gone (uploaded first), the rest opens and says so.
        assert entry["removed"] == "frames", entry
        local = zarr.open_group(str(run / "run.zarr"), mode="r")
        assert "pixels" not in local["frames"].array_keys()
        assert local.attrs["retention"]["frames_removed_unix"] > 0
        np.testing.assert_array_equal(local["products/dolp"][...], up["products/dolp"][...])
        audit = [json.loads(l) for l in (st.dir / "data" / "audit.log").read_text().splitlines()]
        assert any(a["action"] == "upload" and a["ok"] for a in audit)
        assert any(a["action"] == "upload" and not a["ok"] for a in audit)
        assert any(a["action"] == "retention" and a["ok"] for a in audit)
    finally:
        st.stop()
        if moto:
            moto.terminate()
            moto.wait(timeout=30)
        log.close()
