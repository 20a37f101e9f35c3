#!/usr/bin/env python3
"""Check that the modules of a crate form a DAG: no import cycle.

Usage: python3 scripts/check_module_dag.py [--with-tests] [SRC_DIR | --workspace]
       (default: crates/model/src; --workspace: every workspace crate's src/, as CI runs it)

Each file is one module: `a.rs` and `a/mod.rs` are `a`, `a/b.rs` is `a::b`; the crate root
(`lib.rs`) is not a node, it only declares the modules and re-exports (`crate::ModelError` counts
as a reference to the module `lib.rs` re-exports it from). A `mod foo { ... }` written inside a
file belongs to that file, and its references count as the file's. Items under `#[cfg(test)]`
(the test modules, inline or in their own file) are left out: they are compiled only into the
crate's test build, where they sit above every module like an integration test, so a test of
`scene` that loads an example through `scene_file` is not a cycle. `--with-tests` counts them.

A module refers to another when its code (comments and string literals removed) names it by a
path: `crate::a::b::Item` in a `use` statement or an expression, a grouped `use crate::{a, b::c}`,
`super::` and `self::` paths, and a path whose first segment is one of its child modules. Each
path is resolved to the longest prefix that is a module. Doc links (`[`crate::a`]`) are comments
and do not count.

Prints every cycle as a chain of module names, with one place each edge comes from, and exits 1;
otherwise prints the number of modules and of edges and exits 0.
"""

import os
import re
import sys

MAX_CYCLES = 200


def strip_comments_and_strings(text):
    """The source with comments, string and char literals blanked (newlines kept, for line numbers)."""
    out = []
    i, n = 0, len(text)

    def blank(s):
        return "".join(ch if ch == "\n" else " " for ch in s)

    while i < n:
        c = text[i]
        if text.startswith("//", i):
            j = text.find("\n", i)
            j = n if j < 0 else j
            out.append(blank(text[i:j]))
            i = j
        elif text.startswith("/*", i):
            depth, j = 1, i + 2
            while j < n and depth:
                if text.startswith("/*", j):
                    depth, j = depth + 1, j + 2
                elif text.startswith("*/", j):
                    depth, j = depth - 1, j + 2
                else:
                    j += 1
            out.append(blank(text[i:j]))
            i = j
        elif c in "rb" and re.match(r"(br|r)#*\"", text[i:i + 260]) and not (
            i > 0 and (text[i - 1].isalnum() or text[i - 1] == "_")
        ):
            m = re.match(r"(br|r)(#*)\"", text[i:])
            close = '"' + m.group(2)
            j = text.find(close, i + m.end())
            j = n if j < 0 else j + len(close)
            out.append(blank(text[i:j]))
            i = j
        elif c == '"' or (c == "b" and text.startswith('b"', i)):
            j = i + (2 if c == "b" else 1)
            while j < n and text[j] != '"':
                j += 2 if text[j] == "\\" else 1
            j += 1
            out.append(blank(text[i:j]))
            i = j
        elif c == "'":
            m = re.match(r"'(\\u\{[0-9a-fA-F]+\}|\\x[0-9a-fA-F]{2}|\\.|[^\\'\n])'", text[i:])
            if m:
                out.append(blank(m.group(0)))
                i += m.end()
            else:  # a lifetime or a label
                out.append(c)
                i += 1
        else:
            out.append(c)
            i += 1
    return "".join(out)


CFG_TEST = re.compile(r"#\s*\[\s*cfg\s*\(\s*test\s*\)\s*\]")


def strip_test_items(code):
    """The code with every `#[cfg(test)]` item blanked; and the names of `#[cfg(test)] mod x;`."""
    test_mods = set()
    while True:
        m = CFG_TEST.search(code)
        if not m:
            return code, test_mods
        i = m.end()
        while i < len(code) and code[i] != "{" and code[i] != ";":
            i += 1
        if i < len(code) and code[i] == "{":
            depth = 0
            while i < len(code):
                depth += {"{": 1, "}": -1}.get(code[i], 0)
                i += 1
                if depth == 0:
                    break
        else:
            decl = re.search(r"\bmod\s+([A-Za-z_][A-Za-z0-9_]*)\s*$", code[m.end():i])
            if decl:
                test_mods.add(decl.group(1))
            i += 1
        code = code[: m.start()] + "".join(c if c == "\n" else " " for c in code[m.start():i]) + code[i:]


