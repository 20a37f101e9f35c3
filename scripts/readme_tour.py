#!/usr/bin/env python3
"""Run every command the README's tour and the examples' headers show, as a new user would.

Usage: python3 scripts/readme_tour.py --bin PATH/TO/polarimeter [--scratch DIR] [--limit-s S]
       [--jobs N] [--list]

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

Up to N commands (`--jobs`, default 3) run at once: a command waits for every earlier one that
shares a `/tmp/` folder or a file of the scratch directory with it, and every command that
starts, probes or talks to serial devices or the station runs in the README's order with the
others of its kind, so what a line depends on has run before it, as for a user typing them.

Prints one line per command (status, seconds, command) in the README's order and a JSON
summary (with the sum of the commands' seconds and the wall time); exits 1 when any
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
import threading
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


SHARED_DEVICES = "serial ports, simulators and the station"


def resources(command):
    """What a command reads or writes that a later command may use: its `/tmp/NAME` folders,
    the files it names outside examples/ and target/, and (for anything that starts,
    probes or talks to simulated serial devices or the station) one shared token. Commands
    that share nothing run side by side; the rest keep the README's order."""
    text = strip_comment(command)
    tokens = set()
    for word in re.split(r"[\s=>]+", text):
        if word.startswith("/tmp/"):
            tokens.add("/tmp/" + word[len("/tmp/"):].split("/")[0])
        elif (not word.startswith("-") and not word.startswith(("examples/", "target/"))
              and re.match(r"^[\w./-]+$", word) and re.search(r"[A-Za-z]", word)
              and re.search(r"/|\.[A-Za-z]+$", word)):
            tokens.add(word.rstrip("/"))
    if re.search(r"\b(acquire )?run\b", text) and "--out" not in text \
            and re.search(r"\.toml\b", text):
        # A run without --out goes to the default folder, named after the plan and the time.
        tokens.add("the default run folder")
    if re.search(r"\b(devices (list|stage)|simulate stage|station|bench serial)\b", text) \
            or "polarimeter-sim-PID" in text:
        tokens.add(SHARED_DEVICES)
    return tokens


def run_one(run, expected, scratch, env, limit_s):
    """Runs one command; returns (status, seconds, stderr tail, resumed)."""
    t0 = time.monotonic()
    resumed = None
    try:
        r = subprocess.run(["bash", "-o", "pipefail", "-c", run], cwd=scratch, env=env,
                           stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, timeout=limit_s)
        status = (0 if r.returncode == expected
                  else r.returncode or f"exited 0, expected {expected}")
        tail = r.stderr.decode(errors="replace").strip().splitlines()[-3:]
        if r.returncode == PAUSED and expected == 0:
            # A run that paused (exit 3: a device fault its retries did not clear, such as
            # a trigger the camera missed on a loaded host) is resumed, as the README tells
            # a user to; the resume must finish it.
            resumed = resume_paused(r.stdout.decode(errors="replace"), scratch, env, limit_s)
            if resumed is not None:
                status = 0 if resumed == 0 else f"paused, resume exited {resumed}"
    except subprocess.TimeoutExpired:
        status = f"hung past {limit_s:.0f} s"
        tail = []
    return status, time.monotonic() - t0, tail, resumed


