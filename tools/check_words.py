#!/usr/bin/env python3
"""Product text says what a thing does and why, not when it was made; and the paths it names exist.

Product text is what a user or a newcomer reads:
- Markdown: README.md, BENCHMARKS.md, docs/**/*.md (except the lab notebook docs/model-experiments.md and
  docs/history/**), load-tests/README.md, deploy/**/README.md, clients/python/README*, and the model cards
  models/*.md (a card's section headed "Training record ...", down to the next heading of its level or above,
  is its record and is left out of the words check);
- the client contract: proto/**/*.proto, every line;
- what rustdoc and `--help` print: in src/**/*.rs, every doc comment (`///`, `//!`; on clap's structs these
  are the help text) and every `help = "..."`, `about = "..."` (and long_/after_/before_ variants) string.
Plain `//` comments and code are not product text.

1. The words check: no product text tells its own history. The tracker's issues, the working sessions and the
   notebook's rounds are how this repository writes history, so these are offences (case-insensitive):
   - one of the words with a number: `session 7`, `sessions 48-49`, `issue 39`, `issue #16`, `issues 25 and
     29`, `round 2's`, `rounds 3-16` (not when the word is part of a flag, an environment variable or a path:
     `--sessions 2`, `SCONE_MODEL__SESSIONS`, `docs/results/issue39/` are left alone);
   - the tracker's issue without a number: `issue's`, and `the / this / that / its / earlier / later /
     previous / next / same issue(s)` (not `the issue tracker`);
   - a working session without a number: `this / that / earlier / later / previous / past / next / last /
     quiet / whole session(s)`.
   Left alone, because the product uses them for what they say: an ONNX Runtime session (`a session of its
   own`, `two sessions`, `idle session`), `round trip`, `round-robin`, `rounding`, `round()`, and a number of
   measurement rounds written number first (`20 rounds`). A word and its number split over two lines are
   still found (each line is read with the first words of the next).
2. The doc-path check: every repository path that product text names exists in the working tree. A path is a
   Markdown link's relative target (resolved from the file's folder), or a word in backquotes or in plain text
   that starts with one of the top-level folders (TOP_DIRS) and a `/`, or is a top-level file (TOP_FILES); in
   plain text it counts only when it ends in a file extension or a `/` (so that prose such as
   "training/validation" is not read as a path). Placeholders are skipped (a word with `<`, `*`, `{`, `$`,
   `...`, `NNN`), and so are a trailing `:LINE` and `#anchor`. A path outside the root's folders is accepted
   when it exists relative to the file's own folder (deploy/README.md naming `tools/...` of deploy/).

Usage: python3 tools/check_words.py [ROOT]     (exit 1 with each offence as path:line: text, 0 when clean)
       python3 tools/check_words.py --self-test (plants one offence of each kind in a temporary tree and
                                                 checks that each is reported and that the clean tree passes)
"""

import re
import subprocess
import sys
import tempfile
from pathlib import Path

TOP_DIRS = ("src", "docs", "tests", "scripts", "tools", "training", "models", "proto", "deploy", "load-tests",
            "clients", "benches", "ui", "fuzz", "third_party")
TOP_FILES = ("README.md", "BENCHMARKS.md", "Cargo.toml", "Cargo.lock", "build.rs", "deny.toml", "rustfmt.toml")

NOT_IN_A_NAME = r"(?<![\w./$-])"
HISTORY = [
    (re.compile(NOT_IN_A_NAME + r"(?:sessions?|issues?|rounds?)[ \t]+#?\d+", re.I),
     "a session, issue or round by number"),
    (re.compile(r"\bissue's\b", re.I), "the tracker's issue"),
    (re.compile(r"\b(?:the|this|that|its|earlier|later|previous|next|same)[ \t]+issues?\b(?![ \t]+tracker)", re.I),
     "the tracker's issue"),
    (re.compile(r"\b(?:this|that|earlier|later|previous|past|next|last|quiet|whole)[ \t]+sessions?\b", re.I),
     "a working session"),
]

