#!/usr/bin/env python3
"""Public APT client libraries against the simulated Thorlabs APT mounts, over real pseudo-terminals.

Each simulated mount is given as MODEL=PORT (models: prm1z8, k10cr1). Clients:
thorlabs-apt-device (`thorlabs_apt_device.KDC101` for the PRM1Z8 on its KDC101; the K10CR1 has
no class of its own there, so its generic `APTDevice_Motor` is used as the library's
documentation says for other single-channel controllers, polling `MOT_REQ_STATUSUPDATE`), its
protocol layer (`thorlabs_apt_device.protocol`: `HW_REQ_INFO` packed and `HW_GET_INFO` unpacked
by the library's own code, which its device classes never send), and pylablib's
`Thorlabs.KinesisMotor`.

Every operation a client offers is run as the library's documentation runs it and checked
through the same client. An operation is `passed`, or a `client difference` whose reason is
stated here and whose symptom is checked (a client that changes makes the row fail), or
`not offered`. Anything else is `FAILED`. Output: a Markdown table on stdout and, with
--results FILE, one tab-separated row per cell (client, model, operation, status, detail).
Exit status 1 if any row FAILED.

Run by tests/tests/hil/conformance_apt.rs, which serves the mounts at 90 deg/s (velocity cap,
homing and default velocity) so that homing takes at most 4 s.
"""

import argparse
import concurrent.futures
import sys
import time
import traceback

# The simulated mounts' facts the checks rely on (hil-mocks/src/apt.rs).
MODELS = {
    # model: (controller string, serial, counts per degree, status request)
    "prm1z8": ("KDC101", 27000456, 1919.6418578623391),
    "k10cr1": ("K10CR1", 55000123, 409600 / 3),
}
# A reading is within 3 counts of its target: 6 sigma of the PRM1Z8's 0.5-count servo dither
# (the K10CR1's microstep counter is exact).
TOL_COUNTS = 3
# Where each mount is left, for the Rust test to check the simulator's ground truth.
PARK_DEG = 123.0
# The slowest motion the checks wait for: a full turn at 90 deg/s plus the ramps, with margin.
WAIT_S = 15.0

OPERATIONS = [
    "identify (HW_REQ_INFO)",
    "identify (MOD_IDENTIFY)",
    "enable / disable channel",
    "home",
    "move absolute",
    "move relative",
    "position",
    "velocity parameters",
    "status bits",
    "jog",
    "move at velocity + stop",
    "home parameters",
    "backlash (general move parameters)",
]


class Difference(Exception):
    """The client behaves differently from what the device supports; the reason says how."""


class NotOffered(Exception):
    """The client has no such operation."""


def check(cond, what):
    if not cond:
        raise AssertionError(what)


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
        self.rows.append((self.client, self.model, op, status, detail, time.monotonic() - t0))


def wait_for(cond, what, timeout=WAIT_S):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if cond():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


# ---------------------------------------------------------------------------------------------
# thorlabs-apt-device: protocol layer


def apt_protocol_info(model, port):
    """HW_REQ_INFO packed by the library, HW_GET_INFO decoded by its Unpacker."""
    import serial
    from thorlabs_apt_device import protocol as apt
    from thorlabs_apt_device.enums import EndPoint

    rec = Recorder("thorlabs-apt-device (protocol)", model)
    controller, serial_no, _ = MODELS[model]

    def info():
        with serial.Serial(port, baudrate=115200, timeout=0.1) as p:
            p.reset_input_buffer()
            p.write(apt.hw_req_info(source=EndPoint.HOST, dest=EndPoint.USB))
            unpacker = apt.Unpacker(p)
            t_end = time.monotonic() + 2.0
            while time.monotonic() < t_end:
                for m in unpacker:
                    if m.msg == "hw_get_info":
                        model_no = m.model_number.rstrip(b"\0").decode()
                        check(model_no == controller, f"model {model_no!r}, want {controller}")
                        check(m.serial_number == serial_no, f"serial {m.serial_number}")
                        check(m.nchs == 1, f"channels {m.nchs}")
                        return f"{model_no} serial {m.serial_number}, firmware {m.firmware_version}"
            raise AssertionError("no hw_get_info within 2 s")

    rec.run("identify (HW_REQ_INFO)", info)
    return rec.rows


# ---------------------------------------------------------------------------------------------
# thorlabs-apt-device: KDC101 / APTDevice_Motor