def module_of(rel_path):
    """`a/b.rs` -> ('a', 'b'); `a/mod.rs` -> ('a',); `lib.rs` -> ()."""
    parts = rel_path[:-3].split(os.sep)
    if parts[-1] == "mod":
        parts = parts[:-1]
    if parts == ["lib"]:
        parts = []
    return tuple(parts)


TOKEN = re.compile(r"\$?[A-Za-z_][A-Za-z0-9_]*|::|[{},;()<>]|\S")


def tokens(code):
    """(token, line) pairs."""
    line = 1
    pos = 0
    for m in TOKEN.finditer(code):
        line += code.count("\n", pos, m.start())
        pos = m.start()
        yield m.group(0), line


def use_tree_paths(toks, k, prefix):
    """Expand the use tree starting at toks[k] (after `prefix::`); returns (paths, next index)."""
    paths = []
    if toks[k][0] == "{":
        k += 1
        while toks[k][0] != "}":
            sub, k = use_tree_paths(toks, k, prefix)
            paths += sub
            if toks[k][0] == ",":
                k += 1
        return paths, k + 1
    path = list(prefix)
    while True:
        t = toks[k][0]
        if t == "{":
            sub, k = use_tree_paths(toks, k, path)
            return paths + sub, k
        if t == "*":
            return paths + [path], k + 1
        path.append(t)
        k += 1
        if toks[k][0] == "::":
            k += 1
            continue
        if toks[k][0] == "as":
            k += 2
        return paths + [path], k


def references(code):
    """(path segments, line) of every path the code names, `use` trees expanded."""
    toks = list(tokens(code))
    refs = []
    k = 0
    while k < len(toks):
        t, line = toks[k]
        prev = toks[k - 1][0] if k else ""
        if t == "use" and prev != "::":
            paths, k2 = use_tree_paths(toks, k + 1, [])
            refs += [(p, line) for p in paths]
            k = k2
            continue
        if re.match(r"[A-Za-z_]", t) and prev != "::" and k + 1 < len(toks) and toks[k + 1][0] == "::":
            if prev == "in":  # pub(in crate::a): a visibility, not a reference
                k += 1
                continue
            path = [t]
            j = k + 1
            while j + 1 < len(toks) and toks[j][0] == "::" and re.match(r"[A-Za-z_{]", toks[j + 1][0]):
                if toks[j + 1][0] == "{":  # expression paths do not group; a turbofish or struct literal
                    break
                path.append(toks[j + 1][0])
                j += 2
            refs.append((path, line))
            k = j
            continue
        k += 1
    return refs


