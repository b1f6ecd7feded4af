#!/usr/bin/env python3
"""The size of the house: no Rust file grows past what a reader takes in at once.

- source files (src/ and benches/): at most SOURCE_LINES lines;
- test files (tests/, and the test modules of src/: a file declared under `#[cfg(test)]`, or named
  `tests.rs` / `*_tests.rs`): at most TEST_LINES lines.

A file over its limit is split by what its code does (a group of operations, a stage, the tables of a report),
not cut at a line number.

Usage: python3 tools/check_sizes.py [ROOT]   (exit 1 with the offenders and their counts listed, 0 when clean)
"""

import re
import sys
from pathlib import Path

SOURCE_LINES = 700
TEST_LINES = 900

TEST_MODULE = re.compile(r"#\[cfg\(test\)\]\s*(?:#\[[^\]]*\]\s*)*(?:pub(?:\([^)]*\))?\s+)?mod\s+(\w+)\s*;")


def test_modules(src):
    """The files of src/ that a `#[cfg(test)] mod name;` declares."""
    out = set()
    for f in src.rglob("*.rs"):
        # A file's child modules live beside it (lib.rs, main.rs, mod.rs) or in the folder named after it.
        folder = f.parent if f.name in ("lib.rs", "main.rs", "mod.rs") else f.with_suffix("")
        for name in TEST_MODULE.findall(f.read_text()):
            for child in (folder / f"{name}.rs", folder / name / "mod.rs"):
                if child.is_file():
                    out.add(child)
    return out


def is_test_file(f, root, tests_of_src):
    rel = f.relative_to(root)
    return rel.parts[0] == "tests" or f in tests_of_src or f.name == "tests.rs" or f.name.endswith("_tests.rs")


def main():
    root = Path(sys.argv[1] if len(sys.argv) > 1 else Path(__file__).resolve().parent.parent)
    tests_of_src = test_modules(root / "src")
    offenders, checked = [], 0
    for top in ("src", "benches", "tests"):
        for f in sorted((root / top).rglob("*.rs")):
            checked += 1
            lines = len(f.read_text().splitlines())
            test = is_test_file(f, root, tests_of_src)
            limit = TEST_LINES if test else SOURCE_LINES
            if lines > limit:
                kind = "test file" if test else "source file"
                offenders.append(f"{f.relative_to(root)}: {lines} lines (a {kind} holds at most {limit})")
    for o in offenders:
        print(o)
    print(f"{checked} files: {len(offenders)} over their limit ({SOURCE_LINES} lines of source, {TEST_LINES} of tests)")
    return 1 if offenders else 0


if __name__ == "__main__":
    sys.exit(main())
