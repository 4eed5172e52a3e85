"""Regenerate (or check) the tables of the docs that come from committed result files.

    python scripts/doc_tables.py          # rewrite every generated table in README.md and docs/*.md
    python scripts/doc_tables.py --check  # exit 1, naming each stale table, if any differs

A generated table sits between two comment lines that say how it is made:

    <!-- table: stream_results table docs/results/stream/stream-fast-s11.json ... -->
    | ... the table as the command prints it ... |
    <!-- /table -->

The first word after ``table:`` is the script (``stream_results`` or ``clustering_tables``), the
second its table kind, the rest its files (globs allowed, sorted). Paths are relative to the
repository root.
"""

from __future__ import annotations

import argparse
import contextlib
import glob
import importlib.util
import io
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OPEN = re.compile(r"^<!-- table: (?P<spec>.+?) -->$")
CLOSE = "<!-- /table -->"
TABLES = {"stream_results": ("table",), "clustering_tables": ("features", "distances", "assign", "ablate")}


def _script(name: str):
    spec = importlib.util.spec_from_file_location(f"_doc_{name}", ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def render(spec: str) -> str:
    """The table that ``spec`` (script, kind, files) prints."""
    words = spec.split()
    if len(words) < 3 or words[0] not in TABLES or words[1] not in TABLES[words[0]]:
        raise ValueError(f"bad table spec {spec!r}: want '<script> <kind> FILE...' with script/kind in {TABLES}")
    files: list[str] = []
    for pattern in words[2:]:
        found = sorted(glob.glob(str(ROOT / pattern)))
        if not found:
            raise FileNotFoundError(f"table spec {spec!r}: no file matches {pattern!r}")
        files += found
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        getattr(_script(words[0]), words[1])(files)
    return out.getvalue()


def regenerate(text: str, where: str = "") -> str:
    """``text`` with every generated table replaced by what its spec prints now."""
    lines, out, i = text.splitlines(keepends=True), [], 0
    while i < len(lines):
        m = OPEN.match(lines[i].rstrip("\n"))
        out.append(lines[i])
        i += 1
        if m is None:
            continue
        start = i
        while i < len(lines) and lines[i].rstrip("\n") != CLOSE:
            i += 1
        if i == len(lines):
            raise ValueError(f"{where}:{start}: table without its closing '{CLOSE}'")
        out.append(render(m.group("spec")))
        out.append(lines[i])
        i += 1
    return "".join(out)


def documents() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="change nothing; exit 1 if a table is stale")
    args = p.parse_args(argv)
    stale = []
    for path in documents():
        text = path.read_text()
        new = regenerate(text, str(path.relative_to(ROOT)))
        if new != text:
            stale.append(str(path.relative_to(ROOT)))
            if not args.check:
                path.write_text(new)
    verb = "stale" if args.check else "rewrote"
    for name in stale:
        print(f"{verb}: {name}")
    return 1 if (args.check and stale) else 0


if __name__ == "__main__":
    sys.exit(main())
