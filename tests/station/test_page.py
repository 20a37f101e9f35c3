"""The status page at `/`, in headless Chromium (Debian's chromium): after a run, the page
given a read key shows the station healthy, the history's done item, the queue state and the
latest DoLP and AoP images; a screenshot goes to target/station-page.png (docs/station/status-page.png
is the committed one)."""

import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import httpx

from conftest import ROOT, plan_text

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars", "--window-size=1280,900", "--virtual-time-budget=8000"]


def chromium(*args):
    with tempfile.TemporaryDirectory() as profile:
        p = subprocess.run([CHROMIUM, *FLAGS, f"--user-data-dir={profile}", *args],
                           capture_output=True, text=True, timeout=120,
                           stdin=subprocess.DEVNULL)
    return p


def test_the_status_page_shows_the_station_in_chromium(station):
    with station.client("queue") as c:
        assert c.post("/api/v1/queue", json={"plan": plan_text("capture")}).status_code == 201
    station.wait_history(1)
    for name in ("dolp", "aop", "s0"):
        with station.client("read") as c:
            r = c.get(f"/api/v1/products/latest/{name}")
        assert r.status_code == 200 and r.content[:8] == b"\x89PNG\r\n\x1a\n", (name, r.status_code)
    r = httpx.get(station.url + "/")
    assert r.status_code == 200 and "text/html" in r.headers["content-type"]
    assert station.keys["read"]["key"] not in r.text
    url = f"{station.url}/#key={station.keys['read']['key']}"
    dom = chromium("--dump-dom", url)
    assert dom.returncode == 0, dom.stderr[-2000:]
    html = dom.stdout
    assert 'data-loaded="yes"' in html, html[-3000:]
    assert re.search(r'id="health" class="ok">healthy<', html), "health shown"
    assert "rooftop capture" in html and ">done<" in html, "the history's done item"
    assert re.search(r'id="dolp"[^>]*src="blob:', html) and re.search(r'id="aop"[^>]*src="blob:', html)
    shot = ROOT / "target" / "station-page.png"
    shot.parent.mkdir(exist_ok=True)
    p = chromium(f"--screenshot={shot}", url)
    assert p.returncode == 0 and shot.stat().st_size > 10_000, p.stderr[-2000:]
    # Without a key the page still loads and shows only health.
    dom = chromium("--dump-dom", station.url + "/")
    assert dom.returncode == 0 and re.search(r'id="health" class="ok">healthy<', dom.stdout)
    assert 'data-loaded="yes"' not in dom.stdout
