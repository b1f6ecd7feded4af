#!/usr/bin/env python3
"""third_party/hnsw_rs is hnsw_rs 0.3.5 as published on crates.io with docs/patches/hnsw_rs-0.3.5-reload.patch
applied, and nothing else (third_party/hnsw_rs/PATCHED.md).

Takes the published crate from cargo's download cache, or else from crates.io (the registry cargo itself
downloads from; with the `[patch]` in place cargo no longer fetches it, so a fresh machine downloads it here),
checks it against the checksum Cargo.lock pinned before the patch, applies the patch with `git apply` and
compares every vendored file: `src/`, the licences and notes, and `Cargo.toml` (the published one without its
example, test and bench targets and dev-dependencies, which are not vendored). Nothing else may be there but
PATCHED.md. Exit 1 with the differences listed, 0 when they agree.

Usage: python3 tools/check_vendored.py
"""

import filecmp
import hashlib
import io
import os
import re
import subprocess
import sys
import tarfile
import tempfile
import urllib.request
from pathlib import Path

CRATE = "hnsw_rs-0.3.5"
SHA256 = "c9b4dcb9840006fae9964e97dfdb354cd00b7a15d69d143caae7eeca0410af9f"
URL = f"https://static.crates.io/crates/hnsw_rs/{CRATE}.crate"
COPIED = ("LICENSE-APACHE", "LICENSE-MIT", "README.md", "Changes.md")
ROOT_ENTRIES = {"src", "Cargo.toml", "PATCHED.md", *COPIED}


def vendored_manifest(published_toml: str) -> str:
    """The published Cargo.toml without the sections of what is not vendored."""
    sections = re.split(r"(?m)^(?=\[)", published_toml)
    return "".join(p for p in sections if not re.match(r"\[\[(example|test|bench)\]\]|\[dev-dependencies", p))


def published() -> bytes:
    cache = Path(os.environ.get("CARGO_HOME", Path.home() / ".cargo")) / "registry" / "cache"
    for f in sorted(cache.glob(f"*/{CRATE}.crate")):
        return f.read_bytes()
    with urllib.request.urlopen(URL, timeout=60) as r:
        return r.read()


def main() -> int:
    root = Path(__file__).resolve().parent.parent
    vendored = root / "third_party" / "hnsw_rs"
    data = published()
    if hashlib.sha256(data).hexdigest() != SHA256:
        print(f"check_vendored: {CRATE}.crate does not have the checksum Cargo.lock pinned")
        return 1
    with tempfile.TemporaryDirectory() as tmp:
        with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as t:
            # The archive's checksum was checked above; the filter argument is missing on older 3.11 builds.
            if hasattr(tarfile, "data_filter"):
                t.extractall(tmp, filter="data")
            else:
                t.extractall(tmp)
        upstream = Path(tmp) / CRATE
        patch = root / "docs" / "patches" / f"{CRATE}-reload.patch"
        subprocess.run(["git", "apply", "-p1", str(patch)], cwd=upstream, check=True)
        wrong = []
        for f in sorted((upstream / "src").rglob("*")) + [upstream / n for n in COPIED]:
            if f.is_file():
                rel = f.relative_to(upstream)
                mine = vendored / rel
                if not mine.is_file() or not filecmp.cmp(f, mine, shallow=False):
                    wrong.append(str(rel))
        if vendored_manifest((upstream / "Cargo.toml").read_text()) != (vendored / "Cargo.toml").read_text():
            wrong.append("Cargo.toml")
        extra = [str(f.relative_to(vendored)) for f in (vendored / "src").rglob("*") if f.is_file()
                 and not (upstream / f.relative_to(vendored)).is_file()]
        extra += [e.name for e in vendored.iterdir() if e.name not in ROOT_ENTRIES]
    for w in wrong:
        print(f"third_party/hnsw_rs/{w}: not the published file (with the patch, or without the unvendored sections)")
    for e in extra:
        print(f"third_party/hnsw_rs/{e}: not in the published crate, or not vendored")
    if wrong or extra:
        return 1
    print(f"third_party/hnsw_rs: {CRATE} as published, with docs/patches/{CRATE}-reload.patch")
    return 0


if __name__ == "__main__":
    sys.exit(main())
