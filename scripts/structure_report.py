#!/usr/bin/env python3
"""The workspace's structure in numbers: import cycles between files of each crate, and the
longest functions.

Usage: python3 scripts/structure_report.py [--top N] [--max-lines L]

For each crate's `src/` (every workspace member with one), the import cycles between its
files as `scripts/check_module_dag.py` counts them (test modules left out). Then the N longest
functions of the non-test code (`#[cfg(test)]` items left out, as the DAG check does), from the
line of `fn` to the closing brace, and how many are longer than L lines (default 150: a
function a reader can hold). Exits 0: a report, not a gate (the gate is the DAG check each
crate runs in CI).
"""

import contextlib
import io
import os
import re
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.normpath(os.path.join(HERE, ".."))
sys.path.insert(0, HERE)
import check_module_dag as dag  # noqa: E402


def cycles_of(src):
    """The number of import cycles the DAG check finds in `src`."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        status = dag.main(["check_module_dag.py", src])
    if status == 0:
        return 0
    m = re.search(r"has (\d+)\+? import cycle", buf.getvalue())
    return int(m.group(1)) if m else -1


def functions(path):
    """(name, first line, lines) of every function with a body in the file's non-test code."""
    with open(path, encoding="utf-8") as f:
        code = dag.strip_comments_and_strings(f.read())
    code, _ = dag.strip_test_items(code)
    out = []
    for m in re.finditer(r"\bfn\s+([A-Za-z_][A-Za-z0-9_]*)", code):
        depth, i, body = 0, m.end(), None
        while i < len(code):
            c = code[i]
            if c in "([":
                depth += 1
            elif c in ")]":
                depth -= 1
            elif depth == 0 and c == ";":
                break
            elif depth == 0 and c == "{":
                body = i
                break
            i += 1
        if body is None:
            continue
        level, j = 0, body
        while j < len(code):
            if code[j] == "{":
                level += 1
            elif code[j] == "}":
                level -= 1
                if level == 0:
                    break
            j += 1
        first = code.count("\n", 0, m.start()) + 1
        last = code.count("\n", 0, j) + 1
        out.append((m.group(1), first, last - first + 1))
    return out


def main(argv):
    top = int(argv[argv.index("--top") + 1]) if "--top" in argv else 15
    limit = int(argv[argv.index("--max-lines") + 1]) if "--max-lines" in argv else 150
    print("import cycles between files, by crate (scripts/check_module_dag.py):")
    total = 0
    for src in dag.crate_sources():
        n = cycles_of(src)
        total += max(n, 0)
        print(f"  {os.path.relpath(src, ROOT):32} {n}")
    print(f"  {'total':32} {total}")
    found = []
    for src in dag.crate_sources():
        for root, _, names in os.walk(src):
            for name in names:
                if name.endswith(".rs"):
                    path = os.path.join(root, name)
                    for fn, line, lines in functions(path):
                        found.append((lines, f"{os.path.relpath(path, ROOT)}:{line}", fn))
    found.sort(reverse=True)
    over = sum(1 for f in found if f[0] > limit)
    print(f"\nlongest functions ({len(found)} in all, {over} over {limit} lines):")
    for lines, where, fn in found[:top]:
        print(f"  {lines:5}  {fn:32} {where}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
