#!/usr/bin/env python3
"""Run every command the README's tour and the examples' headers show, as a new user would.

Usage: python3 scripts/readme_tour.py --bin PATH/TO/polarimeter [--scratch DIR] [--limit-s S]
       [--list]

What a user is shown must work: each `polarimeter ...` line of README.md's indented code
blocks (before its "Lab hardware" section) and each command in the examples' header comments
(`#   polarimeter ...` lines and `polarimeter ...` in backticks that name a file of examples/)
runs with stdin closed, in a scratch directory holding a copy of examples/, under a time limit,
and must exit 0. Paths under /tmp/ are moved into the scratch directory, so nothing outside it
is touched. A line whose comment says `needs hardware` is listed as skipped; one whose comment
says `exits N` must exit N (an example of an error). A run that pauses (exit 3: a device fault
its retries did not clear, such as a trigger missed on a loaded host) is resumed with the
`acquire resume` command it prints, as the README tells a user to, and passes only if the resume
finishes it; the line says so. A command shown again (an example's header
repeating a README line, up to its `--out DIR`) runs once and is listed as the same.

`polarimeter simulate stage ... &` (or `station serve ... &`) starts the simulator (or the
station) in the background, and the
`/tmp/polarimeter-sim-PID/...` placeholders of the lines after it become the link it prints;
it is stopped (SIGTERM) at the end, and no `polarimeter-*` entry it or any other command made
may be left in the temporary directory.

Prints one line per command (status, seconds, command) and a JSON summary; exits 1 when any
command failed, hung or left files behind, 2 on a usage error.
"""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def readme_commands():
    """The README's tour commands, in order, with the line number."""
    out = []
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
        for number, line in enumerate(f, 1):
            if line.startswith("## Lab hardware"):
                break
            m = re.match(r"^    (.*\bpolarimeter\s.*)$", line.rstrip("\n"))
            if m and not m.group(1).lstrip().startswith("#"):
                out.append((f"README.md:{number}", m.group(1).strip()))
    return out


def example_commands():
    """Commands in the examples' header comments that name a file of examples/."""
    out = []
    for base, _dirs, files in sorted(os.walk(os.path.join(ROOT, "examples"))):
        for name in sorted(files):
            path = os.path.join(base, name)
            rel = os.path.relpath(path, ROOT)
            with open(path, encoding="utf-8", errors="replace") as f:
                for number, line in enumerate(f, 1):
                    if not line.startswith("#"):
                        break
                    found = re.findall(r"`(polarimeter [^`]+)`", line)
                    m = re.match(r"^#\s{2,}(polarimeter\s.*)$", line.rstrip("\n"))
                    if m:
                        found.append(m.group(1))
                    for c in found:
                        if "examples/" in c:
                            out.append((f"{rel}:{number}", c.strip()))
    return out


def needs_hardware(command):
    return "needs hardware" in command


def strip_comment(command):
    return re.sub(r"\s+#.*$", "", command)


def same_as(command):
    """The command without its comment and its `--out DIR`: an example's header that shows a
    command the README already ran (into another folder) runs once."""
    return re.sub(r"\s+--out\s+\S+", "", strip_comment(command)).strip()


PAUSED = 3


def resume_paused(stdout, scratch, env, limit_s):
    """Runs the `resume` command a paused run printed (its JSON's `resume`); returns its exit
    status, or None when the output names none."""
    m = re.search(r'"resume":\s*"(polarimeter acquire resume [^"]+)"', stdout)
    if not m:
        return None
    try:
        r = subprocess.run(["bash", "-c", m.group(1)], cwd=scratch, env=env,
                           stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL, timeout=limit_s)
    except subprocess.TimeoutExpired:
        return "hung"
    return r.returncode


def temp_entries():
    tmp = tempfile.gettempdir()
    return {e for e in os.listdir(tmp) if e.startswith("polarimeter-")}


