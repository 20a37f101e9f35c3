#!/usr/bin/env python3
"""Public SMC100 and CONEX-AGP clients against the simulated Newport controllers, over real
pseudo-terminals.

Devices, each given as NAME=PORT:
* `bus`: two SMC100CC controllers with PR50CC stages at addresses 1 and 2 on one port;
* `smc100`: one SMC100CC with a PR50CC at address 1;
* `agp`: one CONEX-AGP with an AG-PR100P at address 1 (921600 baud).

Clients, independent of each other and of us:
* pystages (Ledger-Donjon), its `SMC100` class over pyserial, on the bus (both addresses);
* yaq's daemons `yaqd-newport-smc100` and `yaqd-newport-conex-agp` (yaqd-newport), driven
  through their TCP client `yaqc`, on `smc100` and `agp`.

Every operation a client offers is run as its documentation runs it and checked through the same
client. A row is `passed`, or a `client difference` whose reason is stated here and whose
symptom is checked, or `not offered`; anything else is `FAILED`. Output: a Markdown table on
stdout and, with --results FILE, one tab-separated row per cell (client, device, operation,
status, detail). Exit status 1 if any row FAILED. At the end, address 1 of every device is parked
at PARK_DEG for the Rust test (tests/tests/hil/conformance_smc100.rs) to check against the
simulator's ground truth.
"""

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time
import traceback

# Where each device's address 1 is left.
PARK_DEG = 123.0
# A position read back is within 0.002 deg of its target: the simulated encoder's 0.0005 deg
# step plus 3 sigma of its 0.0002 deg noise, with margin (the AG-PR100P's step is 0.001 deg).
TOL_DEG = 0.003
# The slowest wait: yaq's homing (RS, its own 5 s pause, a turn at the test speed) with margin.
WAIT_S = 40.0


class Difference(Exception):
    """A client difference: the client cannot do this as the device allows, for a stated reason."""


def near(a, b, tol=TOL_DEG):
    return abs(a - b) <= tol


def pystages_rows(port):
    from pystages import SMC100, Vector
    from pystages.smc100 import State

    rows = []
    stage = SMC100(port, [1, 2])

    def row(op, fn):
        try:
            detail = fn()
            rows.append(("pystages", "bus (addresses 1, 2)", op, "passed", detail))
        except Difference as e:
            rows.append(("pystages", "bus (addresses 1, 2)", op, "client difference", str(e)))
        except Exception as e:  # noqa: BLE001 - every failure is a row
            rows.append(("pystages", "bus (addresses 1, 2)", op, "FAILED", f"{e!r}"))
            traceback.print_exc(file=sys.stderr)

    def state_at_power_on():
        states = [stage.get_error_and_state(a).state for a in (1, 2)]
        assert all(s == State.NOT_REFERENCED_FROM_RESET for s in states), states
        return "both NOT REFERENCED from reset (0A)"

    def home():
        stage.home(wait=True)
        states = [stage.get_error_and_state(a).state for a in (1, 2)]
        assert all(s == State.READY_FROM_HOMING for s in states), states
        p = stage.position
        assert near(p[0], 0.0) and near(p[1], 0.0), p
        return "both READY from HOMING (32) at 0"

    def move_absolute():
        stage.move_to(Vector(45.0, -10.0), wait=True)
        p = stage.position
        assert near(p[0], 45.0) and near(p[1], -10.0), p
        return f"1 at {p[0]:.4f}, 2 at {p[1]:.4f} deg (sent in one write)"

    def error_and_state():
        es = [stage.get_error_and_state(a) for a in (1, 2)]
        assert all(e.is_ready and e.state == State.READY_FROM_MOVING for e in es), es
        assert all(int(e.error) == 0 for e in es), es
        return "READY from MOVING (33), no positioner error"

    def park():
        stage.move_to(Vector(PARK_DEG, 0.0), wait=True)
        p = stage.position
        assert near(p[0], PARK_DEG), p
        return f"1 at {p[0]:.4f} deg"

    row("state at power-on (TS?)", state_at_power_on)
    row("home (OR, TS? polling)", home)
    row("move absolute, two addresses (MM1, PA)", move_absolute)
    row("error and state (TS?)", error_and_state)
    row("park at 123 deg", park)
    stage.link.serial.close()
    return rows


