#!/usr/bin/env python3
"""Standa's libximc against its own virtual controller and against the simulated Standa 8SMC5-USB
with the 8MPR16-1: the same command sequence, the replies compared field by field.

Usage: standa_ximc.py PORT [--results FILE] [--beyond]. PORT is the simulator's pseudo-terminal
(`/dev/pts/N` or the symlink `polarimeter simulate stage --dialect standa` prints; an `xi-com:`
URI is taken as it is). The emulator is libximc's virtual controller (`xi-emu:///DIR/virtual.bin`,
libximc's `devvirt.c`) on a state file in a fresh temporary directory, so it starts at its own
power-on defaults. Run it against a freshly started simulator: the first rows read the power-on
state. Needs libximc (pinned in scripts/requirements.txt) in the Python that runs it.

The sequence (libximc's C API through its `lowlevel` ctypes binding, so every call's result code
is seen as libximc returns it: 0 ok, -1 error, -2 not implemented, -3 value error (`errv`),
-4 no device): identity and the settings as found; the 8MPR16-1's move settings and a fast home
written to both; home, wait, zero; homezero; move, movr, set_position; an out-of-range speed (the
controller corrects it and answers `errv`) read back; right then soft stop; left then stop.

Output: a Markdown table on stdout (operation, emulator reply, simulator reply, same/different,
the differing fields with the reason where one is known) and, with --results FILE, one
tab-separated row per operation (operation, verdict, emulator reply, simulator reply, reasons).
A row is `same`, `different` (both answered, values differ; each difference has a reason, or
`UNEXPLAINED`) or `INCOMPATIBLE` (the call failed on the simulator and succeeded on the
emulator). Exit status 1 if any row is INCOMPATIBLE.

--beyond also runs calls whose commands are outside the simulator's documented set (`gnmf`,
`gnme`, `gsec`, `geds`, `gblv`, ...): the simulator answers them `errc` (libximc: -1), so they
are listed in a second table as `not modelled` and do not change the exit status.
"""

import argparse
import ctypes
import os
import sys
import tempfile
import time
import types

# libximc 3.1.2's binding does `import winreg` at the top, on every platform; a stand-in lets it
# load on Linux (winreg is only used on its Windows branch). 3.1.1 (the pinned one) does not need it.
if os.name != "nt":
    sys.modules.setdefault("winreg", types.ModuleType("winreg"))

from libximc.lowlevel import _lowlevel as ll  # noqa: E402

lib = ll.lib

RESULTS = {0: "ok", -1: "error", -2: "not implemented", -3: "value error (errv)", -4: "no device"}

# The 8MPR16-1's move settings as the simulator has them (Standa's profile from profile builder
# 0.9.16; the 0.10.26 one has Accel 500, Decel 1000): written to both devices so the motion rows
# compare behaviour, not two profiles.
PROFILE_MOVE = dict(Speed=500, uSpeed=0, Accel=2000, Decel=4000, AntiplaySpeed=500,
                    uAntiplaySpeed=0, MoveFlags=0)
# Its home settings, with FastHome raised from 100 to 4000 steps/s so the simulator's homing (up
# to a whole turn, 28 800 steps) takes seconds, not minutes.
FAST_HOME = dict(FastHome=4000, uFastHome=0, SlowHome=10, uSlowHome=0, HomeDelta=0,
                 uHomeDelta=0, HomeFlags=0x170)
# Over the protocol's range (move_settings_t.Speed: 0..100000).
OUT_OF_RANGE_SPEED = 200_000
JOG_S = 0.5
WAIT_MS = 10

MVCMD = {0: "UKNWN", 1: "MOVE", 2: "MOVR", 3: "LEFT", 4: "RIGHT", 5: "STOP", 6: "HOME",
         7: "LOFT", 8: "SSTP"}
FLAGS = [(0x1, "ERRC"), (0x2, "ERRD"), (0x4, "ERRV"), (0x10, "EEPROM_CONNECTED"),
         (0x20, "IS_HOMED"), (0x40, "ALARM")]
MOVE_STATE = [(0x1, "MOVING"), (0x2, "TARGET_SPEED"), (0x4, "ANTIPLAY")]


def mvcmd(v):
    s = MVCMD.get(v & 0x3F, f"?{v & 0x3F}")
    if v & 0x80:
        s += "|RUNNING"
    if v & 0x40:
        s += "|ERROR"
    return f"0x{v:02x} {s}"


def bits(v, names):
    on = [n for b, n in names if v & b]
    return f"0x{v:x}" + (f" {'|'.join(on)}" if on else "")