DOC_LINE = re.compile(r"^\s*//(?:/(?!/)|!)(.*)$")
HELP_STRING = re.compile(
    r"\b(?:long_|after_|after_long_|before_|before_long_)?(?:help|about)\s*=\s*\"((?:[^\"\\]|\\.)*)\"")
DOC_ATTR = re.compile(r"#\[doc\s*=\s*\"((?:[^\"\\]|\\.)*)\"")
HEADING = re.compile(r"^(#{1,6})\s+(.*)$")
RECORD_HEADING = re.compile(r"^training record\b", re.I)

BACKQUOTED = re.compile(r"`([^`]+)`")
MD_LINK = re.compile(r"\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
BARE = re.compile(r"(?<![\w/.$~@:-])((?:" + "|".join(re.escape(d) for d in TOP_DIRS) + r")/[\w./@+-]*)")
PLACEHOLDER = re.compile(r"[<*{$]|\.\.\.|NNN")


def product_files(root):
    """(path, kind) of every file of product text; kind is 'md', 'card', 'proto' or 'rs'."""
    out = []
    for name in ("README.md", "BENCHMARKS.md", "load-tests/README.md"):
        if (root / name).is_file():
            out.append((root / name, "md"))
    docs = root / "docs"
    for f in sorted(docs.rglob("*.md")) if docs.is_dir() else []:
        rel = f.relative_to(docs)
        if rel.parts[0] == "history" or rel.as_posix() == "model-experiments.md":
            continue
        out.append((f, "md"))
    for pattern, base in (("README*.md", "deploy"), ("README*", "clients/python")):
        if (root / base).is_dir():
            out += [(f, "md") for f in sorted((root / base).rglob(pattern)) if f.is_file()]
    if (root / "models").is_dir():
        out += [(f, "card") for f in sorted((root / "models").glob("*.md"))]
    if (root / "proto").is_dir():
        out += [(f, "proto") for f in sorted((root / "proto").rglob("*.proto"))]
    if (root / "src").is_dir():
        out += [(f, "rs") for f in sorted((root / "src").rglob("*.rs"))]
    return out


def text_lines(path, kind):
    """(line number, text, checked for words) of the product text of one file."""
    lines = path.read_text(encoding="utf-8").splitlines()
    if kind == "rs":
        out = []
        for n, line in enumerate(lines, 1):
            m = DOC_LINE.match(line)
            if m:
                out.append((n, m.group(1), True))
                continue
            for m in list(HELP_STRING.finditer(line)) + list(DOC_ATTR.finditer(line)):
                out.append((n, m.group(1), True))
        return out
    if kind == "card":
        out, record_level = [], None
        for n, line in enumerate(lines, 1):
            h = HEADING.match(line)
            if h:
                level = len(h.group(1))
                if record_level is not None and level <= record_level:
                    record_level = None
                if record_level is None and RECORD_HEADING.match(h.group(2)):
                    record_level = level
            out.append((n, line, record_level is None))
        return out
    return [(n, line, True) for n, line in enumerate(lines, 1)]


def word_offences(rel, entries):
    out = []
    for i, (n, text, checked) in enumerate(entries):
        if not checked:
            continue
        # The first words of the next line, so that a word and its number split by a line break are found.
        joined = text
        if i + 1 < len(entries) and entries[i + 1][0] == n + 1 and entries[i + 1][2]:
            joined += " " + " ".join(entries[i + 1][1].split()[:2])
        for pattern, what in HISTORY:
            for m in pattern.finditer(joined):
                if m.start() < len(text):
                    out.append(f"{rel}:{n}: {what}: \"{m.group(0)}\" in: {text.strip()}")
                    break
    return out


def clean_path(word):
    word = word.strip().rstrip(".,;:)'\"")
    if word.endswith("'s"):
        word = word[:-2]
    word = re.sub(r"#.*$", "", word)
    word = re.sub(r":\d+(?:-\d+)?$", "", word)
    return word.rstrip(".,;:)'\"")


def is_repo_path(word, bare):
    if not word or PLACEHOLDER.search(word):
        return False
    if word in TOP_FILES:
        return True
    top, slash, rest = word.partition("/")
    if top not in TOP_DIRS or not slash:
        return False
    if bare:
        return word.endswith("/") or re.search(r"\.\w+$", rest.rsplit("/", 1)[-1]) is not None
    return True


def path_offences(root, path, rel, entries, rust):
    """(offence, path) of every path this file names that does not exist."""
    missing, seen = [], set()

    def check(n, word, base):
        if (n, word) in seen:
            return
        seen.add((n, word))
        if not (root / word).exists() and not (base / word).exists():
            missing.append((f"{rel}:{n}: names `{word}`, which does not exist", root / word))

    for n, text, _ in entries:
        for m in MD_LINK.finditer(text):
            target = m.group(1)
            if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I) or target.startswith("#"):
                continue
            target = re.sub(r"#.*$", "", target)
            if rust:
                # rustdoc's links name items (`crate::x`, `mod@format`); a repository path is checked as one.
                if is_repo_path(clean_path(target), bare=False):
                    check(n, clean_path(target), path.parent)
            elif target and not PLACEHOLDER.search(target):
                if not (path.parent / target).exists():
                    missing.append((f"{rel}:{n}: links to `{target}`, which does not exist", path.parent / target))
                seen.add((n, target))
        spans = BACKQUOTED.findall(text)
        for span in spans:
            for word in span.split():
                word = clean_path(word)
                if is_repo_path(word, bare=False):
                    check(n, word, path.parent)
        plain = BACKQUOTED.sub(" ", MD_LINK.sub(" ", text))
        for m in BARE.finditer(plain):
            word = clean_path(m.group(1))
            if is_repo_path(word, bare=True):
                check(n, word, path.parent)
    return missing


