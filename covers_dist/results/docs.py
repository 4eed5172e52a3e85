"""The generated parts of the docs: result tables between markers, and docs/guide/configuration.md.

A generated table sits between two comment lines that say how it is made::

    <!-- table: stream docs/results/stream/*.json -->
    | ... the table as :mod:`~covers_dist.results.tables` makes it ... |
    <!-- /table -->

The first word after ``table:`` is the table kind (:data:`~covers_dist.results.tables.KINDS`),
the rest its files (globs, sorted), relative to the repository root. docs/guide/configuration.md is
written whole from the config's own field docs (:func:`covers_dist.config.reference`).
"""

from __future__ import annotations

import glob
import re
from pathlib import Path

from ..config import Config, reference
from .summary import ResultError
from .tables import KINDS

OPEN = re.compile(r"^<!-- table: (?P<spec>.+?) -->$")
CLOSE = "<!-- /table -->"
CONFIG_REFERENCE = "docs/guide/configuration.md"


def render(spec: str, root: str | Path) -> str:
    """The table that ``spec`` (kind, files) makes, files relative to ``root``."""
    words = spec.split()
    if len(words) < 2 or words[0] not in KINDS:
        raise ResultError(f"bad table spec {spec!r}: want '<kind> FILE...' with kind one of {sorted(KINDS)}")
    files: list[str] = []
    for pattern in words[1:]:
        found = sorted(glob.glob(str(Path(root) / pattern)))
        if not found:
            raise ResultError(f"table spec {spec!r}: no file matches {pattern!r}")
        files += found
    return KINDS[words[0]](files)


def regenerate(text: str, root: str | Path, where: str = "") -> str:
    """``text`` with every generated table replaced by what its spec makes now."""
    lines, out, i = text.splitlines(keepends=True), [], 0
    while i < len(lines):
        m = OPEN.match(lines[i].rstrip("\n"))
        out.append(lines[i])
        i += 1
        if m is None:
            continue
        start = i
        while i < len(lines) and lines[i].rstrip("\n") != CLOSE:
            if OPEN.match(lines[i].rstrip("\n")):
                break
            i += 1
        if i == len(lines) or lines[i].rstrip("\n") != CLOSE:
            raise ResultError(f"{where}:{start}: table without its closing '{CLOSE}'")
        out.append(render(m.group("spec"), root))
        out.append(lines[i])
        i += 1
    return "".join(out)


def _code(text: str) -> str:
    """``text`` as inline code in a table cell (pipes escaped)."""
    return "`" + text.replace("|", "\\|") + "`"


def configuration_reference() -> str:
    """docs/guide/configuration.md: every config key with its type, default, range and meaning."""
    rows = reference(Config)
    sections: dict[str, list[dict]] = {}
    for r in rows:
        sections.setdefault(r["name"].split(".")[0] if "." in r["name"] else "", []).append(r)
    out = [
        "# Configuration reference",
        "",
        "Every key of the config, with its type, default, the range that loading checks and what it",
        "does. Generated from the field docs in `covers_dist/config.py` by `covers-dist results`; do",
        "not edit by hand. A config file sets any of these (`base: NAME` builds on another file), and",
        "`--set section.key=value` overrides one from the command line (the value is parsed as YAML).",
        "`covers-dist config --config NAME` prints a config resolved; [usage.md](usage.md) shows how to",
        "use them.",
        "",
    ]
    for section, fields in sections.items():
        out += [f"## `{section}`" if section else "## Top level", ""]
        out += ["| key | type | default | range | meaning |", "|---|---|---|---|---|"]
        for r in fields:
            doc = " ".join(str(r["doc"]).split()).replace("|", "\\|")
            out.append(f"| `{r['name']}` | {_code(r['type'])} | {_code(repr(r['default']))} | {r['range']} | {doc} |")
        out.append("")
    return "\n".join(out)


def documents(root: str | Path) -> list[Path]:
    root = Path(root)
    return [root / "README.md", *sorted((root / "docs").rglob("*.md"))]


def update(root: str | Path, check: bool = False) -> list[str]:
    """Rewrite (or with ``check``, only compare) every generated part under ``root``; the
    repository-relative paths that were (or would be) changed."""
    root = Path(root)
    if not (root / "README.md").exists() or not (root / "docs").is_dir():
        raise ResultError(f"{root}: not a covers-dist checkout (no README.md and docs/)")
    changed = []
    wanted = {root / CONFIG_REFERENCE: configuration_reference()}
    for path in documents(root):
        if path in wanted:
            continue
        text = path.read_text()
        wanted[path] = regenerate(text, root, str(path.relative_to(root)))
    for path, new in wanted.items():
        old = path.read_text() if path.exists() else None
        if new != old:
            changed.append(str(path.relative_to(root)))
            if not check:
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(new)
    return sorted(changed)