def fields_of(struct):
    out = {}
    for name, _kind in struct._fields_:
        v = getattr(struct, name)
        if isinstance(v, bytes):
            v = v.decode("latin-1")
        elif hasattr(v, "__len__"):
            v = list(v)
        out[name] = v
    return out


def show(name, v, status=False):
    if status and name == "MvCmdSts":
        return mvcmd(v)
    if status and name == "Flags":
        return bits(v, FLAGS)
    if status and name == "MoveSts":
        return bits(v, MOVE_STATE)
    if name in ("HomeFlags", "EngineFlags", "WindSts", "PowerFlags", "MoveFlags"):
        return f"0x{v:x}"
    if isinstance(v, str):
        return repr(v)
    return str(v)


class Device:
    """One libximc device, its calls recorded as (result code, fields)."""

    def __init__(self, uri):
        self.uri = uri
        self.id = lib.open_device(uri.encode())
        if self.id < 0:
            raise ConnectionError(f"libximc open_device({uri!r}) = {self.id}")

    def close(self):
        d = ctypes.c_int(self.id)
        return lib.close_device(ctypes.byref(d))

    def get(self, fn, struct):
        s = struct()
        r = getattr(lib, fn)(self.id, ctypes.byref(s))
        return {"result": r, **(fields_of(s) if r == 0 else {})}

    def call(self, fn, *args):
        return {"result": getattr(lib, fn)(self.id, *args)}

    def set(self, fn, struct, values):
        s = struct(**values)
        return {"result": getattr(lib, fn)(self.id, ctypes.byref(s))}


