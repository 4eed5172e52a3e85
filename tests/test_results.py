"""`covers-dist results`: a run's result file, the docs' tables from such files, the generated
configuration reference, and the provenance a run records."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from covers_dist.cli import main
from covers_dist.config import describe, load_config
from covers_dist.results import ResultError, configuration_reference, read_starts, regenerate, render, summarize
from covers_dist.runtime.driver import Trainer

ROOT = Path(__file__).resolve().parents[1]
SPEC = "features docs/results/clustering/features-tune-s10-batch8.jsonl"
TINY = [
    "runtime.serial=true",
    "runtime.num_workers=1",
    "runtime.envs_per_worker=4",
    "env.episodes_per_task=8",
    "env.max_episode_steps=25",
    "env.held_out=2",
    "clustering.update_every=8",
    "ppo.epochs=1",
    "network.channels=[2,4]",
    "network.hidden=8",
    "runtime.log_every_s=1000",
    "runtime.total_env_steps=400",
    "runtime.checkpoint_every=100",
]


def test_the_docs_generated_parts_are_current(capsys):
    """The committed tables and docs/guide/configuration.md are what `covers-dist results` writes."""
    assert main(["results", "--check", "--root", str(ROOT)]) == 0, capsys.readouterr()


def test_a_stale_table_is_rewritten_and_the_text_around_it_kept():
    text = f"before\n<!-- table: {SPEC} -->\n| old | table |\n<!-- /table -->\nafter\n"
    new = regenerate(text, ROOT)
    table = render(SPEC, ROOT)
    assert new == f"before\n<!-- table: {SPEC} -->\n{table}<!-- /table -->\nafter\n"
    assert table.startswith("| env steps | own: separation / correct") and "| 36,000 |" in table
    assert regenerate(new, ROOT) == new


def test_bad_table_specs_are_named():
    with pytest.raises(ResultError, match="without its closing"):
        regenerate(f"<!-- table: {SPEC} -->\n| x |\n", ROOT, "page.md")
    with pytest.raises(ResultError, match="without its closing"):  # a second opening before the first closes
        regenerate(f"<!-- table: {SPEC} -->\n<!-- table: {SPEC} -->\n<!-- /table -->\n", ROOT)
    with pytest.raises(ResultError, match="bad table spec"):
        render("nonsense docs/results/clustering/features-tune-s10-batch8.jsonl", ROOT)
    with pytest.raises(ResultError, match="no file matches"):
        render("stream docs/results/stream/no-such-run.json", ROOT)


def test_update_writes_the_tables_and_the_reference_and_check_changes_nothing(tmp_path, capsys):
    (tmp_path / "docs" / "results").mkdir(parents=True)
    data = tmp_path / "docs" / "results" / "f.jsonl"
    data.write_text((ROOT / "docs/results/clustering/features-tune-s10-batch8.jsonl").read_text())
    page = tmp_path / "docs" / "page.md"
    page.write_text("# Page\n<!-- table: features docs/results/f.jsonl -->\n<!-- /table -->\n")
    (tmp_path / "README.md").write_text("# readme\n")
    assert main(["results", "--check", "--root", str(tmp_path)]) == 1
    assert page.read_text().count("|") == 0 and not (tmp_path / "docs/guide/configuration.md").exists()
    out = capsys.readouterr().out
    assert "stale: docs/guide/configuration.md" in out and "stale: docs/page.md" in out
    assert main(["results", "--root", str(tmp_path)]) == 0
    assert "| 1,450,800 |" in page.read_text()
    assert (tmp_path / "docs/guide/configuration.md").read_text() == configuration_reference()
    assert main(["results", "--check", "--root", str(tmp_path)]) == 0
    assert main(["results", "--check", "--root", str(tmp_path / "docs")]) == 2  # not a checkout
    assert "not a covers-dist checkout" in capsys.readouterr().err


def test_the_configuration_reference_has_every_key_with_its_range():
    text = configuration_reference()
    for name, _tp, default, _doc in describe():
        assert f"| `{name}` |" in text, name
    assert "| `env.image_size` | `int` | `32` | >= 8, <= 256 |" in text
    assert "`'toy' \\| 'metaworld'`" in text  # a pipe inside a cell is escaped


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory, one_torch_thread):
    """A tiny serial run, then `covers-dist eval` on the report split."""
    run_dir = tmp_path_factory.mktemp("results") / "run"
    cfg = load_config("configs/smoke.yaml", [*TINY, f"runtime.run_dir={run_dir}"])
    trainer = Trainer(cfg, log=lambda *_: None)
    try:
        assert trainer.run()["status"] == "finished"
    finally:
        trainer.close()
    assert main(["eval", str(run_dir), "--episodes", "2", "--modes", "greedy", "--selections", "agnostic"]) == 0
    return run_dir


def test_a_run_records_its_commit_and_cpu_and_a_resume_appends(finished_run):
    starts = read_starts(finished_run)
    assert len(starts) == 1 and starts[0]["resumed"] is False
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    if head:  # a git checkout (CI's fresh clone is one)
        assert starts[0]["commit"] == head and isinstance(starts[0]["dirty"], bool)
    assert starts[0]["cpu"] and starts[0]["version"]


def test_summarize_gives_every_pair_with_its_n(finished_run, tmp_path, capsys):
    out = tmp_path / "r.json"
    args = ["results", "summarize", str(finished_run), "--role", "report", "--out", str(out), "--commit", "abc123"]
    assert main(args) == 0
    result = json.loads(out.read_text())
    assert result["role"] == "report" and result["commit"] == "abc123" and result["seed"] == 0
    assert result["env_steps"] >= 400 and result["budget"] == {"env_steps": 400, "minutes": None}
    assert result["report"]["episodes_per_pair"] == 2
    pairs = [p for g in result["report"]["groups"].values() for kind in ("trainable", "held_out") for p in g["pairs"][kind]]
    assert pairs and all(p["n"] == 2 and 0 <= p["successes"] <= 2 for p in pairs)
    assert sum(len(g["pairs"]["held_out"]) for g in result["report"]["groups"].values()) == 2
    assert result["stopped"] == "budget" and result["tasks"] == ["reach", "push", "avoid"]
    table = render(f"stream {out.relative_to(tmp_path)}", tmp_path)
    assert table.count("\n") == 3 and "| smoke | 0 (report) |" in table and "(budget) |" in table
    # the headline table: one row per label over its seeds
    second = json.loads(out.read_text()) | {"seed": 1, "role": "tuning"}
    (tmp_path / "r2.json").write_text(json.dumps(second))
    head = render("headline r.json r2.json", tmp_path)
    assert head.count("\n") == 3 and "| smoke | 3 groups under D4 |" in head and "| 0, 1 (report/tuning) |" in head
    mean = sum(p["success"] for g in result["report"]["groups"].values() for p in g["pairs"]["trainable"]) / sum(
        len(g["pairs"]["trainable"]) for g in result["report"]["groups"].values()
    )
    assert f"mean {mean:.2f}" in head and "| 400 env steps |" in head
    # without --commit, the run's own provenance gives it (where the code ran from a git checkout)
    recorded = read_starts(finished_run)[0]["commit"]
    if recorded:
        assert summarize(finished_run, "tuning")["commit"] == recorded
    else:
        with pytest.raises(ResultError, match="commit is unknown"):
            summarize(finished_run, "tuning")


def test_summarize_refuses_what_cannot_give_a_result(finished_run, tmp_path, capsys):
    with pytest.raises(ResultError, match="not a run directory"):
        summarize(tmp_path, "report", commit="x")
    with pytest.raises(ResultError, match="role must be one of"):
        summarize(finished_run, "headline", commit="x")
    bare = tmp_path / "bare"
    bare.mkdir()
    for name in ("config.yaml", "metrics.jsonl"):
        (bare / name).write_text((finished_run / name).read_text())
    with pytest.raises(ResultError, match="no report-split pass"):
        summarize(bare, "report", commit="x")
    (bare / "provenance.jsonl").write_text("")
    (bare / "eval.jsonl").write_text((finished_run / "eval.jsonl").read_text())
    with pytest.raises(ResultError, match="commit is unknown"):
        summarize(bare, "report")
    assert main(["results", "summarize", str(bare)]) == 2  # no --role / --out
    assert main(["results", "summarize", str(tmp_path), "--role", "report", "--out", str(tmp_path / "x.json")]) == 2
    assert "not a run directory" in capsys.readouterr().err


def test_results_imports_no_ray_fastapi_or_torch():
    code = (
        "import sys, covers_dist.results, covers_dist.commands.results\n"
        "bad = [m for m in ('ray', 'fastapi', 'torch', 'covers_dist.runtime') if m in sys.modules]; assert not bad, bad"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
