#!/usr/bin/env python3
"""The layering of src/, checked from the code's own paths, and the documents that describe it checked against
the code, so that neither can drift.

From the code:
- no import cycle between files, and no module that imports from a module above it (its parent, or any
  ancestor);
- the transports stay in `server/`: no module outside it imports it or names one of the transport crates
  (TRANSPORT_CRATES), and no module outside `offline/` imports `offline/` (what the service never calls).

Against the documents:
- the module table of docs/architecture.md ("Where things are", in its layout section): every top-level module
  of src/ has a row, every row names a path of src/, and no module imports one listed below it (the table is
  bottom layer first);
- every `//!` paragraph that begins "Who imports whom": its chain `a -> b / c -> d` (top to bottom, the
  names in backquotes, `this file` for the file itself, parentheses being comments) names every child module
  of its directory once, and each child imports only from children of later layers.

Every `crate::...` and `super::...` path in code (use lines and qualified calls; comments and test modules
are left out) is resolved to the file of the deepest module it names.

Usage: python3 tools/check_imports.py [SRC_DIR]   (exit 1 with the offences listed, 0 when clean)
"""

import re
import sys
from pathlib import Path

TRANSPORT_CRATES = ("tonic", "axum", "hyper", "hyper_util", "http", "tower", "tower_http", "prost")

PATH = re.compile(r"\b(crate|super)(?=::)((?:::(?:super|[a-z_][a-z0-9_]*))*)(::\{[^;]*?\}|::[A-Z][A-Za-z0-9_]*|::\*)?", re.S)
CRATE_PATH = re.compile(r"(?<![\w:])(" + "|".join(TRANSPORT_CRATES) + r")::")


def library_modules(src):
    """Module path (tuple) of every library file; binaries (src/bin) are their own crates and left out, and so
    are test modules (`tests.rs`, `*_tests.rs`, and a module's `tests/` folder)."""
    modules = {}
    for f in src.rglob("*.rs"):
        rel = f.relative_to(src)
        if rel.parts[0] == "bin" or "tests" in rel.parts[:-1] or f.name.endswith("tests.rs") or f.name == "test_dir.rs":
            continue
        parts = list(rel.with_suffix("").parts)
        if parts[-1] in ("mod", "lib"):
            parts = parts[:-1]
        modules[tuple(parts)] = f
    return modules


def code_of(text):
    """The file's code without string contents, comments and its test modules."""
    text = re.sub(r"'(?:\\.|[^'\\])'", "' '", text)
    text = re.sub(r'"(?:\\.|[^"\\])*"', '""', text, flags=re.S)
    text = "\n".join(line.split("//")[0] for line in text.splitlines())
    return re.split(r"#\[cfg\(test\)\]\s*(?:#\[[^\]]*\]\s*)*mod \w+\s*\{", text)[0]


def resolve(modules, base, segments):
    """The deepest module named by `segments` (from `base`)."""
    path = list(base)
    for s in segments:
        if s == "super":
            path = path[:-1]
        else:
            path.append(s)
    while tuple(path) not in modules and path:
        path.pop()
    return tuple(path)


def import_edges(modules):
    """file -> the files it imports from."""
    files = {f: m for m, f in modules.items()}
    edges = {}
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
                    targets.append(resolve(modules, base, segs + names))
            else:
                targets = [resolve(modules, base, segs)]
            for t in targets:
                if t != m and t in modules:
                    out.add(modules[t])
    return edges


def layering_offences(src, modules, edges):
    """Upward imports and cycles."""
    files = {f: m for m, f in modules.items()}
    offences = []
    for f, targets in edges.items():
        m = files[f]
        for g in targets:
            t = files[g]
            if m[: len(t)] == t:
                offences.append(f"upward: {f.relative_to(src)} imports from {g.relative_to(src)} ({'::'.join(('crate',) + t)})")
    # Cycles: strongly connected components (Tarjan).
    index, low, stack, on, counter = {}, {}, [], set(), [0]

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
                offences.append("cycle: " + " <-> ".join(sorted(str(c.relative_to(src)) for c in comp)))

    sys.setrecursionlimit(10000)
    for v in list(edges):
        if v not in index:
            strong(v)
    return offences


def transport_offences(src, modules, edges):
    """Transports only in server/, and offline/ imported by no one outside it."""
    files = {f: m for m, f in modules.items()}
    offences = []
    for f, targets in edges.items():
        top = files[f][:1]
        for g in targets:
            for kept in ("server", "offline"):
                if files[g][:1] == (kept,) and top != (kept,):
                    offences.append(f"{kept}/ imported from outside it: {f.relative_to(src)} imports {g.relative_to(src)}")
        if top != ("server",):
            for crate in sorted(set(CRATE_PATH.findall(code_of(f.read_text())))):
                offences.append(f"transport outside server/: {f.relative_to(src)} uses the crate {crate}")
    return offences


TABLE_DOC = Path("docs") / "architecture.md"


