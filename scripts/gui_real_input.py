#!/usr/bin/env python3
"""polarimeter-gui as a user drives it: real X input events (xdotool) on the real window under
Xvfb, at 900x650 points.

The GUI writes its state and where its named controls are (``--state-file``); this script moves
the X pointer to a control's centre and clicks, types or turns the wheel there, as a person
would, and waits for the state to follow. The path: connect the simulated devices, type an
exposure below the camera's minimum (a note names it, nothing is clamped), live polarimetry
for a half turn and stop (no stale raw frame), a run paused, resumed and aborted while it
runs, the devices connected again after it, the log's last line brought into the window with
the wheel, and the left panel made narrower by dragging its edge. Each step has a time
limit; the script exits 1 naming the step that failed, with the GUI's last state and stderr.

    python3 scripts/gui_real_input.py --bin target/release/polarimeter-gui

Needs Xvfb and xdotool (scripts/test.sh installs both).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

WIDTH, HEIGHT = 900, 650

# A capture long enough to pause, resume and abort while it runs (40 sets of 4 frames).
PLAN = """name = "real input"
kind = "capture"

[capture]
angles_deg = [0, 45, 90, 135]
exposure_us = [250]
repeats = 40
darks_before = 1
darks_after = 0

[simulation]
width = 96
height = 72
seed = 3
stage_deg_per_s = 90
"""


class Failed(Exception):
    pass


class Session:
    def __init__(self, gui_bin: Path, scratch: Path) -> None:
        self.scratch = scratch
        self.state_path = scratch / "state.json"
        self.display = self._start_xvfb()
        self.env = dict(os.environ, DISPLAY=self.display)
        self.env.pop("WAYLAND_DISPLAY", None)
        plan = scratch / "plan.toml"
        plan.write_text(PLAN)
        self.stderr = open(scratch / "gui.stderr", "w")
        self.gui = subprocess.Popen(
            [str(gui_bin), "--simulate", "--out", str(scratch / "runs"), "--plan", str(plan),
             "--window-size", f"{WIDTH}x{HEIGHT}", "--state-file", str(self.state_path)],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=self.stderr,
            env=self.env)
        self.window = None

    def _start_xvfb(self) -> str:
        for n in range(90, 140):
            if Path(f"/tmp/.X{n}-lock").exists() or Path(f"/tmp/.X11-unix/X{n}").exists():
                continue
            self.xvfb = subprocess.Popen(
                ["Xvfb", f":{n}", "-screen", "0", "1280x1024x24", "-nolisten", "tcp"],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            for _ in range(100):
                if Path(f"/tmp/.X11-unix/X{n}").exists():
                    return f":{n}"
                if self.xvfb.poll() is not None:
                    break
                time.sleep(0.05)
            self.xvfb.kill()
        raise Failed("no free X display for Xvfb in :90..:139")

    def close(self) -> None:
        if self.gui.poll() is None:
            self.gui.send_signal(signal.SIGTERM)
            try:
                self.gui.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.gui.kill()
        self.xvfb.terminate()
        self.xvfb.wait(timeout=10)
        self.stderr.close()

    def xdotool(self, *args: str) -> str:
        r = subprocess.run(["xdotool", *args], env=self.env, capture_output=True, text=True,
                           timeout=20, stdin=subprocess.DEVNULL)
        if r.returncode != 0:
            raise Failed(f"xdotool {' '.join(args)}: {r.stderr.strip()}")
        return r.stdout

    def state(self) -> dict:
        try:
            return json.loads(self.state_path.read_text())
        except (OSError, json.JSONDecodeError):
            return {}

    def wait(self, what: str, cond, limit_s: float = 60.0) -> dict:
        t0 = time.monotonic()
        while time.monotonic() - t0 < limit_s:
            if self.gui.poll() is not None:
                raise Failed(f"waiting for {what}: the GUI exited with {self.gui.returncode}")
            s = self.state()
            if s and cond(s):
                return s
            time.sleep(0.1)
        raise Failed(f"waited {limit_s:.0f} s for {what}")

    def find_window(self) -> None:
        out = self.xdotool("search", "--sync", "--onlyvisible", "--name", "^polarimeter$")
        self.window = out.split()[0]
        self.xdotool("windowmove", self.window, "0", "0")
        # No window manager gives the window the keyboard: give it as one would.
        self.xdotool("windowfocus", "--sync", self.window)
        time.sleep(0.3)

    def origin(self) -> tuple[float, float]:
        geo = dict(line.split("=", 1) for line in
                   self.xdotool("getwindowgeometry", "--shell", self.window).split())
        return float(geo["X"]), float(geo["Y"])

    def centre(self, name: str, state: dict | None = None) -> tuple[int, int]:
        s = state or self.wait(f"the control {name!r}", lambda s: name in s.get("controls", {}))
        x0, y0, x1, y1 = s["controls"][name]
        ppp = s.get("pixels_per_point", 1.0)
        ox, oy = self.origin()
        return int(ox + 0.5 * (x0 + x1) * ppp), int(oy + 0.5 * (y0 + y1) * ppp)

    def click(self, name: str) -> None:
        x, y = self.centre(name)
        self.xdotool("mousemove", "--sync", str(x), str(y))
        time.sleep(0.15)
        self.xdotool("click", "1")
        time.sleep(0.3)


def steps(s: Session) -> list[tuple[str, float]]:
    done: list[tuple[str, float]] = []
    t = time.monotonic()

    def mark(what: str) -> None:
        nonlocal t
        done.append((what, time.monotonic() - t))
        t = time.monotonic()

    s.wait("the first state", lambda st: "controls" in st, 60)
    s.find_window()
    st = s.wait("the window at 900x650", lambda st: st["window"] == [WIDTH, HEIGHT], 20)
    mark(f"window {st['window'][0]:.0f}x{st['window'][1]:.0f} points")

    s.click("Devices")
    s.click("Connect")
    s.wait("connected", lambda st: st["connected"] and not st["device_pending"], 60)
    mark("Connect: connected")

    # An exposure below the simulated camera's 10 us, typed into the field.
    s.click("Exposure (us)")
    s.xdotool("key", "ctrl+a")
    s.xdotool("type", "--delay", "50", "1")
    s.xdotool("key", "Return")
    st = s.wait("the note on the exposure",
                lambda st: any(k.startswith("note: Exposure (us) = 1 ") for k in st["controls"]), 10)
    mark("exposure 1 us typed: " + next(k for k in st["controls"] if k.startswith("note: ")))
    s.click("Exposure (us)")
    s.xdotool("key", "ctrl+a")
    s.xdotool("type", "--delay", "50", "250")
    s.xdotool("key", "Return")
    s.wait("the note gone", lambda st: not any(k.startswith("note: ") for k in st["controls"]), 10)
    mark("exposure 250 us typed: the note is gone")

    s.click("Live polarimetry")
    s.wait("a half turn", lambda st: (st["half_turns"] or 0) >= 1, 90)
    s.click("Stop")
    st = s.wait("live stopped", lambda st: st["live"] is None, 30)
    if st["live_frame_shown"]:
        raise Failed("after live polarimetry the panel holds a camera frame")
    mark("live polarimetry: a half turn, stopped, no stale frame")

    s.click("Start")
    s.wait("Running", lambda st: st["status"].startswith("State: Running"), 60)
    s.click("Pause")
    s.wait("Paused", lambda st: st["status"].startswith("State: Paused"), 60)
    s.click("Resume")
    st = s.wait("Running again", lambda st: st["status"].startswith("State: Running"), 60)
    before = st["done"]
    s.click("Abort")
    st = s.wait("Aborted", lambda st: st["status"].startswith("State: Aborted"), 60)
    if not st["done"] < st["planned"]:
        raise Failed(f"the run was not aborted while it ran: {st['done']} of {st['planned']}")
    mark(f"run: paused, resumed at {before} frames, aborted at {st['done']} of {st['planned']}")
    st = s.wait("the devices connected again", lambda st: st["connected"], 60)
    mark("devices connected again after the run")

    # The log's last line (aborted) into the 650-point window with the wheel over the panel.
    x, y = s.centre("Forecast")
    s.xdotool("mousemove", "--sync", str(x), str(y))
    for turn in range(30):
        st = s.state()
        rect = st["controls"].get("log last line")
        if rect and rect[3] <= HEIGHT and any("aborted" in l for l in st["log_tail"]):
            break
        s.xdotool("click", "5")
        time.sleep(0.25)
    else:
        raise Failed(f"the log's last line stays outside the window: {rect}")
    mark(f"log's last line at y {rect[1]:.0f}-{rect[3]:.0f} after {turn} wheel turns")

    # The left panel's right edge dragged 150 points to the left.
    st = s.state()
    x0, y0, x1, y1 = st["controls"]["plan panel"]
    ox, oy = s.origin()
    ppp = st.get("pixels_per_point", 1.0)
    ex, ey = int(ox + x1 * ppp), int(oy + 0.5 * (y0 + y1) * ppp)
    # Hover the edge first (egui shows the resize cursor), then press and drag slowly.
    s.xdotool("mousemove", "--sync", str(ex), str(ey))
    time.sleep(0.3)
    s.xdotool("mousemove", "--sync", str(ex + 1), str(ey))
    time.sleep(0.3)
    s.xdotool("mousedown", "1")
    time.sleep(0.3)
    for k in range(1, 11):
        s.xdotool("mousemove", "--sync", str(ex - 15 * k), str(ey))
        time.sleep(0.1)
    s.xdotool("mouseup", "1")
    st = s.wait("the panel narrower",
                lambda st: st["controls"]["plan panel"][2] < x1 - 100, 10)
    mark(f"left panel dragged: right edge {x1:.0f} -> {st['controls']['plan panel'][2]:.0f}")
    return done


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bin", required=True, type=Path, help="the polarimeter-gui binary")
    ap.add_argument("--scratch", type=Path, default=Path("target/gui-real-input"))
    args = ap.parse_args()
    for tool in ("Xvfb", "xdotool"):
        if shutil.which(tool) is None:
            print(f"gui_real_input: {tool} is not installed (scripts/test.sh installs it)",
                  file=sys.stderr)
            return 2
    if not args.bin.is_file():
        print(f"gui_real_input: --bin {args.bin}: not a file", file=sys.stderr)
        return 2
    shutil.rmtree(args.scratch, ignore_errors=True)
    args.scratch.mkdir(parents=True)
    s = Session(args.bin.resolve(), args.scratch.resolve())
    code = 0
    try:
        for what, secs in steps(s):
            print(f"ok {secs:6.1f} s  {what}")
    except Failed as e:
        print(f"gui_real_input: FAILED: {e}", file=sys.stderr)
        print(f"last state: {json.dumps(s.state())[:3000]}", file=sys.stderr)
        code = 1
    finally:
        s.close()
    err = (args.scratch / "gui.stderr").read_text(errors="replace")
    if "panicked" in err:
        print(f"gui_real_input: the GUI panicked:\n{err[-3000:]}", file=sys.stderr)
        code = 1
    elif code:
        print(f"GUI stderr (last lines):\n{err[-2000:]}", file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
