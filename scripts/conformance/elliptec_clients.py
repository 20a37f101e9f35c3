#!/usr/bin/env python3
"""Public client libraries against the simulated devices, over real pseudo-terminals.

Each simulated device is given as MODEL=PORT (models: ell14, ell18, ell6, ell9, fw102c,
fw212c). Every operation a client library offers is run the way the library's own examples run
it (moves back to back, no pauses of our own) and checked by reading back through the same
client. An operation is either `passed`, or a `client difference` whose reason is stated here
and whose symptom is checked too (so a client that changes makes the row fail), or `not
offered` by that client. Anything else is `FAILED`.

Clients: pylablib (`pylablib.devices.Thorlabs.ElliptecMotor`, `pylablib.devices.Thorlabs.FW`),
thorlabs_elliptec (`thorlabs_elliptec.ELLx`) and roesel's elliptec (`elliptec.Rotator`,
`elliptec.Slider`). Output: a Markdown table on stdout and, with
--results FILE, one tab-separated row per cell (client, model, operation, status, detail).
Exit status 1 if any row FAILED. CONFORMANCE_DEBUG=1 logs every exchange of the clients that log
(thorlabs_elliptec) to stderr.

Run by tests/tests/hil/conformance_elliptec.rs, which serves the devices.
"""

import argparse
import concurrent.futures
import logging
import os
import sys
import time
import traceback

# The simulated devices' facts the checks rely on (hil-mocks/src/elliptec.rs, fw102c.rs).
ROTATORS = {"ell14": (0x0E, 143360), "ell18": (0x12, 262144)}
SLIDERS = {"ell6": (0x06, [0, 31]), "ell9": (0x09, [0, 32, 64, 96])}
WHEELS = {"fw102c": 6, "fw212c": 12}
# Motor 1's forward/backward periods at power-on: frequency = 14.74 MHz / period.
MOTOR1_PERIODS = (0x0091, 0x0088)
# A rotator reading is within 3 counts of its target: 6 sigma of the simulator's 0.5-count
# encoder noise, plus the clients' own rounding (pylablib truncates to a count; thorlabs_elliptec
# rounds degrees to 1e-3).
ROTATOR_TOL_COUNTS = 3
# Where each device is left, for the Rust test to check the simulator's ground truth.
PARK_DEG = 123.0
PARK_SLOT = 1
PARK_WHEEL = 3

OPERATIONS = [
    "identify",
    "home",
    "absolute moves back to back",
    "relative moves",
    "raw-count moves",
    "velocity",
    "status",
    "jog",
    "stop",
    "home offset",
    "motor info",
    "motor frequencies",
    "frequency search",
    "address change",
    "save settings",
    "slots",
    "position count",
    "speed mode",
    "trigger mode",
    "sensor mode",
    "bad command",
]


class Difference(Exception):
    """The client behaves differently from what the device supports; the reason says how."""


class NotOffered(Exception):
    """The client has no such operation."""


def check(cond, what):
    if not cond:
        raise AssertionError(what)


def near_deg(got, want, pulses):
    """Whether two angles agree within ROTATOR_TOL_COUNTS counts, modulo a turn."""
    d = (got - want + 180.0) % 360.0 - 180.0
    return abs(d) <= ROTATOR_TOL_COUNTS * 360.0 / pulses + 1e-3


class Recorder:
    def __init__(self, client, model):
        self.client, self.model, self.rows = client, model, []

    def run(self, op, fn):
        t0 = time.monotonic()
        try:
            detail = fn() or ""
            status = "passed"
        except NotOffered as e:
            status, detail = "not offered", str(e)
        except Difference as e:
            status, detail = "client difference", str(e)
        except Exception as e:  # noqa: BLE001 - any other outcome is a failure to report
            status = "FAILED"
            detail = f"{type(e).__name__}: {e}"
            traceback.print_exc(file=sys.stderr)
        dt = time.monotonic() - t0
        self.rows.append((self.client, self.model, op, status, detail, dt))


def not_offered(what):
    def f():
        raise NotOffered(what)

    return f


# ---------------------------------------------------------------------------------------------
# pylablib: ElliptecMotor