def start_background(run, scratch, env):
    """Starts `COMMAND &`; returns (process, status, the simulator's port or None)."""
    p = subprocess.Popen(["bash", "-c", "exec " + run[:-1]], cwd=scratch, env=env,
                         stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    line = p.stdout.readline()
    try:
        # A simulator prints its port; a station, the URL it listens on.
        printed = json.loads(line)
        return p, 0, (None if "listening" in printed else printed["port"])
    except (ValueError, KeyError):
        return p, "no port or address printed", None


def plan_jobs(commands):
    """Each command as a job: skipped (needs hardware), the same as an earlier one, run in the
    background (`... &`), or run; with the earlier jobs it must wait for."""
    jobs, seen, last_user = [], {}, {}
    for where, command in commands:
        job = {"where": where, "command": command, "after": set()}
        jobs.append(job)
        if needs_hardware(command):
            job["kind"] = "skip"
            continue
        same = same_as(command)
        if same in seen:
            job["kind"], job["as"] = "same", seen[same]
            continue
        seen[same] = where
        job["kind"] = "background" if strip_comment(command).endswith("&") else "run"
        for token in resources(command):
            if token in last_user:
                job["after"].add(last_user[token])
            last_user[token] = len(jobs) - 1
    return jobs


def result_line(job):
    """The job's line as the tour prints it, and the lines of its stderr tail on a failure."""
    kind, command, where = job["kind"], job["command"], job["where"]
    if kind == "skip":
        return [f"skip  {'':>7}  {command}  ({where}: needs hardware)"]
    if kind == "same":
        return [f"same  {'':>7}  {command}  ({where}: ran as {job['as']})"]
    status, seconds = job["status"], job["seconds"]
    if kind == "background":
        return [f"{status!s:>4}  {0.0:7.1f}  {command}  (background)"]
    note = ("  (paused, then resumed: " + "; ".join(job["tail"]) + ")"
            if job["resumed"] == 0 else "")
    lines = [f"{status!s:>4}  {seconds:7.1f}  {command}{note}"]
    if status != 0:
        lines += [f"        {t}" for t in job["tail"]]
    return lines


def run_jobs(jobs, scratch, env, limit_s, workers):
    """Runs the jobs, up to `workers` at once, each after the jobs it waits for; prints each
    job's line in the README's order as soon as it and the jobs before it are done. Returns
    the background processes."""
    lock = threading.Condition()
    done = [j["kind"] in ("skip", "same") for j in jobs]
    started = list(done)
    background, sim = [], {"port": None}
    printed = 0

    def work(i):
        job = jobs[i]
        run = strip_comment(job["command"]).replace("/tmp/", scratch + "/tmp/")
        if sim["port"]:
            run = re.sub(r"\S*/polarimeter-sim-PID/\S+", sim["port"], run)
        if job["kind"] == "background":
            p, job["status"], port = start_background(run, scratch, env)
            job["seconds"], job["resumed"], job["tail"] = 0.0, None, []
            background.append(p)
            if port:
                sim["port"] = port
        else:
            expected = re.search(r"#.*\bexits (\d+)", job["command"])
            expected = int(expected.group(1)) if expected else 0
            job["status"], job["seconds"], job["tail"], job["resumed"] = run_one(
                run, expected, scratch, env, limit_s)
        with lock:
            done[i] = True
            lock.notify_all()

    with lock:
        while printed < len(jobs):
            running = sum(1 for i in range(len(jobs)) if started[i] and not done[i])
            for i, job in enumerate(jobs):
                if running >= workers:
                    break
                if not started[i] and all(done[a] for a in job["after"]):
                    started[i] = True
                    running += 1
                    threading.Thread(target=work, args=(i,), daemon=True).start()
            while printed < len(jobs) and done[printed]:
                for line in result_line(jobs[printed]):
                    print(line, flush=True)
                printed += 1
            if printed < len(jobs):
                lock.wait(timeout=1.0)
    return background


def main(argv):
    args = {"--bin": None, "--scratch": None, "--limit-s": "900", "--jobs": "3"}
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
    if not args["--bin"] or not (args["--jobs"] or "").isdigit() or int(args["--jobs"]) < 1:
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

    t0 = time.monotonic()
    jobs = plan_jobs(commands)
    background = run_jobs(jobs, scratch, env, limit_s, int(args["--jobs"]))
    failed = sum(1 for j in jobs if j["kind"] in ("run", "background") and j["status"] != 0)
    results = []
    for j in jobs:
        r = {"where": j["where"], "command": j["command"]}
        if j["kind"] == "skip":
            r.update(status="skipped", reason="needs hardware")
        elif j["kind"] == "same":
            r.update(status="same", **{"as": j["as"]})
        else:
            r.update(status=j["status"], seconds=round(j["seconds"], 2),
                     **({"paused_then_resumed": True} if j["resumed"] == 0 else {}))
        results.append(r)
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
        "wall_s": round(time.monotonic() - t0, 1),
        "jobs": int(args["--jobs"]),
    }
    with open(os.path.join(scratch, "tour.json"), "w", encoding="utf-8") as f:
        json.dump({"summary": summary, "results": results}, f, indent=1)
    print(json.dumps(summary))
    return 0 if failed == 0 else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