def sequence(dev, beyond=False):
    """The command sequence on `dev`: its rows (operation, reply dict, hint for reason()), the
    --beyond rows, and how long the waits for homing and for the move took."""
    rows = []
    # A hint for reason(): rows between set_position and the next motion command.
    tag = [None]

    def row(op, reply):
        rows.append((op, reply, tag[0]))
        return reply

    row("get_device_information (geti)", dev.get("get_device_information", ll.device_information_t))
    sn = ctypes.c_uint(0)
    r = lib.get_serial_number(dev.id, ctypes.byref(sn))
    row("get_serial_number (gser)", {"result": r, **({"SN": sn.value} if r == 0 else {})})
    v = [ctypes.c_uint(0) for _ in range(3)]
    r = lib.get_firmware_version(dev.id, *[ctypes.byref(x) for x in v])
    row("get_firmware_version (gfwv)",
        {"result": r, **(dict(zip(("Major", "Minor", "Release"), [x.value for x in v]))
                         if r == 0 else {})})
    row("get_entype_settings (gent)", dev.get("get_entype_settings", ll.entype_settings_t))
    row("get_engine_settings (geng)", dev.get("get_engine_settings", ll.engine_settings_t))
    row("get_move_settings (gmov)", dev.get("get_move_settings", ll.move_settings_t))
    row("get_home_settings (ghom)", dev.get("get_home_settings", ll.home_settings_t))
    row("get_power_settings (gpwr)", dev.get("get_power_settings", ll.power_settings_t))
    row("get_status at power-on (gets)", dev.get("get_status", ll.status_t))
    row("get_position at power-on (gpos)", dev.get("get_position", ll.get_position_t))

    row("set_move_settings: 8MPR16-1 profile (smov)",
        dev.set("set_move_settings", ll.move_settings_t, PROFILE_MOVE))
    row("get_move_settings after smov", dev.get("get_move_settings", ll.move_settings_t))
    row("set_home_settings: FastHome 4000 (shom)",
        dev.set("set_home_settings", ll.home_settings_t, FAST_HOME))
    row("get_home_settings after shom", dev.get("get_home_settings", ll.home_settings_t))

    row("command_home (home)", dev.call("command_home"))
    row("get_status just after home", dev.get("get_status", ll.status_t))
    t = time.monotonic()
    row("command_wait_for_stop after home", dev.call("command_wait_for_stop", WAIT_MS))
    home_s = time.monotonic() - t
    row("get_status after homing", dev.get("get_status", ll.status_t))
    row("command_zero (zero)", dev.call("command_zero"))
    row("get_position after zero", dev.get("get_position", ll.get_position_t))
    row("command_homezero (home, wait, zero)", dev.call("command_homezero"))
    row("get_position after homezero", dev.get("get_position", ll.get_position_t))
    st = row("get_status after homezero", dev.get("get_status", ll.status_t))

    row("command_move 800 steps (move)", dev.call("command_move", 800, 0))
    row("get_status just after move", dev.get("get_status", ll.status_t))
    t = time.monotonic()
    row("command_wait_for_stop after move", dev.call("command_wait_for_stop", WAIT_MS))
    move_s = time.monotonic() - t
    row("get_position after move", dev.get("get_position", ll.get_position_t))
    row("get_status after move", dev.get("get_status", ll.status_t))
    row("command_movr -100 steps -128 usteps (movr)", dev.call("command_movr", -100, -128))
    row("command_wait_for_stop after movr", dev.call("command_wait_for_stop", WAIT_MS))
    row("get_position after movr", dev.get("get_position", ll.get_position_t))
    row("get_status after movr", dev.get("get_status", ll.status_t))
    row("set_position 1000 steps (spos)",
        dev.set("set_position", ll.set_position_t,
                dict(Position=1000, uPosition=0, EncPosition=0, PosFlags=0)))
    tag[0] = "after spos"
    row("get_position after spos", dev.get("get_position", ll.get_position_t))

    bad = dict(PROFILE_MOVE, Speed=OUT_OF_RANGE_SPEED)
    row(f"set_move_settings Speed {OUT_OF_RANGE_SPEED} (smov, out of range)",
        dev.set("set_move_settings", ll.move_settings_t, bad))
    row("get_move_settings after out-of-range smov",
        dev.get("get_move_settings", ll.move_settings_t))
    row("get_status after out-of-range smov", dev.get("get_status", ll.status_t))
    row("set_move_settings: profile again (smov)",
        dev.set("set_move_settings", ll.move_settings_t, PROFILE_MOVE))

    before = dev.get("get_position", ll.get_position_t)
    tag[0] = None
    row("command_right (rigt)", dev.call("command_right"))
    time.sleep(JOG_S)
    row(f"get_status {JOG_S} s into right", dev.get("get_status", ll.status_t))
    row("command_sstp (sstp)", dev.call("command_sstp"))
    row("get_status just after sstp", dev.get("get_status", ll.status_t))
    row("command_wait_for_stop after sstp", dev.call("command_wait_for_stop", WAIT_MS))
    row("get_status after sstp", dev.get("get_status", ll.status_t))
    after = dev.get("get_position", ll.get_position_t)
    row("get_position after right + sstp", dict(after, **turned(before, after, 256)))

    before = after
    row("command_left (left)", dev.call("command_left"))
    time.sleep(JOG_S)
    row(f"get_status {JOG_S} s into left", dev.get("get_status", ll.status_t))
    row("command_stop (stop)", dev.call("command_stop"))
    row("get_status after stop", dev.get("get_status", ll.status_t))
    after = dev.get("get_position", ll.get_position_t)
    row("get_position after left + stop", dict(after, **turned(before, after, 256)))

    extra = []
    if beyond:
        for op, fn, struct in [
            ("get_controller_name (gnmf)", "get_controller_name", ll.controller_name_t),
            ("get_stage_name (gnme)", "get_stage_name", ll.stage_name_t),
            ("get_secure_settings (gsec)", "get_secure_settings", ll.secure_settings_t),
            ("get_edges_settings (geds)", "get_edges_settings", ll.edges_settings_t),
            ("get_feedback_settings (gfbs)", "get_feedback_settings", ll.feedback_settings_t),
            ("get_sync_out_settings (gsno)", "get_sync_out_settings", ll.sync_out_settings_t),
        ]:
            extra.append((op, dev.get(fn, struct)))
        v = [ctypes.c_uint(0) for _ in range(3)]
        r = lib.get_bootloader_version(dev.id, *[ctypes.byref(x) for x in v])
        extra.append(("get_bootloader_version (gblv)", {"result": r}))
        extra.append(("command_save_settings (save)", dev.call("command_save_settings")))
        # After the refusals: is the line still in step?
        extra.append(("get_position after the refusals", dev.get("get_position",
                                                                 ll.get_position_t)))
    return rows, extra, {"home_wait_s": home_s, "move_wait_s": move_s}


def turned(before, after, per):
    if before.get("result") != 0 or after.get("result") != 0:
        return {}
    d = (after["Position"] - before["Position"]) * per + (after["uPosition"] - before["uPosition"])
    return {"turned": "+" if d > 0 else "-" if d < 0 else "0"}