def git_ignored(root, paths):
    """The paths git ignores (a file the reader makes, such as `deploy/keys`); none outside a git work tree."""
    if not paths:
        return set()
    try:
        done = subprocess.run(["git", "-C", str(root), "check-ignore", "--stdin"], input="\n".join(map(str, paths)),
                              capture_output=True, text=True, check=False)
    except OSError:
        return set()
    return {Path(line) for line in done.stdout.splitlines()} if done.returncode in (0, 1) else set()


def check(root):
    offences, missing = [], []
    for path, kind in product_files(root):
        rel = path.relative_to(root).as_posix()
        entries = text_lines(path, kind)
        offences += word_offences(rel, entries)
        missing += path_offences(root, path, rel, entries, kind == "rs")
    ignored = git_ignored(root, [p for _, p in missing])
    return offences + [o for o, p in missing if p not in ignored]


PLANTED = {
    "README.md": "# Demo\n\nIt matches images (`src/lib.rs`, [docs](docs/guide.md)). Added in session 12.\n"
                 "The tests are in `tests/gone.rs`.\n",
    "docs/guide.md": "# Guide\n\nOne ONNX Runtime session per worker; a write is one round trip; rounding is half\n"
                     "up. See [the readme](../README.md) and [a page](missing.md). The rule of issue\n"
                     "27 holds.\n",
    "docs/model-experiments.md": "# Notebook\n\nRound 3 of issue 39 (session 41), `docs/nowhere.md`.\n",
    "docs/history/old.md": "# Old\n\nSession 7 chose rerank.\n",
    "docs/results/issue39/summary.md": "# Summary\n\nThe ring context, measured.\n",
    "proto/demo/v1/demo.proto": "syntax = \"proto3\";\n// Revision 3 (issue 39) adds step 9.\nmessage A {}\n",
    "models/card.md": "# Card\n\nShipped by the issue's rule.\n\n## Training record\n\nSession 36 kept it.\n\n"
                      "### Its first run\n\nRound 2.\n\n## Input contract\n\nChosen in round 2.\n",
    "src/lib.rs": "//! Matching (issue 25: zoom).\n//! Reads `src/gone.rs` and `src/lib.rs`.\n"
                  "// session 3 is a plain comment\n"
                  "/// Embeds on this session alone.\npub fn f() -> &'static str { \"round 4\" }\n"
                  "/// A pool of `--sessions 2` sessions (`SCONE_MODEL__SESSIONS`), `docs/results/issue39/`.\n"
                  "pub fn g() {}\n"
                  "/// Stored as [the format](mod@format), see [the code](src/gone.rs).\npub fn h() {}\n",
    "deploy/README.md": "# Deploy\n\nRun `tools/validate.sh` of this folder.\n",
    "deploy/tools/validate.sh": "#!/bin/sh\n",
    "src/bin/demo.rs": "#[derive(clap::Parser)]\n#[command(about = \"Demo, as of round 5\")]\n"
                       "struct A {\n    /// Window, chosen in sessions 48-49.\n"
                       "    #[arg(long, help = \"ratio of issue #16\")]\n    r: f32,\n}\n",
}