def apt_device(model, port):
    from thorlabs_apt_device import KDC101, protocol as apt
    from thorlabs_apt_device.devices.aptdevice_motor import APTDevice_Motor
    from thorlabs_apt_device.enums import EndPoint

    _, _, cpd = MODELS[model]
    if model == "prm1z8":
        client = "thorlabs-apt-device KDC101"
        dev = KDC101(serial_port=port, home=True)
    else:
        client = "thorlabs-apt-device APTDevice_Motor"
        dev = APTDevice_Motor(
            serial_port=port,
            home=True,
            status_updates="polled",
            controller=None,
            bays=(EndPoint.USB,),
            channels=(1,),
        )
        dev.update_message = apt.mot_req_statusupdate
    rec = Recorder(client, model)
    st = dev.status_[0][0]

    def still():
        keys = ("moving_forward", "moving_reverse", "jogging_forward", "jogging_reverse", "homing")
        return not any(st[k] for k in keys)

    def settle(target, what):
        wait_for(lambda: still() and abs(st["position"] - target) <= TOL_COUNTS, what)

    try:

        def identify():
            dev.identify()
            # MOD_IDENTIFY has no reply: the mount must go on answering the client's polling.
            wait_for(lambda: st["msgid"] != 0, "a status update after MOD_IDENTIFY", 2.0)
            return "no reply by design; the status polling goes on"

        def enable():
            wait_for(lambda: st["channel_enabled"], "channel enabled (the constructor enables)")
            dev.set_enabled(False)
            wait_for(lambda: not st["channel_enabled"], "channel disabled")
            dev.set_enabled(True)
            wait_for(lambda: st["channel_enabled"], "channel enabled again")

        def home():
            # The constructor homes after 1 s (home=True).
            wait_for(lambda: st["homed"] and still(), "homed")
            check(abs(st["position"]) <= TOL_COUNTS, f"position {st['position']} after homing")

        def move_absolute():
            for deg in (90.0, 350.0, 10.0):
                target = round(deg * cpd)
                dev.move_absolute(target)
                settle(target, f"absolute move to {deg} deg")

        def move_relative():
            start = st["position"]
            dev.move_relative(round(-20.0 * cpd))
            settle(start - round(20.0 * cpd), "relative move by -20 deg")

        def position():
            dev.move_absolute(round(45.0 * cpd))
            settle(round(45.0 * cpd), "45 deg")
            return f"{st['position'] / cpd:.4f} deg"

        def velocity():
            vp = dev.velparams_[0][0]
            wait_for(lambda: vp["max_velocity"] > 0, "velocity parameters read at connect")
            acc, vmax = vp["acceleration"], vp["max_velocity"] // 2
            dev.set_velocity_params(acc, vmax)
            wait_for(lambda: vp["max_velocity"] == vmax, "max velocity read back")
            check(vp["acceleration"] == acc, f"acceleration {vp['acceleration']}")
            dev.set_velocity_params(acc, vmax * 2)
            wait_for(lambda: vp["max_velocity"] == vmax * 2, "max velocity restored")

        def status():
            check(st["homed"] and st["channel_enabled"], f"status {st}")
            check(st["motor_connected"], "motor connected bit")
            return "homed, enabled, motor connected, moving flags"

        def jog():
            jp = dev.jogparams_[0][0]
            step = round(5.0 * cpd)
            dev.set_jog_params(step, jp["acceleration"] or 1000, jp["max_velocity"] or 1000)
            wait_for(lambda: jp["step_size"] == step, "jog step read back")
            start = st["position"]
            dev.move_jog("forward")
            wait_for(lambda: still() and abs(abs(st["position"] - start) - step) <= TOL_COUNTS, "one jog step")

        def velocity_stop():
            # MOT_MOVE_VELOCITY both ways (param2 1 forward, 2 reverse), each ended by
            # MOT_MOVE_STOP: profiled after the forward run, immediate after the reverse one.
            # The KDC101 class inverts by default (invert_direction_logic=True: its "forward"
            # sends param2 2, toward negative counts, and it swaps the moving bits to match);
            # the counts must move the way the client's flag says.
            invert = -1 if dev.invert_direction_logic else 1
            for direction, sign, immediate in (("forward", invert, False), ("reverse", -invert, True)):
                start = st["position"]
                bit = "moving_" + direction
                dev.move_velocity(direction)
                wait_for(lambda: st[bit], f"the {bit} bit at velocity")
                time.sleep(0.3)
                dev.stop(immediate=immediate)
                wait_for(still, "stopped")
                p = st["position"]
                check(sign * (p - start) > 0, f"a {direction} velocity move went {start} -> {p} counts")
                time.sleep(0.3)
                check(abs(st["position"] - p) <= TOL_COUNTS, "still after the stop")

        def home_params():
            hp = dev.homeparams_[0][0]
            wait_for(lambda: hp["home_velocity"] > 0, "home parameters read at connect")
            v = hp["home_velocity"]
            dev.set_home_params(v, 0, direction="reverse")
            wait_for(lambda: hp["home_dir"] == 2 and hp["offset_distance"] == 0, "home parameters")

        def backlash():
            gp = dev.genmoveparams_[0][0]
            dev.set_move_params(round(0.5 * cpd))
            wait_for(lambda: gp["backlash_distance"] == round(0.5 * cpd), "backlash read back")

        rec.run("identify (HW_REQ_INFO)", lambda: (_ for _ in ()).throw(NotOffered(
            "the device classes never send HW_REQ_INFO (see the protocol-layer row)")))
        rec.run("identify (MOD_IDENTIFY)", identify)
        rec.run("home", home)
        rec.run("enable / disable channel", enable)
        rec.run("move absolute", move_absolute)
        rec.run("move relative", move_relative)
        rec.run("position", position)
        rec.run("velocity parameters", velocity)
        rec.run("status bits", status)
        rec.run("jog", jog)
        rec.run("move at velocity + stop", velocity_stop)
        rec.run("home parameters", home_params)
        rec.run("backlash (general move parameters)", backlash)
        target = round(PARK_DEG * cpd)
        # Park: the nearest count at PARK_DEG from where the mount is.
        here = st["position"]
        turns = round((here - target) / (360.0 * cpd))
        target += round(turns * 360.0 * cpd)
        dev.move_absolute(target)
        settle(target, "park")
    finally:
        dev.close()
        time.sleep(0.3)
    return rec.rows


