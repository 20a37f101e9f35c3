#!/usr/bin/env python3
"""pylablib's Standa8SMC against the simulated Standa 8SMC5-USB with the 8MPR16-1, over a real
pseudo-terminal.

Usage: standa_clients.py PORT [--results FILE]. pylablib (`pylablib.devices.Standa.Standa8SMC`)
speaks the controller's binary protocol itself over pyserial: 115200 8N2, `gent` and `geng` at
connect, `gets` polled every 10 ms while a command runs, positions in microsteps.

Every operation it offers is run as its documentation runs it and checked through the same
client. A row is `passed` or `FAILED`. Output: a Markdown table on
stdout and, with --results FILE, one tab-separated row per cell (client, device, operation,
status, detail). Exit status 1 if any row FAILED. At the end the stage is parked at PARK_DEG for
the Rust test (tests/tests/hil/conformance_standa.rs) to check against the simulator's truth.
"""

import argparse
import sys
import time
import traceback

# The 8MPR16-1: 80 full steps per degree at 1/256 microsteps.
USTEPS_PER_DEG = 80 * 256
PARK_DEG = 123.0
# The slowest wait: a homing over a whole turn at the test speed, with margin.
WAIT_S = 30.0


def rows_for(port):
    from pylablib.devices import Standa

    rows = []
    device = "8SMC5-USB + 8MPR16-1"
    stage = Standa.Standa8SMC(port)

    def row(op, fn):
        try:
            detail = fn()
            rows.append(("pylablib Standa8SMC", device, op, "passed", detail))
        except Exception as e:  # noqa: BLE001 - every failure is a row
            rows.append(("pylablib Standa8SMC", device, op, "FAILED", f"{e!r}"))
            traceback.print_exc(file=sys.stderr)

    def calibration():
        steps, usteps = stage.get_stepper_motor_calibration()
        assert (steps, usteps) == (20, 256), (steps, usteps)
        return "20 steps per motor turn, 256 microsteps (geng)"

    def engine():
        kind = stage.get_engine_type()
        assert tuple(kind) == ("step", "integr"), kind
        return "stepper, integrated driver (gent)"

    def home():
        stage.home(sync=True, timeout=WAIT_S)
        st = stage.get_status()
        assert st.flags & 0x20, st
        assert st.scmd == ("home", "success"), st
        return "home, gets until done; STATE_IS_HOMED set"

    def zero():
        stage.set_position_reference(0)
        p = stage.get_position()
        assert p == 0, p
        return "spos 0; gpos reads 0"

    def move_to():
        target = int(45 * USTEPS_PER_DEG)
        stage.move_to(target)
        stage.wait_move(timeout=WAIT_S)
        p = stage.get_position()
        assert p == target, (p, target)
        return f"at {p} microsteps (45 deg)"

    def move_by():
        before = stage.get_position()
        stage.move_by(-512)
        stage.wait_move(timeout=WAIT_S)
        p = stage.get_position()
        assert p == before - 512, (p, before)
        return "-512 microsteps from the target"

    def status():
        st = stage.get_status()
        assert not stage.is_moving() and st.scmd == ("movr", "success"), st
        assert st.spwr == "norm" and st.senc == "absent", st
        return "movr done, power normal, no encoder"

    def jog_and_stop():
        before = stage.get_position()
        stage.jog("+")
        time.sleep(0.3)
        assert stage.is_moving()
        stage.stop()
        stage.wait_move(timeout=WAIT_S)
        p = stage.get_position()
        assert p > before, (p, before)
        return f"rigt, then sstp: {p - before} microsteps turned"

    def jog_left():
        before = stage.get_position()
        stage.jog("-")
        time.sleep(0.3)
        stage.stop()
        stage.wait_move(timeout=WAIT_S)
        p = stage.get_position()
        assert p < before, (p, before)
        return f"left, then sstp: {before - p} microsteps turned"

    def move_parameters():
        params = stage.get_move_parameters()
        stage.setup_move(speed=params.speed)
        again = stage.get_move_parameters()
        assert abs(again.speed - params.speed) < 1e-6, (again, params)
        return f"gmov/smov round trip ({params.speed:g} microsteps/s)"

    def park():
        target = int(PARK_DEG * USTEPS_PER_DEG)
        stage.move_to(target)
        stage.wait_move(timeout=WAIT_S)
        p = stage.get_position()
        assert p == target, (p, target)
        return f"at {p} microsteps ({PARK_DEG} deg)"

    row("engine type (gent)", engine)
    row("calibration (geng)", calibration)
    row("home", home)
    row("position reference (spos)", zero)
    row("move absolute (move)", move_to)
    row("move relative (movr)", move_by)
    row("status (gets)", status)
    row("jog and soft stop (rigt, sstp)", jog_and_stop)
    row("move parameters (gmov, smov)", move_parameters)
    row("jog left (left)", jog_left)
    row("park at 123 deg", park)
    stage.close()
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("port")
    ap.add_argument("--results")
    args = ap.parse_args()
    rows = rows_for(args.port)
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