def main(argv):
    args = {"--bin": None, "--scratch": None, "--limit-s": "900"}
    listing = "--list" in argv
    it = iter(a for a in argv[1:] if a != "--list")
    for a in it:
        if a not in args:
            print(__doc__, file=sys.stderr)
            return 2
        args[a] = next(it, None)
    commands = readme_commands() + example_commands()
    if listing:
        for where, c in commands:
            print(f"{where}: {c}")
        return 0
    if not args["--bin"]:
        print(__doc__, file=sys.stderr)
        return 2
    binary = os.path.abspath(args["--bin"])
    limit_s = float(args["--limit-s"])
    scratch = os.path.abspath(args["--scratch"] or os.path.join(ROOT, "target", "readme-tour"))
    shutil.rmtree(scratch, ignore_errors=True)
    os.makedirs(os.path.join(scratch, "tmp"))
    shutil.copytree(os.path.join(ROOT, "examples"), os.path.join(scratch, "examples"))
    os.makedirs(os.path.join(scratch, "docs"))
    if os.path.isdir(os.path.join(ROOT, "target", "py-venv")):
        os.makedirs(os.path.join(scratch, "target"))
        os.symlink(os.path.join(ROOT, "target", "py-venv"),
                   os.path.join(scratch, "target", "py-venv"))
    bindir = os.path.join(scratch, "bin")
    os.makedirs(bindir)
    os.symlink(binary, os.path.join(bindir, "polarimeter"))
    env = dict(os.environ, PATH=bindir + os.pathsep + os.environ.get("PATH", ""))
    before = temp_entries()

    results = []
    background = []
    sim_port = None
    failed = 0
    seen = {}
    for where, command in commands:
        if needs_hardware(command):
            results.append({"where": where, "command": command, "status": "skipped",
                            "reason": "needs hardware"})
            print(f"skip  {'':>7}  {command}  ({where}: needs hardware)", flush=True)
            continue
        same = same_as(command)
        if same in seen:
            results.append({"where": where, "command": command, "status": "same",
                            "as": seen[same]})
            print(f"same  {'':>7}  {command}  ({where}: ran as {seen[same]})", flush=True)
            continue
        seen[same] = where
        run = strip_comment(command).replace("/tmp/", scratch + "/tmp/")
        if sim_port:
            run = re.sub(r"\S*/polarimeter-sim-PID/\S+", sim_port, run)
        if run.endswith("&"):
            p = subprocess.Popen(["bash", "-c", "exec " + run[:-1]], cwd=scratch, env=env,
                                 stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
            line = p.stdout.readline()
            try:
                # A simulator prints its port; a station, the URL it listens on.
                printed = json.loads(line)
                if "listening" not in printed:
                    sim_port = printed["port"]
                status = 0
            except (ValueError, KeyError):
                status = "no port or address printed"
            background.append(p)
            results.append({"where": where, "command": command, "status": status,
                            "seconds": 0.0})
            print(f"{status!s:>4}  {0.0:7.1f}  {command}  (background)", flush=True)
            if status != 0:
                failed += 1
            continue
        expected = re.search(r"#.*\bexits (\d+)", command)
        expected = int(expected.group(1)) if expected else 0
        t0 = time.monotonic()
        try:
            r = subprocess.run(["bash", "-o", "pipefail", "-c", run], cwd=scratch, env=env,
                               stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, timeout=limit_s)
            status = (0 if r.returncode == expected
                      else r.returncode or f"exited 0, expected {expected}")
            tail = r.stderr.decode(errors="replace").strip().splitlines()[-3:]
            resumed = None
            if r.returncode == PAUSED and expected == 0:
                # A run that paused (exit 3: a device fault its retries did not clear, such as
                # a trigger the camera missed on a loaded host) is resumed, as the README tells
                # a user to; the resume must finish it.
                resumed = resume_paused(r.stdout.decode(errors="replace"), scratch, env,
                                        limit_s)
                if resumed is not None:
                    status = 0 if resumed == 0 else f"paused, resume exited {resumed}"
        except subprocess.TimeoutExpired:
            status = f"hung past {limit_s:.0f} s"
            tail = []
            resumed = None
        seconds = time.monotonic() - t0
        results.append({"where": where, "command": command, "status": status,
                        "seconds": round(seconds, 2),
                        **({"paused_then_resumed": True} if resumed == 0 else {})})
        note = "  (paused, then resumed: " + "; ".join(tail) + ")" if resumed == 0 else ""
        print(f"{status!s:>4}  {seconds:7.1f}  {command}{note}", flush=True)
        if status != 0:
            failed += 1
            for t in tail:
                print(f"        {t}", flush=True)
    for p in background:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            failed += 1
            results.append({"command": "background simulator", "status": "did not stop"})
    time.sleep(0.2)
    left = sorted(temp_entries() - before)
    if left:
        failed += 1
    summary = {
        "ok": failed == 0,
        "commands": len(results),
        "ran": sum(1 for r in results if r["status"] not in ("skipped", "same")),
        "same": sum(1 for r in results if r["status"] == "same"),
        "skipped": sum(1 for r in results if r["status"] == "skipped"),
        "failed": failed,
        "left_in_temp": left,
        "total_s": round(sum(r.get("seconds", 0.0) for r in results), 1),
    }
    with open(os.path.join(scratch, "tour.json"), "w", encoding="utf-8") as f:
        json.dump({"summary": summary, "results": results}, f, indent=1)
    print(json.dumps(summary))
    return 0 if failed == 0 else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