DEVVIRT = "libximc's virtual controller (devvirt.c)"
# Why the emulator's replies differ from the simulator's, with the source.
REASONS = {
    "identity": f"{DEVVIRT} answers geti as 'XISM-USB' with the version fields 0; the simulator "
                "answers as an 8SMC5-USB, hardware 2.3",
    "serial": "the emulator's serial is the one given in its URI (`?serial=`; none here: 0); the "
              "simulator's is its configured 17654",
    "firmware": f"{DEVVIRT} answers gfwv with zeros; the simulator says firmware 4.3.12",
    "profile": f"the emulator's power-on settings are {DEVVIRT} create_empty_state(): a generic "
               "200-step motor at 1000 steps/s; the simulator's are Standa's 8MPR16-1 profile "
               "(20-step motor, 500 steps/s, FastHome 100)",
    "errv": f"{DEVVIRT} stores every setting as sent, without range checks; the controller "
            "corrects a value out of range, applies it and answers errv (protocol.xi: "
            "move_settings_t.Speed 0..100000; STATE_ERRV in the next gets), which libximc "
            "returns as -3 (result_value_error)",
    "errv-readback": "the emulator kept the out-of-range speed as sent; the controller stored "
                     "the corrected value (the limit, 100000)",
    "supply": f"{DEVVIRT} draws random supply readings on every gets (Upwr 1201..1210, Ipwr "
              "3..9, Uusb 480..520, Iusb 180..210, CurT 366); the simulator's are fixed (Upwr "
              "1200, Ipwr 180, Uusb 500, Iusb 100, CurT 300)",
    "pwrsts": f"{DEVVIRT} never sets PWRSts (0, PWR_STATE_UNKNOWN) nor WindSts; the simulator "
              "reports PWR_STATE_NORM (3) and both windings fine (0x33)",
    "flags": f"{DEVVIRT} never sets Flags: no STATE_EEPROM_CONNECTED (0x10), no STATE_IS_HOMED "
             "(0x20) after a homing, no STATE_ERRV (0x4) after an errv; the simulator sets all "
             "three",
    "movests": f"{DEVVIRT} never sets MoveSts; the simulator sets MOVING while the motor turns "
               "and TARGET_SPEED at the cruise speed",
    "home": f"{DEVVIRT}'s home does not move: it sets MvCmdSts to HOME without the running bit "
            "and leaves the position; the simulator searches the home sensor (the index) at "
            "FastHome, so it stands elsewhere after homing until zero",
    "sstp": f"{DEVVIRT}'s sstp stops at once (MvCmdSts SSTP, speed 0); the controller "
            "decelerates at Decel, the command running (SSTP|RUNNING) until it stands",
    "ramp": f"{DEVVIRT} has no acceleration: it turns at the set speed from the first instant "
            "and stops at once; the simulator ramps at Accel/Decel, so an instant into a motion "
            "and after a timed jog the two stand at different places",
    "not-fresh": "the simulator had been driven before this run (not freshly started), so what "
                 "these rows read is where the last client left it, not the power-on state",
    "spos-drift": f"{DEVVIRT}'s spos sets the position but not the target of the last move, and "
                  "its CalculateNewPosition() keeps moving toward that target whenever the last "
                  "command was move/movr, running or not: its position drifts from 1000 back "
                  "toward the movr target 699.5 at 500 steps/s (an emulator defect); the "
                  "simulator stays where spos put it",
}


def reason(op, field, emu, sim, tag=None):
    """The REASONS key for the emulator's `field` differing from the simulator's, or None."""
    if field == "result":
        return "errv" if (sim == -3 and emu == 0) else None
    if field in ("Upwr", "Ipwr", "Uusb", "Iusb", "CurT"):
        return "supply"
    if op.startswith("get_device_information"):
        return "identity"
    if op.startswith("get_serial_number"):
        return "serial"
    if op.startswith("get_firmware_version"):
        return "firmware"
    if op.startswith(("get_engine_settings", "get_move_settings (", "get_home_settings (",
                      "get_power_settings", "get_entype_settings")):
        return "profile"
    if op.startswith("get_move_settings after out-of-range"):
        return "errv-readback"
    if field in ("PWRSts", "WindSts"):
        return "pwrsts"
    if field == "Flags":
        return "flags"
    if field == "MoveSts":
        return "movests"
    moving = ("CurPosition", "uCurPosition", "CurSpeed", "uCurSpeed", "Position", "uPosition")
    if "at power-on" in op and field in moving + ("MvCmdSts",):
        return "not-fresh"
    if "hom" in op and field in moving + ("MvCmdSts",):
        return "home"
    if "sstp" in op and field in ("MvCmdSts", "CurSpeed", "uCurSpeed"):
        return "sstp"
    if tag == "after spos" and field in moving:
        return "spos-drift"
    if field in moving and any(w in op for w in ("just after", "into", "sstp", "stop")):
        return "ramp"
    return None