def main(argv):
    with_tests = "--with-tests" in argv
    argv = [a for a in argv if a != "--with-tests"]
    src = argv[1] if len(argv) > 1 else os.path.join(
        os.path.dirname(os.path.abspath(__file__)), "..", "crates", "model", "src"
    )
    src = os.path.normpath(src)
    files = {}
    for root, _, names in os.walk(src):
        for name in sorted(names):
            if name.endswith(".rs"):
                path = os.path.join(root, name)
                files[module_of(os.path.relpath(path, src))] = path
    modules = {m for m in files if m}
    code = {}
    test_only = set()
    for m, path in files.items():
        with open(path, encoding="utf-8") as f:
            code[m] = strip_comments_and_strings(f.read())
        if not with_tests:
            code[m], test_mods = strip_test_items(code[m])
            test_only |= {m + (t,) for t in test_mods}
    # a test module in its own file, and everything under it
    for m in list(code):
        if any(m[: len(t)] == t for t in test_only):
            code[m] = ""

    # Names the crate root re-exports: `pub use a::b::Item;` -> Item is reached through a::b.
    root_reexports = {}
    for path, _ in references(code.get((), "")):
        if path and path[0] != "crate" and len(path) > 1:
            root_reexports[path[-1]] = path

    def resolve(m, path):
        """The module a path seen in module m names (longest module prefix), or None."""
        if not path:
            return None
        if path[0] == "crate":
            segs = path[1:]
            if segs and (segs[0],) not in modules and segs[0] in root_reexports:
                segs = root_reexports[segs[0]]
            base = ()
        elif path[0] in ("self", "super"):
            base, segs = m, list(path)
            while segs and segs[0] in ("self", "super"):
                if segs.pop(0) == "super":
                    base = base[:-1]
        elif m + (path[0],) in modules:  # a child module, named relatively
            base, segs = m, path
        else:
            return None  # std, an external crate, a local item or enum variant
        best = base if base else None
        for i in range(1, len(segs) + 1):
            cand = base + tuple(segs[:i])
            if cand in modules:
                best = cand
            else:
                break
        return best

    edges = {}  # (from, to) -> (file, line)
    for m in sorted(modules):
        for path, line in references(code[m]):
            target = resolve(m, path)
            if target and target != m and (m, target) not in edges:
                edges[(m, target)] = (os.path.relpath(files[m]), line)

    graph = {m: sorted({t for (f, t) in edges if f == m}) for m in modules}
    name = "::".join

    cycles = elementary_cycles(graph)
    if cycles:
        print(f"module graph has {len(cycles)}{'+' if len(cycles) >= MAX_CYCLES else ''} "
              f"import cycle(s):")
        for cyc in cycles:
            chain = cyc + [cyc[0]]
            print("  " + " -> ".join(name(x) for x in chain))
            for a, b in zip(chain, chain[1:]):
                f, line = edges[(a, b)]
                print(f"      {name(a)} -> {name(b)}: {f}:{line}")
        return 1
    what = "with" if with_tests else "without"
    print(f"ok: {len(modules)} modules, {len(edges)} edges ({what} test modules), no import cycle")
    return 0


def elementary_cycles(graph):
    """Elementary cycles (Johnson's algorithm, simplified), each starting at its least node."""
    order = sorted(graph)
    index = {v: i for i, v in enumerate(order)}
    cycles = []
    for s in order:
        # cycles through s using only nodes >= s
        allowed = {v for v in order if index[v] >= index[s]}
        stack = [(s, iter(graph[s]))]
        path = [s]
        on_path = {s}
        while stack:
            v, it = stack[-1]
            nxt = next(it, None)
            if nxt is None:
                stack.pop()
                on_path.discard(path.pop())
                continue
            if nxt == s:
                cycles.append(list(path))
                if len(cycles) >= MAX_CYCLES:
                    return cycles
            elif nxt in allowed and nxt not in on_path:
                path.append(nxt)
                on_path.add(nxt)
                stack.append((nxt, iter(graph[nxt])))
    return cycles


def crate_sources():
    """Every workspace crate's `src` directory (a folder with a Cargo.toml and a src/)."""
    root = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
    out = []
    for base in ("crates", "."):
        for name in sorted(os.listdir(os.path.join(root, base))):
            crate = os.path.join(root, base, name)
            if os.path.isdir(os.path.join(crate, "src")) and os.path.isfile(
                os.path.join(crate, "Cargo.toml")
            ):
                out.append(os.path.normpath(os.path.join(crate, "src")))
    return sorted(set(out))


def workspace(argv):
    """Checks every crate; exits 1 if any has a cycle."""
    flags = [a for a in argv[1:] if a == "--with-tests"]
    failed = []
    for src in crate_sources():
        print(f"{os.path.relpath(src)}: ", end="", flush=True)
        if main([argv[0], *flags, src]) != 0:
            failed.append(src)
    if failed:
        print(f"import cycles in {len(failed)} crate(s): {', '.join(map(os.path.relpath, failed))}")
        return 1
    return 0


if __name__ == "__main__":
    if "--workspace" in sys.argv:
        sys.exit(workspace([a for a in sys.argv if a != "--workspace"]))
    sys.exit(main(sys.argv))