def module_table(doc):
    """The first column of the "Where things are" table of docs/architecture.md, in order."""
    text = doc.read_text()
    start = text.find("**Where things are**")
    if start < 0:
        return None
    rows = []
    for line in text[start:].splitlines()[1:]:
        if rows and not line.startswith("|"):
            break
        cell = re.match(r"\|\s*`([^`]+)`\s*\|", line)
        if cell:
            rows.append(cell.group(1))
    return rows


def table_offences(src, modules, edges, doc):
    if not doc.is_file():
        return [f"{TABLE_DOC}: missing (the module table lives there)"]
    rows = module_table(doc)
    if not rows:
        return [f"{TABLE_DOC}: no module table under **Where things are**"]
    offences = []
    position = {}
    for i, row in enumerate(rows):
        path = src / row.rstrip("/")
        if not (path.is_dir() if row.endswith("/") else path.is_file()):
            offences.append(f"{TABLE_DOC} table: `{row}` is not a {'directory' if row.endswith('/') else 'file'} of src/")
        module = tuple(Path(row.rstrip("/")).with_suffix("").parts) if row.endswith(".rs") else tuple(Path(row).parts)
        if module in modules:
            position[module] = i
    for m, f in sorted(modules.items()):
        if len(m) == 1 and m not in position:
            offences.append(f"{TABLE_DOC} table: no row for the top-level module {f.relative_to(src)}")
    files = {f: m for m, f in modules.items()}
    for f, targets in edges.items():
        a = files[f][:1]
        for g in targets:
            b = files[g][:1]
            if a != b and a in position and b in position and position[b] > position[a]:
                offences.append(
                    f"{TABLE_DOC} table: `{rows[position[a]]}` imports `{rows[position[b]]}`, which the table lists below it "
                    f"({f.relative_to(src)} -> {g.relative_to(src)})"
                )
    return offences


def module_doc(text):
    """The `//!` lines at the top of a file, joined in paragraphs."""
    lines = []
    for line in text.splitlines():
        if not line.startswith("//!"):
            break
        lines.append(line[3:].strip())
    return [" ".join(p.split("\n")) for p in "\n".join(lines).split("\n\n")]


def chain_of(paragraph):
    """The layers of a "Who imports whom" chain, top to bottom, each a list of names."""
    text = re.sub(r"\]\([^)]*\)", "]", paragraph)  # link targets
    while re.search(r"\([^()]*\)", text):
        text = re.sub(r"\([^()]*\)", "", text)  # comments
    text = text.split(":", 1)[1] if ":" in text else ""
    text = re.split(r"\.(?:\s|$)", text)[0]
    return [re.findall(r"`([^`]+)`|(this file)", layer) for layer in text.split("->")]


def chain_offences(src, modules, edges):
    files = {f: m for m, f in modules.items()}
    offences = []
    for f, m in sorted(files.items()):
        for paragraph in module_doc(f.read_text()):
            at = paragraph.lower().find("who imports whom")
            if at < 0:
                continue
            paragraph = paragraph[at:]
            where = f.relative_to(src)
            children = {c[-1] for c in modules if len(c) == len(m) + 1 and c[: len(m)] == m}
            layer_of = {}
            for i, layer in enumerate(chain_of(paragraph)):
                for name, this in layer:
                    name = name or this
                    if name in layer_of:
                        offences.append(f"{where}: who imports whom names `{name}` twice")
                    elif name != "this file" and name not in children:
                        offences.append(f"{where}: who imports whom names `{name}`, which is no module of this directory")
                    layer_of[name] = i
            for c in sorted(children - set(layer_of)):
                offences.append(f"{where}: who imports whom leaves out `{c}`")

            def member(g):
                t = files[g]
                if t == m:
                    return "this file"
                return t[len(m)] if len(t) > len(m) and t[: len(m)] == m else None

            for a_file, targets in edges.items():
                a = member(a_file)
                for g in targets:
                    b = member(g)
                    if a is None or b is None or a == b or a not in layer_of or b not in layer_of:
                        continue
                    if layer_of[b] <= layer_of[a]:
                        offences.append(
                            f"{where}: who imports whom puts `{b}` {'beside' if layer_of[a] == layer_of[b] else 'above'} "
                            f"`{a}`, which imports it ({a_file.relative_to(src)} -> {g.relative_to(src)})"
                        )
    return offences


def main():
    src = Path(sys.argv[1] if len(sys.argv) > 1 else Path(__file__).resolve().parent.parent / "src")
    modules = library_modules(src)
    edges = import_edges(modules)
    offences = (
        layering_offences(src, modules, edges)
        + transport_offences(src, modules, edges)
        + table_offences(src, modules, edges, src.parent / TABLE_DOC)
        + chain_offences(src, modules, edges)
    )
    for o in sorted(set(offences)):
        print(o)
    print(f"{len(modules)} files, {sum(len(e) for e in edges.values())} imports between them: "
          f"{len(set(offences))} offences")
    return 1 if offences else 0


if __name__ == "__main__":
    sys.exit(main())
