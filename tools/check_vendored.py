#!/usr/bin/env python3
"""third_party/hnsw_rs is hnsw_rs 0.3.5 as published on crates.io with docs/patches/hnsw_rs-0.3.5-reload.patch
applied, and nothing else (third_party/hnsw_rs/PATCHED.md).

Takes the published crate from cargo's download cache, or else from crates.io (the registry cargo itself
downloads from), checks it against the checksum Cargo.lock pinned before the patch, applies the patch with
`git apply` and compares every vendored file. Exit 1 with the differences listed, 0 when they agree.

Usage: python3 tools/check_vendored.py
"""

import filecmp
import hashlib
import io
import os
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
        extra = [str(f.relative_to(vendored)) for f in (vendored / "src").rglob("*") if f.is_file()
                 and not (upstream / f.relative_to(vendored)).is_file()]
    for w in wrong:
        print(f"third_party/hnsw_rs/{w}: not the published file with the patch applied")
    for e in extra:
        print(f"third_party/hnsw_rs/{e}: not in the published crate")
    if wrong or extra:
        return 1
    print(f"third_party/hnsw_rs: {CRATE} as published, with docs/patches/{CRATE}-reload.patch")
    return 0


if __name__ == "__main__":
    sys.exit(main())