EXPECTED = {
    ("README.md", 3, "session"), ("README.md", 4, "path"),
    ("docs/guide.md", 4, "path"), ("docs/guide.md", 4, "issue"),
    ("proto/demo/v1/demo.proto", 2, "issue"),
    ("models/card.md", 3, "issue"), ("models/card.md", 15, "round"),
    ("src/lib.rs", 1, "issue"), ("src/lib.rs", 2, "path"), ("src/lib.rs", 4, "session"), ("src/lib.rs", 8, "path"),
    ("src/bin/demo.rs", 2, "round"), ("src/bin/demo.rs", 4, "session"), ("src/bin/demo.rs", 5, "issue"),
}

CLEAN = {
    "README.md": "# Demo\n\nIt matches images (`src/lib.rs`, [docs](docs/guide.md)).\n",
    "docs/guide.md": "# Guide\n\nOne ONNX Runtime session per worker; a write is one round trip; rounding is half\n"
                     "up, over 20 rounds, around 20 centres. See [the readme](../README.md).\n",
    "proto/demo/v1/demo.proto": "syntax = \"proto3\";\n// Revision 3 adds step 9.\nmessage A {}\n",
    "models/card.md": "# Card\n\nShipped by its rule.\n\n## Training record\n\nSession 36 kept it.\n",
    "src/lib.rs": "//! Matching under zoom.\n// session 3 is a plain comment\n"
                  "/// A session of its own, idle sessions.\npub fn f() -> &'static str { \"round 4\" }\n",
    "src/bin/demo.rs": "#[derive(clap::Parser)]\n#[command(about = \"Demo\")]\n"
                       "struct A {\n    /// Window.\n    #[arg(long, help = \"ratio\")]\n    r: f32,\n}\n",
}


def kind_of(offence):
    if "does not exist" in offence:
        return "path"
    quoted = offence.split('"')[1].lower()
    return next(w for w in ("session", "issue", "round") if w in quoted)


def write_tree(root, files):
    for name, text in files.items():
        f = root / name
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text(text, encoding="utf-8")


def self_test():
    failures = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        write_tree(root, PLANTED)
        found = check(root)
        got = {(o.split(":")[0], int(o.split(":")[1]), kind_of(o)) for o in found}
        for missing in sorted(EXPECTED - got):
            failures.append(f"planted offence not reported: {missing}")
        for extra in sorted(got - EXPECTED):
            failures.append(f"reported but not planted: {extra}: {[o for o in found if o.startswith(extra[0])]}")
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        write_tree(root, CLEAN)
        for o in check(root):
            failures.append(f"clean tree reported: {o}")
    for f in failures:
        print(f)
    print(f"self-test: {len(EXPECTED)} planted offences, {len(failures)} failures")
    return 1 if failures else 0


def main():
    args = sys.argv[1:]
    if args == ["--self-test"]:
        return self_test()
    root = Path(args[0] if args else Path(__file__).resolve().parent.parent)
    offences = check(root)
    for o in offences:
        print(o)
    files = len(product_files(root))
    print(f"{files} files of product text: {len(offences)} offences (history words, or paths that do not exist)")
    return 1 if offences else 0


if __name__ == "__main__":
    sys.exit(main())
