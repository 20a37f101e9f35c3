"""The station's API from outside: a queued plan runs to the end on the simulated rig and its
run opens in zarr-python; queue edits are all or nothing and owner-checked; run control
pauses, resumes and aborts; the event stream carries increasing change ids; the OpenAPI
description is valid OpenAPI 3.1 (openapi-spec-validator), matches the endpoints, and
docs/STATION.md names each."""

import json
import threading
import time

import httpx
import openapi_spec_validator
import zarr

from conftest import ROOT, cli, plan_text, timelapse


def test_a_queued_plan_runs_to_the_end_and_its_run_is_whole(station):
    with station.client("queue") as c:
        r = c.post("/api/v1/queue", json={"plan": plan_text("capture")})
        assert r.status_code == 201, r.text
        (item_id,) = r.json()["ids"]
    (entry,) = station.wait_history(1)
    assert entry["item"]["id"] == item_id and entry["exit"] == "done", entry
    assert entry["item"]["owner"] == station.keys["queue"]["id"]
    run = station.dir / "data" / entry["run_dir"]
    check = json.loads(cli("acquire", "check", run).stdout)
    assert check["ok"] and check["finished"], check
    # The forecast's frames are the frames the run recorded (capture: darks + 4 angles x 3).
    assert check["frames_recorded"] == entry["item"]["forecast"]["frames"] == 16
    g = zarr.open_group(str(run / "run.zarr"), mode="r")
    assert g["frames/pixels"].shape[0] == 16
    # The write was audited with the key's id.
    audit = [json.loads(l) for l in (station.dir / "data" / "audit.log").read_text().splitlines()]
    assert any(a["action"] == "queue.add" and a["key"] == station.keys["queue"]["id"] and a["ok"]
               for a in audit)


def test_queue_edits_are_all_or_nothing_and_owner_checked(station):
    with station.client("admin") as admin, station.client("queue") as mine, \
            station.client("other") as other:
        assert admin.post("/api/v1/queue/stop").status_code == 200
        bad = {"items": [{"plan": timelapse()}, {"plan": timelapse().replace("count = 4", "count = 0")}]}
        r = mine.post("/api/v1/queue", json=bad)
        assert r.status_code == 400 and r.json()["field"] == "items[1].plan", r.text
        assert "count" in r.json()["error"], "the plan's own key is named"
        assert mine.get("/api/v1/queue").json()["items"] == [], "nothing of a refused batch queued"
        ids = mine.post("/api/v1/queue", json={"items": [{"plan": timelapse(name=f"t{i}")}
                                                         for i in range(3)]}).json()["ids"]
        assert len(ids) == 3 and ids == sorted(ids)
        assert mine.post(f"/api/v1/queue/{ids[2]}/move", json={"position": 0}).status_code == 200
        order = [i["id"] for i in mine.get("/api/v1/queue").json()["items"]]
        assert order == [ids[2], ids[0], ids[1]]
        r = other.delete(f"/api/v1/queue/{ids[0]}")
        assert r.status_code == 403 and "owner" in r.json()["error"], r.text
        assert other.post(f"/api/v1/queue/{ids[0]}/move", json={"position": 2}).status_code == 403
        assert admin.delete(f"/api/v1/queue/{ids[0]}").status_code == 200
        assert other.delete("/api/v1/queue").status_code == 200, "clears only its own (none)"
        assert len(mine.get("/api/v1/queue").json()["items"]) == 2
        assert mine.delete("/api/v1/queue").status_code == 200
        assert mine.get("/api/v1/queue").json()["items"] == []
        v = mine.post("/api/v1/queue/validate", json={"plan": timelapse()})
        assert v.status_code == 200 and v.json()["items"][0]["forecast"]["frames"] == 12, v.text
        assert mine.get("/api/v1/queue").json()["items"] == [], "validate queues nothing"


def collect_events(station, stop, into):
    headers = {"Authorization": f"Bearer {station.keys['read']['key']}"}
    with httpx.Client(base_url=station.url, timeout=None) as c:
        with c.stream("GET", "/api/v1/events", headers=headers) as r:
            for line in r.iter_lines():
                if line.startswith("data:"):
                    into.append(json.loads(line[5:]))
                if stop.is_set():
                    return