def compare(op, emu, sim, tag=None):
    keys = list(dict.fromkeys(list(emu) + list(sim)))
    diffs = []
    for k in keys:
        a, b = emu.get(k, "(absent)"), sim.get(k, "(absent)")
        if a != b:
            diffs.append((k, a, b, reason(op, k, a, b, tag)))
    if not diffs:
        return "same", []
    if emu.get("result") == 0 and sim.get("result") not in (0, -3):
        return "INCOMPATIBLE", diffs
    return "different", diffs


def fmt(reply):
    r = reply.get("result")
    parts = [f"result={r} ({RESULTS.get(r, '?')})"]
    status = "MvCmdSts" in reply
    parts += [f"{k}={show(k, v, status)}" for k, v in reply.items() if k != "result"]
    return "; ".join(parts)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("port")
    ap.add_argument("--results")
    ap.add_argument("--beyond", action="store_true",
                    help="also run calls outside the simulator's documented command set")
    args = ap.parse_args()
    sim_uri = args.port if args.port.startswith("xi-") else "xi-com://" + args.port
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="ximc-emu-") as tmp:
        emu_uri = "xi-emu://" + os.path.join(tmp, "virtual_controller.bin")
        emu = Device(emu_uri)
        emu_rows, emu_extra, emu_t = sequence(emu, args.beyond)
        emu.close()
    t1 = time.monotonic()
    sim = Device(sim_uri)
    sim_rows, sim_extra, sim_t = sequence(sim, args.beyond)
    sim.close()
    t2 = time.monotonic()

    version = ctypes.create_string_buffer(32)
    lib.ximc_version(version)
    print(f"libximc {version.value.decode()}; emulator {emu_uri} ({t1 - t0:.1f} s); "
          f"simulator {sim_uri} ({t2 - t1:.1f} s; homing waited {sim_t['home_wait_s']:.1f} s, "
          f"the 800-step move {sim_t['move_wait_s']:.1f} s)\n")

    table = []
    for (op, e, tag), (op2, s, _) in zip(emu_rows, sim_rows):
        assert op == op2
        verdict, diffs = compare(op, e, s, tag)
        table.append((op, verdict, e, s, diffs))

    used = []

    def notes(diffs):
        groups = {}
        for k, a, b, why in diffs:
            groups.setdefault(why, []).append(k)
        out = []
        for why, ks in groups.items():
            if why is None:
                out.append(f"{', '.join(ks)}: UNEXPLAINED")
            else:
                if why not in used:
                    used.append(why)
                out.append(f"{', '.join(ks)} [{why}]")
        return "; ".join(out)

    print("| operation | emulator (xi-emu) | simulator (xi-com) | verdict | differences and reasons |")
    print("|---|---|---|---|---|")
    for op, verdict, e, s, diffs in table:
        print(f"| {op} | {fmt(e)} | {fmt(s)} | {verdict} | {notes(diffs)} |")

    extra_table = []
    if args.beyond:
        print("\nOutside the simulator's documented command set (not counted):\n")
        print("| operation | emulator (xi-emu) | simulator (xi-com) | verdict |")
        print("|---|---|---|---|")
        for (op, e), (_, s) in zip(emu_extra, sim_extra):
            verdict, _ = compare(op, e, s)
            if verdict == "INCOMPATIBLE":
                verdict = "not modelled"
            extra_table.append((op, verdict, e, s, []))
            print(f"| {op} | {fmt(e)} | {fmt(s)} | {verdict} |")

    print("\nReasons:\n")
    for key in used:
        print(f"- [{key}] {REASONS[key]}")

    bad = [t for t in table if t[1] == "INCOMPATIBLE"]
    unexplained = [t for t in table if any(d[3] is None for d in t[4])]
    print(f"\n{sum(t[1] == 'same' for t in table)} same, "
          f"{sum(t[1] == 'different' for t in table)} different, {len(bad)} incompatible "
          f"({len(unexplained)} rows with an unexplained difference)")
    for op, _, e, s, _ in bad:
        print(f"INCOMPATIBLE: {op}: emulator {fmt(e)}; simulator {fmt(s)}")
    if args.results:
        with open(args.results, "w") as f:
            for op, verdict, e, s, diffs in table + extra_table:
                f.write("\t".join((op, verdict, fmt(e), fmt(s), notes(diffs))) + "\n")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
