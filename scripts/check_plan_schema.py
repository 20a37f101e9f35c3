#!/usr/bin/env python3
"""The file schemas (`polarimeter plan schema --file plan|rig|scene|camera`) against the files
users are shown, judged by the `jsonschema` package (Draft 2020-12), not by our parsers.

Usage: check_plan_schema.py --bin PATH/TO/polarimeter

Every plan in examples/plans/ and tests/fixtures/ (TOML or YAML, those with a `kind`), every
rig in examples/rigs/, every camera in examples/cameras/ and every scene in examples/ (those
with a `[sun]`) must validate (our parsers read them all: the tests use them). The schema must not be vacuous: a capture plan with an unknown key, a wrong type (`repeats = "three"`), an
unknown kind or without its `exposure_us` must each be refused. Prints one line per plan; exits
1 on any failure.
"""

import glob
import json
import os
import subprocess
import sys
import tomllib

import jsonschema
import yaml

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def load(path):
    with open(path, "rb") as f:
        if path.endswith(".toml"):
            return tomllib.load(f)
        return yaml.safe_load(f)


def main(argv):
    if len(argv) != 3 or argv[1] != "--bin":
        print(__doc__, file=sys.stderr)
        return 2
    binary = argv[2]
    def validator_of(kind):
        schema = json.loads(subprocess.run([binary, "plan", "schema", "--file", kind], check=True,
                                           capture_output=True, text=True).stdout)
        return jsonschema.Draft202012Validator(schema)

    failed = 0
    others = [("rig", "examples/rigs/*.toml", "stage"), ("camera", "examples/cameras/*.toml", "name"),
              ("scene", "examples/*.toml", "sun")]
    for kind, pattern, marker in others:
        v = validator_of(kind)
        found = 0
        for path in sorted(glob.glob(os.path.join(ROOT, pattern))):
            data = load(path)
            if marker not in data:
                continue
            found += 1
            errors = [e.message for e in v.iter_errors(data)]
            rel = os.path.relpath(path, ROOT)
            print(f"{'ok' if not errors else 'FAILED'}  {kind} {rel}"
                  + (f": {errors[:3]}" if errors else ""))
            failed += bool(errors)
        if found < 2:
            print(f"FAILED  fewer than 2 {kind} files found")
            failed += 1
    validator = validator_of("plan")
    paths = sorted(glob.glob(os.path.join(ROOT, "examples/plans/*.*"))
                   + glob.glob(os.path.join(ROOT, "tests/fixtures/*.toml")))
    checked = 0
    for path in paths:
        if not path.endswith((".toml", ".yaml", ".yml")):
            continue
        plan = load(path)
        if not isinstance(plan, dict) or "kind" not in plan:
            continue
        checked += 1
        errors = [e.message for e in validator.iter_errors(plan)]
        rel = os.path.relpath(path, ROOT)
        print(f"{'ok' if not errors else 'FAILED'}  {rel}" + (f": {errors[:3]}" if errors else ""))
        failed += bool(errors)
    good = {"kind": "capture", "capture": {"angles_deg": [0, 45, 90], "exposure_us": [100]}}
    bad = {
        "unknown key": {**good, "capture": {**good["capture"], "repeat": 3}},
        "wrong type": {**good, "capture": {**good["capture"], "repeats": "three"}},
        "unknown kind": {**good, "kind": "capturing"},
        "missing exposure_us": {**good, "capture": {"angles_deg": [0, 45, 90]}},
    }
    if list(validator.iter_errors(good)):
        print(f"FAILED  a minimal capture plan is refused: {good}")
        failed += 1
    for what, plan in bad.items():
        refused = bool(list(validator.iter_errors(plan)))
        print(f"{'ok' if refused else 'FAILED'}  refused: {what}")
        failed += not refused
    print(f"{checked} plans validated, {failed} failures")
    if checked < 10:
        print("FAILED  fewer than 10 plans found")
        return 1
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
