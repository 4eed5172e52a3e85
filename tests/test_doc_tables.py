"""The docs' generated tables equal what their committed result files print (scripts/doc_tables.py)."""

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SPEC = "clustering_tables features docs/results/clustering/features-tune-s10-batch8.jsonl"


@pytest.fixture(scope="module")
def doc_tables():
    spec = importlib.util.spec_from_file_location("doc_tables", ROOT / "scripts" / "doc_tables.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_generated_table_in_the_docs_is_current(doc_tables, capsys):
    assert doc_tables.main(["--check"]) == 0, capsys.readouterr().out


def test_a_stale_table_is_rewritten_and_the_text_around_it_kept(doc_tables):
    text = f"before\n<!-- table: {SPEC} -->\n| old | table |\n<!-- /table -->\nafter\n"
    new = doc_tables.regenerate(text)
    table = doc_tables.render(SPEC)
    assert new == f"before\n<!-- table: {SPEC} -->\n{table}<!-- /table -->\nafter\n"
    assert table.startswith("| env steps | own: separation / correct") and "| 36,000 |" in table
    assert doc_tables.regenerate(new) == new


def test_bad_table_specs_are_named(doc_tables):
    with pytest.raises(ValueError, match="without its closing"):
        doc_tables.regenerate(f"<!-- table: {SPEC} -->\n| x |\n")
    with pytest.raises(ValueError, match="bad table spec"):
        doc_tables.render("clustering_tables nonsense docs/results/clustering/features-tune-s10-batch8.jsonl")
    with pytest.raises(FileNotFoundError, match="no file matches"):
        doc_tables.render("stream_results table docs/results/stream/no-such-run.json")