def test_pause_resume_and_abort_with_the_event_stream(station):
    events, stop = [], threading.Event()
    t = threading.Thread(target=collect_events, args=(station, stop, events), daemon=True)
    t.start()
    with station.client("queue") as mine, station.client("other") as other, \
            station.client("admin") as admin:
        (item,) = mine.post("/api/v1/queue", json={"plan": timelapse(count=6)}).json()["ids"]
        station.wait(lambda s: (s["live"].get("progress") or {}).get("done", 0) >= 1, "frames")
        assert other.post("/api/v1/run/pause").status_code == 200
        s = station.wait(lambda s: s["current"] and s["current"]["phase"] == "paused", "the pause")
        assert "user" in s["current"]["pause_reason"]
        assert other.post("/api/v1/run/pause").status_code == 409
        assert other.post("/api/v1/run/resume").status_code == 200
        station.wait(lambda s: s["current"] and s["current"]["phase"] == "running"
                     and not s["current"]["resume_requested"], "the resume")
        r = other.post("/api/v1/run/abort")
        assert r.status_code == 403 and "admin" in r.json()["error"], "another key's item"
        assert admin.post("/api/v1/run/abort").status_code == 200
        (entry,) = station.wait_history(1)
        assert entry["item"]["id"] == item and entry["exit"] == "aborted", entry
    time.sleep(0.5)
    stop.set()
    assert events[0]["kind"] == "hello" and "id" not in events[0]
    ids = [e["id"] for e in events[1:]]
    assert ids == sorted(ids) and len(set(ids)) == len(ids), "change ids increase"
    states = [e["data"].get("state") for e in events if e["kind"] == "run.state"]
    for s in ("running", "paused", "aborted"):
        assert s in states, (s, states)
    audit = (station.dir / "data" / "audit.log").read_text()
    assert f'"key":"{station.keys["admin"]["id"]}"' in audit.replace(" ", "")


def test_the_openapi_description_matches_the_endpoints_and_the_docs(station):
    doc = httpx.get(station.url + "/api/v1/openapi.json").json()
    assert doc["openapi"].startswith("3.1")
    # Valid OpenAPI 3.1 by the specification's own schema (raises on any violation).
    openapi_spec_validator.validate(doc)
    docs = (ROOT / "docs" / "STATION.md").read_text()
    with station.client("admin") as c:
        for path, ops in doc["paths"].items():
            assert f"`{path}`" in docs or path in docs, f"docs/STATION.md lacks {path}"
            for method in ops:
                if path.endswith("/events"):
                    continue
                concrete = path.replace("{id}", "999999").replace("{name}", "dolp")
                r = c.request(method.upper(), concrete, json={})
                assert r.status_code != 404 or "item" in r.text or "no run" in r.text, \
                    (method, path, r.status_code, r.text)
    r = httpx.get(station.url + "/api/v1/nothing-here")
    assert r.status_code == 404 and "openapi" in r.json()["error"]


def test_health_tells_the_truth(station):
    r = httpx.get(station.url + "/healthz")
    h = r.json()
    assert r.status_code == 200 and h["ok"], h
    assert h["devices"]["ok"] and h["disk"]["free_bytes"] > h["disk"]["reserve_bytes"]
    assert h["clock"]["ok"]


def test_sigterm_pauses_the_run_and_the_next_start_resumes_it(station):
    """systemctl stop with an event stream open: the going run pauses at a safe point, the
    station exits promptly, and the next start resumes the run to the end."""
    events, stop = [], threading.Event()
    threading.Thread(target=collect_events, args=(station, stop, events), daemon=True).start()
    with station.client("queue") as mine:
        (item,) = mine.post("/api/v1/queue", json={"plan": timelapse(count=5)}).json()["ids"]
    station.wait(lambda s: (s["live"].get("progress") or {}).get("done", 0) >= 1, "frames")
    t0 = time.monotonic()
    station.stop()
    assert time.monotonic() - t0 < 30, "the stop waited for the event stream"
    state = json.loads((station.dir / "data" / "state.json").read_text())
    assert state["current"]["phase"] == "paused" and state["current"]["resume_on_start"], state
    station.start()
    (entry,) = station.wait_history(1)
    assert entry["item"]["id"] == item and entry["exit"] == "done", entry
    assert entry["crash_resumes"] == 0, "a clean stop is not a crash"
    check = json.loads(cli("acquire", "check", station.dir / "data" / entry["run_dir"]).stdout)
    assert check["ok"] and check["frames_recorded"] >= 15, check
    stop.set()