def free_tcp_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def yaq_rows(kind, device, port, baud, scratch):
    import yaqc

    who = f"yaqd-newport-{kind}"
    rows = []
    tcp = free_tcp_port()
    config = os.path.join(scratch, f"{kind}.toml")
    with open(config, "w") as f:
        f.write(
            f'[stage]\nhost = "127.0.0.1"\nport = {tcp}\nserial_port = "{port}"\n'
            f"baud_rate = {baud}\naxis = 1\n"
        )
    env = dict(os.environ, XDG_DATA_HOME=os.path.join(scratch, f"{kind}-state"))
    exe = os.path.join(os.path.dirname(sys.executable), who)
    log = open(os.path.join(scratch, f"{kind}.log"), "w")
    daemon = subprocess.Popen([exe, "--config", config], env=env, stdout=log, stderr=log)
    client = None

    def row(op, fn):
        try:
            detail = fn()
            rows.append((who, device, op, "passed", detail))
        except Difference as e:
            rows.append((who, device, op, "client difference", str(e)))
        except Exception as e:  # noqa: BLE001
            rows.append((who, device, op, "FAILED", f"{e!r}"))
            traceback.print_exc(file=sys.stderr)

    def wait_idle():
        t = time.time()
        time.sleep(0.3)
        while client.busy():
            assert time.time() - t < WAIT_S, f"still busy after {WAIT_S} s"
            time.sleep(0.1)

    def connect():
        nonlocal client
        t = time.time()
        while True:
            try:
                client = yaqc.Client(tcp, host="127.0.0.1")
                break
            except ConnectionError:
                assert time.time() - t < 20, "the daemon did not listen within 20 s"
                time.sleep(0.2)
        limits = client.get_limits()
        assert limits[0] < -1e5 and limits[1] > 1e5, limits
        return f"limits from SL?/SR?: {limits[0]:g} .. {limits[1]:g} deg"

    def home_at_start():
        wait_idle()
        state = client.get_state()
        assert "READY" in str(state), state
        # On a first start the daemon moves to its remembered destination, which is NaN: it
        # sends `1PAnan`, which the controller refuses (error C) and the daemon only logs.
        return "RS, OR, READY; its `1PAnan` refused with error C as by the device"

    def move_absolute():
        client.set_position(45.0)
        wait_idle()
        p = client.get_position()
        assert near(p, 45.0), p
        return f"at {p:.4f} deg"

    def state():
        s = str(client.get_state())
        assert "READY from MOVING" in s and "0000" in s, s
        return "READY from MOVING, error code 0000"

    def home_again():
        client.home()
        wait_idle()
        p = client.get_position()
        # After homing the daemon returns to its destination (45 deg).
        assert near(p, 45.0), p
        return "RS, OR, back to 45 deg"

    def park():
        client.set_position(PARK_DEG)
        wait_idle()
        p = client.get_position()
        assert near(p, PARK_DEG), p
        return f"at {p:.4f} deg"

    try:
        row("start (SL?, SR?)", connect)
        if client is not None:
            row("home at start (RS, OR)", home_at_start)
            row("move absolute (PA)", move_absolute)
            row("state (TS, TE)", state)
            row("home (RS, OR, PA)", home_again)
            row("park at 123 deg", park)
    finally:
        if client is not None:
            try:
                client.shutdown()
            except Exception:  # noqa: BLE001 - the daemon may already be gone
                pass
        try:
            daemon.wait(10)
        except subprocess.TimeoutExpired:
            daemon.kill()
        log.close()
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("devices", nargs="+", help="NAME=PORT with NAME bus, smc100 or agp")
    ap.add_argument("--results", help="tab-separated rows to this file")
    args = ap.parse_args()
    ports = dict(d.split("=", 1) for d in args.devices)
    rows = []
    with tempfile.TemporaryDirectory(prefix="polar-smc100-clients-") as scratch:
        if "bus" in ports:
            rows += pystages_rows(ports["bus"])
        if "smc100" in ports:
            rows += yaq_rows("smc100", "SMC100CC + PR50CC", ports["smc100"], 57600, scratch)
        if "agp" in ports:
            rows += yaq_rows("conex-agp", "CONEX-AGP + AG-PR100P", ports["agp"], 921600, scratch)
    print("| client | device | operation | result | detail |")
    print("|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")
    if args.results:
        with open(args.results, "w") as f:
            for r in rows:
                f.write("\t".join(r) + "\n")
    return 1 if any(r[3] == "FAILED" for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