# ---------------------------------------------------------------------------------------------
# pylablib: KinesisMotor


def pylablib_kinesis(model, port):
    rec = Recorder("pylablib KinesisMotor", model)

    def connect():
        from pylablib.devices import Thorlabs

        try:
            dev = Thorlabs.KinesisMotor(("serial", port), scale="stage")
        except OSError as e:
            # pylablib cycles RTS (setRTS) when it opens a serial port; a pseudo-terminal has no
            # modem lines and refuses the ioctl (ENOTTY, errno 25). On a real controller's FTDI
            # port the call succeeds.
            if e.errno == 25:
                raise Difference(
                    "KinesisMotor sets RTS on open; a pseudo-terminal refuses it (ENOTTY), so "
                    "pylablib cannot reach the simulator; not run"
                ) from e
            raise
        dev.close()
        return "connected"

    rec.run("identify (HW_REQ_INFO)", connect)
    return rec.rows


def device_rows(model, port):
    rows = apt_protocol_info(model, port)
    rows += apt_device(model, port)
    rows += pylablib_kinesis(model, port)
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
                vals.append(s if s in ("passed", "—") else f"{s}: {d}")
            out.append(f"| {o} | " + " | ".join(vals) + " |")
        out.append("")
    return "\n".join(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("devices", nargs="+", metavar="MODEL=PORT")
    ap.add_argument("--results", help="write tab-separated rows here")
    args = ap.parse_args()
    pairs = [d.split("=", 1) for d in args.devices]
    for m, _ in pairs:
        if m not in MODELS:
            ap.error(f"model {m!r}: allowed prm1z8, k10cr1")
    t0 = time.monotonic()
    with concurrent.futures.ThreadPoolExecutor(max_workers=len(pairs)) as pool:
        futures = {m: pool.submit(device_rows, m, p) for m, p in pairs}
    rows = []
    for m, _ in pairs:
        try:
            rows += futures[m].result()
        except Exception as e:  # noqa: BLE001 - a client that cannot even connect
            traceback.print_exc(file=sys.stderr)
            rows.append(("(connect)", m, "identify (HW_REQ_INFO)", "FAILED", f"{type(e).__name__}: {e}", 0.0))
    print(markdown(rows, [m for m, _ in pairs]))
    if args.results:
        with open(args.results, "w") as f:
            for c, m, o, s, d, dt in rows:
                clean = " ".join(str(d).split()).replace("\t", " ")
                f.write(f"{c}\t{m}\t{o}\t{s}\t{clean}\t{dt:.3f}\n")
    failed = [r for r in rows if r[3] == "FAILED"]
    print(f"conformance rows: {len(rows) - len(failed)} ok, {len(failed)} FAILED in "
          f"{time.monotonic() - t0:.1f} s", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
