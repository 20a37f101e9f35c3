"""Schedules from the model, judged by pvlib: a daily time-lapse from sun elevation 10 deg
rising to 10 deg setting, every 30 minutes, run through a whole December day at the rig's
site on the station's fast simulated clock. Every run starts with the sun above 10 deg (by
pvlib's SPA), none outside, the first within a poll of the window opening, and the station
names the next day's opening as the next start."""

import datetime as dt
import time

import pandas as pd
import pvlib

from conftest import Station, timelapse

SITE = dict(latitude=43.08, longitude=-77.67, altitude=160)  # examples/rigs/sim.toml's [site]
START = "2026-12-21T12:00:00Z"
SPEED = 600  # ten minutes a second


def elevation(unix_s):
    t = pd.DatetimeIndex([pd.Timestamp(unix_s, unit="s", tz="UTC")])
    sp = pvlib.solarposition.get_solarposition(t, SITE["latitude"], SITE["longitude"],
                                               altitude=SITE["altitude"], method="nrel_numpy")
    return float(sp["elevation"].iloc[0])


def crossing(after_unix, level=10.0):
    """pvlib's first minute after `after_unix` with the sun above `level`."""
    t = pd.date_range(pd.Timestamp(after_unix, unit="s", tz="UTC"), periods=2 * 24 * 60,
                      freq="1min")
    sp = pvlib.solarposition.get_solarposition(t, SITE["latitude"], SITE["longitude"],
                                               altitude=SITE["altitude"], method="nrel_numpy")
    above = sp.index[sp["elevation"] > level]
    return int(above[0].timestamp())


def test_a_day_of_a_sun_driven_time_lapse(tmp_path):
    st = Station(tmp_path, f'[simulation]\nclock_start = "{START}"\nclock_speed = {SPEED}\n')
    st.key("admin", "admin")
    st.start()
    try:
        schedule = {"sun_above_deg": 10, "every_s": 1800}
        with st.client("admin") as c:
            bad = c.post("/api/v1/queue", json={"plan": timelapse(count=1),
                                                "schedule": {"sun_above_deg": 100}})
            assert bad.status_code == 400 and bad.json()["field"] == "schedule.sun_above_deg"
            r = c.post("/api/v1/queue", json={"plan": timelapse(count=1, name="daily"),
                                              "schedule": schedule})
            assert r.status_code == 201, r.text
            q = c.get("/api/v1/queue").json()
            start_unix = int(dt.datetime.fromisoformat(START.replace("Z", "+00:00")).timestamp())
            opening = crossing(start_unix)
            said = dt.datetime.fromisoformat(q["items"][0]["next_start"].replace("Z", "+00:00"))
            assert abs(said.timestamp() - opening) <= 120, (said, opening)
            # Until station time passes 22:00 UTC (after sunset at the site).
            end = start_unix + 10 * 3600
            deadline = time.monotonic() + 240
            while time.monotonic() < deadline:
                s = c.get("/api/v1/status").json()
                now = dt.datetime.fromisoformat(s["time"].replace("Z", "+00:00")).timestamp()
                if now > end and s["current"] is None:
                    break
                time.sleep(0.5)
            assert now > end, "the simulated day did not pass in time"
            history = c.get("/api/v1/history").json()["items"]
            starts = [h["started_unix"] for h in history]
            assert len(starts) >= 3, starts
            for h in history:
                assert h["exit"] == "done", h
                e = elevation(h["started_unix"])
                assert e > 9.9, f"a run started with the sun at {e:.2f} deg"
            # One worker poll is a minute of station time; the margin is one real second.
            assert starts[0] - opening <= 60 + SPEED, "the first run starts at the opening"
            gaps = [b - a for a, b in zip(starts, starts[1:])]
            assert min(gaps) >= 1800, f"every_s is honoured: {gaps}"
            # The next start is tomorrow's opening.
            q = c.get("/api/v1/queue").json()
            said = dt.datetime.fromisoformat(q["items"][0]["next_start"].replace("Z", "+00:00"))
            tomorrow = crossing(end)
            assert abs(said.timestamp() - tomorrow) <= 120, (said, tomorrow)
            assert q["items"][0]["runs_done"] == len(history)
            print(f"{len(starts)} runs; first {starts[0] - opening} s after pvlib's opening; "
                  f"elevations at start {[round(elevation(t), 2) for t in starts]}; next start "
                  f"{said.timestamp() - tomorrow:+.0f} s from pvlib's next opening")
    finally:
        st.stop()