def pylablib_elliptec(model, port):
    from pylablib.devices import Thorlabs

    rec = Recorder("pylablib", model)
    rotator = model in ROTATORS
    code, pulses = ROTATORS[model] if rotator else (SLIDERS[model][0], 0)
    slots = None if rotator else SLIDERS[model][1]
    dev = Thorlabs.ElliptecMotor(port, addrs=[0])
    try:

        def identify():
            info = dev.get_device_info()
            check(info.model_no == code, f"model {info.model_no}")
            check(info.pulse == pulses, f"PULSES {info.pulse}, want {pulses}")
            travel = 360 if rotator else slots[-1]
            check(info.travel == travel, f"travel {info.travel}")
            return f"ELL{info.model_no} serial {info.serial_no}, PULSES {info.pulse}"

        def home():
            check(dev.home() is True, "no PO")
            p = dev.get_position()
            check(near_deg(p, 0.0, pulses) if rotator else p == 0, f"at {p}")

        def absolute():
            targets = [45.0, 90.0, 270.5] if rotator else list(reversed(slots)) + slots
            for t in targets:
                check(dev.move_to(t) is True, f"move to {t}: no PO")
                p = dev.get_position()
                check(near_deg(p, t, pulses) if rotator else p == t, f"{t}: read {p}")
            return f"{len(targets)} moves"

        def relative():
            if rotator:
                dev.move_to(90.0)
                for step, want in [(-30.0, 60.0), (15.0, 75.0)]:
                    check(dev.move_by(step) is True, "no PO")
                    p = dev.get_position()
                    check(near_deg(p, want, pulses), f"by {step}: read {p}, want {want}")
            else:
                dev.move_to(slots[0])
                pitch = slots[1] - slots[0]
                check(dev.move_by(pitch) is True, "no PO")
                p = dev.get_position()
                check(p == slots[1], f"read {p}")

        def raw():
            scale = dev.get_scale()
            dev.set_scale("step")
            try:
                t = pulses // 3 if rotator else slots[-1]
                dev.move_to(t)
                p = dev.get_position()
                ok = abs(p - t) <= ROTATOR_TOL_COUNTS if rotator else p == t
                check(ok, f"read {p}, want {t}")
            finally:
                dev.set_scale(scale)

        def velocity():
            check(dev.set_velocity(50) == 50, "set 50")
            check(dev.get_velocity() == 50, "get 50")
            check(dev.set_velocity(100) == 100, "set 100")

        def status():
            s = dev.get_status()
            check(s == "ok", f"status {s}")

        def home_offset():
            check(dev.get_home_offset() == 0, "offset at power-on")
            if not rotator:
                return "read 0 (sliders have no settable offset)"
            got = dev.set_home_offset(10.0)
            check(near_deg(got, 10.0, pulses), f"set 10 deg: read {got}")
            check(dev.set_home_offset(0) == 0, "back to 0")

        def motor_info():
            for m in (1, 2):
                i = dev.get_motor_info(motor=m)
                check(i.motor and 0.0 < i.current < 2.0, f"motor {m}: {i}")
            i = dev.get_motor_info(motor=1)
            want = tuple(14740000 / p for p in MOTOR1_PERIODS)
            check(abs(i.fw_freq - want[0]) < 1 and abs(i.bk_freq - want[1]) < 1, f"{i}")
            return f"motor 1 {i.fw_freq / 1e3:.1f}/{i.bk_freq / 1e3:.1f} kHz"

        def frequencies():
            # The period is an integer: 14.74 MHz / 100 kHz = 147.4 -> 147, 0.3 % off.
            fw, bk = dev.set_frequency(fw_freq=100e3, bk_freq=110e3, motor=1)
            check(abs(fw / 100e3 - 1) < 0.01 and abs(bk / 110e3 - 1) < 0.01, f"{fw} {bk}")

        def search():
            fw, bk = dev.search_frequency(motor=1)
            want = tuple(14740000 / p for p in MOTOR1_PERIODS)
            check(abs(fw - want[0]) < 1 and abs(bk - want[1]) < 1, f"{fw} {bk}")

        def address():
            check(dev.change_addr(5) == "ok", "ca5")
            check(dev.get_connected_addrs() == [5], f"{dev.get_connected_addrs()}")
            check(dev.get_device_info().model_no == code, "in at 5")
            check(dev.change_addr(0, addr=5) == "ok", "back to 0")
            check(dev.get_device_info(addr=0).model_no == code, "in at 0")

        def save():
            check(dev.store_parameters() == "ok", "us")

        rec.run("identify", identify)
        rec.run("home", home)
        rec.run("absolute moves back to back", absolute)
        rec.run("relative moves", relative)
        rec.run("raw-count moves", raw)
        rec.run("velocity", velocity)
        rec.run("status", status)
        rec.run("jog", not_offered("no fw/bw method"))
        rec.run("stop", not_offered("no st method"))
        rec.run("home offset", home_offset)
        rec.run("motor info", motor_info)
        rec.run("motor frequencies", frequencies)
        rec.run("frequency search", search)
        rec.run("address change", address)
        rec.run("save settings", save)
        def slots_op():
            for k, t in enumerate(slots):
                check(dev.move_to(t) is True, f"slot {k}: no PO")
                check(dev.get_position() == t, f"slot {k}")
            return f"by position in counts, {slots}"

        if not rotator:
            rec.run("slots", slots_op)
    finally:
        dev.close()
    return rec.rows


