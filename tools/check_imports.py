#!/usr/bin/env python3
"""The layering of src/, checked from the code's own paths: no import cycle between files, and no module that
imports from a module above it (its parent, or any ancestor).

Every `crate::...` and `super::...` path in code (use lines and qualified calls; comments and test modules
are left out) is resolved to the file of the deepest module it names. An edge from a file to one of its
ancestors is an upward import; a cycle is a strongly connected set of more than one file.

Usage: python3 tools/check_imports.py [SRC_DIR]   (exit 1 with the offences listed, 0 when clean)
"""

import re
import sys
from pathlib import Path

src = Path(sys.argv[1] if len(sys.argv) > 1 else Path(__file__).resolve().parent.parent / "src")

# Module path (tuple) of every library file; binaries (src/bin) are their own crates and left out.
modules = {}
for f in src.rglob("*.rs"):
    rel = f.relative_to(src)
    if rel.parts[0] == "bin" or f.name.endswith("tests.rs") or f.name == "test_dir.rs":
        continue
    parts = list(rel.with_suffix("").parts)
    if parts[-1] in ("mod", "lib"):
        parts = parts[:-1]
    modules[tuple(parts)] = f
files = {f: m for m, f in modules.items()}

PATH = re.compile(r"\b(crate|super)(?=::)((?:::(?:super|[a-z_][a-z0-9_]*))*)(::\{[^;]*?\}|::[A-Z][A-Za-z0-9_]*|::\*)?", re.S)


def code_of(text):
    """The file's code without string contents, comments and its test modules."""
    text = re.sub(r"'(?:\\.|[^'\\])'", "' '", text)
    text = re.sub(r'"(?:\\.|[^"\\])*"', '""', text, flags=re.S)
    text = "\n".join(line.split("//")[0] for line in text.splitlines())
    return re.split(r"#\[cfg\(test\)\]\s*(?:#\[[^\]]*\]\s*)*mod \w+\s*\{", text)[0]


def resolve(base, segments):
    """The deepest module named by `segments` (from `base`), and whether more follows it."""
    path = list(base)
    for s in segments:
        if s == "super":
            path = path[:-1]
        else:
            path.append(s)
    while tuple(path) not in modules and path:
        path.pop()
    return tuple(path)


edges = {}
offences = []
for f, m in files.items():
    code = code_of(f.read_text())
    out = edges.setdefault(f, set())
    for root, segs, tail in PATH.findall(code):
        segs = [s for s in segs.split("::") if s]
        base = () if root == "crate" else m[:-1] if f.name not in ("mod.rs", "lib.rs") else m
        if root == "super":
            base = m[:-1]
        if tail.startswith("::{"):
            # use a::b::{c, d::e, F}: each entry is a module below the prefix, or an item of it (or of one)
            targets = []
            for entry in tail[3:-1].split(","):
                names = [s for s in entry.strip().split(" as ")[0].split("::") if s and s not in ("self", "*")]
                targets.append(resolve(base, segs + names))
        else:
            targets = [resolve(base, segs)]
        for t in targets:
            if t == m or t not in modules:
                continue
            out.add(modules[t])
            if m[: len(t)] == t:
                offences.append(f"upward: {f.relative_to(src)} imports from {modules[t].relative_to(src)} ({'::'.join(('crate',) + t)})")

# Cycles: strongly connected components (Tarjan).
index, low, stack, on, sccs, counter = {}, {}, [], set(), [], [0]


def strong(v):
    index[v] = low[v] = counter[0]
    counter[0] += 1
    stack.append(v)
    on.add(v)
    for w in edges.get(v, ()):
        if w not in index:
            strong(w)
            low[v] = min(low[v], low[w])
        elif w in on:
            low[v] = min(low[v], index[w])
    if low[v] == index[v]:
        comp = []
        while True:
            w = stack.pop()
            on.discard(w)
            comp.append(w)
            if w == v:
                break
        if len(comp) > 1:
            sccs.append(comp)


sys.setrecursionlimit(10000)
for v in list(edges):
    if v not in index:
        strong(v)
for comp in sccs:
    offences.append("cycle: " + " <-> ".join(sorted(str(c.relative_to(src)) for c in comp)))

for o in sorted(set(offences)):
    print(o)
print(f"{len(files)} files, {sum(len(e) for e in edges.values())} imports between them: "
      f"{len(set(offences))} offences")
sys.exit(1 if offences else 0)