# ---------------------------------------------------------------------------------------------
# thorlabs_elliptec: ELLx


def thorlabs_elliptec_client(model, port, park):
    from thorlabs_elliptec import ELLStatus, ELLx

    def settled(read):
        # ELLx._move clears its moving flag before it stores the position of the `PO` reply, so
        # a read right after a blocking move can return the previous position when the machine
        # is loaded (a race in the client, seen here). The background poll (`gp` every 0.1 s)
        # refreshes the position: read after two poll intervals.
        time.sleep(2 * dev.status_poll_interval + 0.05)
        return read()

    rec = Recorder("thorlabs_elliptec", model)
    rotator = model in ROTATORS
    code, pulses = ROTATORS[model] if rotator else (SLIDERS[model][0], 0)
    slots = None if rotator else SLIDERS[model][1]
    dev = ELLx(serial_port=port, x=code)
    try:

        def identify():
            check(dev.model_number == f"ELL{code}/M", dev.model_number)
            check(dev._pp == pulses, f"pulses {dev._pp}")
            return f"{dev.model_number} serial {dev.serial_number}"

        def home():
            dev.home(blocking=True)
            if rotator:
                check(near_deg(settled(dev.get_position), 0.0, pulses), "home")
            else:
                p = settled(dev.get_position_raw)
                check(p == 0, f"read {p}")

        def absolute():
            if not rotator:
                # Units are PULSES-scaled: a slider reports PULSES 0, so get_position divides
                # by 0 and move_absolute always sends `ma00000000`.
                try:
                    dev.get_position()
                except ZeroDivisionError:
                    raise Difference(
                        "scales by PULSES, which an indexed slider reports as 0: "
                        "get_position divides by zero (use the raw-count moves)"
                    ) from None
                raise AssertionError("get_position did not divide by PULSES = 0")
            # The library's own examples: moves one after another, no pause.
            for t in [45.0, 90.0, 270.5, 10.0]:
                dev.move_absolute(t, blocking=True)
                p = settled(dev.get_position)
                check(near_deg(p, t, pulses), f"{t}: read {p}")
            return "4 moves"

        def relative():
            if not rotator:
                dev.move_absolute_raw(slots[0], blocking=True)
                dev.move_relative(1.0, blocking=True)
                p = settled(dev.get_position_raw)
                check(p == slots[0], f"move_relative(1) on PULSES 0 moved to {p}")
                raise Difference(
                    "PULSES-scaled: on an indexed slider (PULSES 0) move_relative sends "
                    "`mr00000000` (use the raw-count moves)"
                )
            dev.move_absolute(90.0, blocking=True)
            for step, want in [(-30.0, 60.0), (15.0, 75.0)]:
                dev.move_relative(step, blocking=True)
                p = settled(dev.get_position)
                check(near_deg(p, want, pulses), f"by {step}: read {p}, want {want}")

        def raw():
            targets = [pulses // 3, pulses // 2] if rotator else list(reversed(slots)) + slots
            for t in targets:
                dev.move_absolute_raw(t, blocking=True)
                p = settled(dev.get_position_raw)
                ok = abs(p - t) <= ROTATOR_TOL_COUNTS if rotator else p == t
                check(ok, f"{t}: read {p}")
            step = pulses // 8 if rotator else slots[1] - slots[0]
            if not rotator:
                dev.move_absolute_raw(slots[0], blocking=True)
            start = settled(dev.get_position_raw)
            dev.move_relative_raw(step, blocking=True)
            p = settled(dev.get_position_raw)
            ok = abs(p - start - step) <= 2 * ROTATOR_TOL_COUNTS if rotator else p == start + step
            check(ok, f"relative {step} from {start}: read {p}")
            return f"{len(targets) + 1} moves"

        def status():
            # Status is polled in the background every 0.1 s.
            time.sleep(0.3)
            check(dev.status == ELLStatus.OK, f"{dev.status}")
            check(not dev.is_moving(raise_errors=True), "moving")

        rec.run("identify", identify)
        rec.run("home", home)
        rec.run("absolute moves back to back", absolute)
        rec.run("relative moves", relative)
        rec.run("raw-count moves", raw)
        rec.run("velocity", not_offered("no sv/gv method"))
        rec.run("status", status)
        rec.run("jog", not_offered("no fw/bw method"))
        rec.run("stop", not_offered("no st method"))
        rec.run("home offset", not_offered("no so/go method"))
        rec.run("motor info", not_offered("no i1/i2 method"))
        rec.run("motor frequencies", not_offered("no f1/b1 method"))
        rec.run("frequency search", not_offered("no s1 method"))
        rec.run("address change", not_offered("documented as unsupported (use a terminal)"))
        rec.run("save settings", not_offered("no us method"))

        def slots_op():
            for k, t in enumerate(slots):
                dev.move_absolute_raw(t, blocking=True)
                check(settled(dev.get_position_raw) == t, f"slot {k}")
            return f"by raw counts, {slots}"

        if not rotator:
            rec.run("slots", slots_op)
        if park:
            if rotator:
                dev.move_absolute(PARK_DEG, blocking=True)
            else:
                dev.move_absolute_raw(slots[PARK_SLOT], blocking=True)
    finally:
        dev.close()
        # close() stops the polling thread, which closes the port: wait for it, so that the
        # next client has the pseudo-terminal to itself.
        dev._thread.join(timeout=5)
    return rec.rows


# ---------------------------------------------------------------------------------------------
# elliptec (roesel): Rotator, Slider


def roesel_elliptec(model, port):
    import elliptec

    rec = Recorder("elliptec", model)
    rotator = model in ROTATORS
    code, pulses = ROTATORS[model] if rotator else (SLIDERS[model][0], 0)
    slots = None if rotator else SLIDERS[model][1]
    ctrl = elliptec.Controller(port, debug=False)
    dev = elliptec.Rotator(ctrl, debug=False) if rotator else elliptec.Slider(ctrl, debug=False)
    try:

        def identify():
            check(dev.motor_type == code, f"type {dev.motor_type}")
            check(dev.pulse_per_rev == pulses, f"pulses {dev.pulse_per_rev}")
            return f"ELL{dev.motor_type} serial {dev.serial_no}"

        def home():
            st = dev.home()
            check(st is not None and st[1] == "PO" and st[2] == 0, f"{st}")

        def absolute():
            if not rotator:
                for k in [len(slots), 1, 2]:
                    check(dev.set_slot(k) == k, f"slot {k}")
                    check(dev.get_slot() == k, f"slot {k} read back")
                return "slots, 1-based"
            for t in [45.0, 90.0, 270.5]:
                got = dev.set_angle(t)
                check(got is not None and near_deg(got, t, pulses), f"{t}: {got}")
                p = dev.get_angle()
                check(near_deg(p, t, pulses), f"{t}: read {p}")
            return "3 moves"

        def relative():
            if not rotator:
                raise NotOffered("no relative move on a slider")
            dev.set_angle(90.0)
            for step, want in [(-30.0, 60.0), (15.0, 75.0)]:
                got = dev.shift_angle(step)
                check(got is not None and near_deg(got, want, pulses), f"by {step}: {got}")

        def jog():
            if rotator:
                dev.set_jog_step(10.0)
                check(near_deg(dev.get_jog_step(), 10.0, pulses), "jog step")
                dev.set_angle(30.0)
                got = dev.jog("forward")
                check(got is not None and near_deg(got, 40.0, pulses), f"forward: {got}")
                got = dev.jog("backward")
                check(got is not None and near_deg(got, 30.0, pulses), f"backward: {got}")
                return "10 deg step"
            dev.set_slot(1)
            for k in range(2, len(slots) + 1):
                check(dev.jog("forward") == k, f"forward to {k}")
            check(dev.jog("forward") == len(slots), "clamped at the last slot")
            check(dev.jog("backward") == len(slots) - 1, "backward")
            return "next/previous slot"

        def status():
            st = dev.get("status")
            check(st == ("0", "GS", "0"), f"{st}")

        def home_offset():
            if not rotator:
                raise NotOffered("no home offset on a slider")
            check(dev.get_home_offset() == 0, "offset at power-on")
            st = dev.set_home_offset(10.0)
            check(st == ("0", "GS", "0"), f"{st}")
            check(near_deg(dev.get_home_offset(), 10.0, pulses), "offset read back")
            dev.set_home_offset(0.0)

        def motor_info():
            for m in (1, 2):
                i = dev.get(f"motor_{m}_info")
                check(isinstance(i, dict) and i["Motor"] == "1", f"motor {m}: {i}")
            want = 14740000 / MOTOR1_PERIODS[0]
            got = dev.get("motor_1_info")["Forward frequency"]
            check(abs(got - want) < 1, f"{got}")

        def address():
            dev.change_address("5")
            check(dev.address == "5", "the client kept the old address")
            check(dev.get("info")["Motor Type"] == code, "in at 5")
            dev.change_address("0")
            check(dev.address == "0" and dev.get("info")["Motor Type"] == code, "back to 0")

        def save():
            check(dev.get("status") is not None, "status")
            dev.save_user_data()
            check(ctrl.last_status == ("0", "GS", "0"), f"{ctrl.last_status}")

        rec.run("identify", identify)
        rec.run("home", home)
        rec.run("absolute moves back to back", absolute)
        rec.run("relative moves", relative)
        rec.run("raw-count moves", not_offered("units only"))
        rec.run("velocity", not_offered("no sv/gv method"))
        rec.run("status", status)
        rec.run("jog", jog)
        rec.run("stop", not_offered("no st method"))
        rec.run("home offset", home_offset)
        rec.run("motor info", motor_info)
        rec.run("motor frequencies", not_offered("f1/b1 listed as to do"))
        rec.run("frequency search", not_offered("s1 listed as to do"))
        rec.run("address change", address)
        rec.run("save settings", save)
        if not rotator:
            rec.run("slots", lambda: absolute() and f"{len(slots)} slots, 1-based")
    finally:
        dev.close_connection()
    return rec.rows


# ---------------------------------------------------------------------------------------------
# pylablib: FW (FW102C / FW212C)


def pylablib_fw(model, port):
    from pylablib.devices import Thorlabs

    rec = Recorder("pylablib", model)
    n = WHEELS[model]
    dev = Thorlabs.FW(port)
    try:

        def identify():
            idn = dev.get_id()
            check("FW102C" in idn, idn)
            return idn

        def slots():
            # Every position, then across the first/last boundary (respect_bound splits it).
            order = list(range(1, n + 1)) + [1, n, 2]
            for k in order:
                check(dev.set_position(k) == k, f"pos={k}")
                check(dev.get_position() == k, f"pos? after pos={k}")
            return f"{len(order)} moves"

        def count():
            check(dev.get_pcount() == n, "pcount?")
            check(dev.set_pcount(n) == n, "pcount=")

        def mode(get, set_, values):
            def f():
                first = get()
                for v in values + [first]:
                    check(set_(v) == v, f"set {v}")
                    check(get() == v, f"get {v}")

            return f

        rec.run("identify", identify)
        rec.run("slots", slots)
        rec.run("position count", count)
        rec.run("speed mode", mode(dev.get_speed_mode, dev.set_speed_mode, ["high", "low"]))
        rec.run("trigger mode", mode(dev.get_trigger_mode, dev.set_trigger_mode, ["out", "in"]))
        rec.run("sensor mode", mode(dev.get_sensor_mode, dev.set_sensor_mode, ["on", "off"]))
        rec.run("save settings", lambda: dev.store_settings())

        def bad_command():
            try:
                reply = dev.ask("bogus?")
            except Exception as e:  # noqa: BLE001 - pylablib raises its own error types
                check("CMD_NOT_DEFINED" in str(e) or "Error" in str(e), f"{e!r}")
                return "refused"
            raise AssertionError(f"an unknown command was answered {reply!r}")

        rec.run("bad command", bad_command)
        check(dev.get_position() >= 1, "still answering after a bad command")
        dev.set_position(PARK_WHEEL)
    finally:
        dev.close()
    return rec.rows


def device_rows(model, port):
    if model in WHEELS:
        return pylablib_fw(model, port)
    rows = pylablib_elliptec(model, port)
    rows += roesel_elliptec(model, port)
    rows += thorlabs_elliptec_client(model, port, park=True)
    return rows


def markdown(rows, models):
    clients = []
    for r in rows:
        if r[0] not in clients:
            clients.append(r[0])
    cell = {(c, m, o): (s, d) for c, m, o, s, d, _ in rows}
    out = []
    for c in clients:
        cols = [m for m in models if any((c, m, o) in cell for o in OPERATIONS)]
        if not cols:
            continue
        out.append(f"**{c}**\n")
        out.append("| operation | " + " | ".join(m.upper() for m in cols) + " |")
        out.append("|---|" + "---|" * len(cols))
        for o in OPERATIONS:
            if not any((c, m, o) in cell for m in cols):
                continue
            vals = []
            for m in cols:
                s, d = cell.get((c, m, o), ("—", ""))
                if s == "—":
                    vals.append("—")
                    continue
                if s == "passed":
                    vals.append("passed")
                elif s == "not offered":
                    vals.append("not offered")
                elif s == "client difference":
                    vals.append(f"client difference: {d}")
                else:
                    vals.append(f"{s}: {d}")
            out.append(f"| {o} | " + " | ".join(vals) + " |")
        out.append("")
    return "\n".join(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("devices", nargs="+", metavar="MODEL=PORT")
    ap.add_argument("--results", help="write tab-separated rows here")
    args = ap.parse_args()
    if os.environ.get("CONFORMANCE_DEBUG"):
        logging.basicConfig(
            level=logging.DEBUG, format="%(relativeCreated)8.0f %(threadName)s %(message)s"
        )
    pairs = [d.split("=", 1) for d in args.devices]
    for m, _ in pairs:
        if m not in ROTATORS and m not in SLIDERS and m not in WHEELS:
            ap.error(f"model {m!r}: allowed ell14, ell18, ell6, ell9, fw102c, fw212c")
    t0 = time.monotonic()
    # One thread per device: each has its own pseudo-terminal.
    with concurrent.futures.ThreadPoolExecutor(max_workers=len(pairs)) as pool:
        futures = {m: pool.submit(device_rows, m, p) for m, p in pairs}
    rows = []
    for m, _ in pairs:
        try:
            rows += futures[m].result()
        except Exception as e:  # noqa: BLE001 - a client that cannot even connect
            traceback.print_exc(file=sys.stderr)
            rows.append(("(connect)", m, "identify", "FAILED", f"{type(e).__name__}: {e}", 0.0))
    print(markdown(rows, [m for m, _ in pairs]))
    if args.results:
        with open(args.results, "w") as f:
            for c, m, o, s, d, dt in rows:
                clean = " ".join(str(d).split()).replace("\t", " ")
                f.write(f"{c}\t{m}\t{o}\t{s}\t{clean}\t{dt:.3f}\n")
    failed = [r for r in rows if r[3] == "FAILED"]
    summary = f"conformance rows: {len(rows) - len(failed)} ok, {len(failed)} FAILED"
    print(f"{summary} in {time.monotonic() - t0:.1f} s", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
