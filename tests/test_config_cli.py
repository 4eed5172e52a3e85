from pathlib import Path

import pytest
import yaml

from covers_dist.cli import main
from covers_dist.config import (
    DEFAULT_THRESHOLDS,
    Config,
    ConfigError,
    config_from_dict,
    describe,
    load_config,
    resolve_config_path,
    shipped_configs,
)

ROOT = Path(__file__).resolve().parents[1]


def test_defaults_and_every_shipped_config_load():
    cfg = load_config()
    assert isinstance(cfg, Config) and cfg.threshold == 1.0
    shipped = shipped_configs()
    assert {"smoke", "quickstart", "demo", "default"} <= set(shipped)
    for name, path in shipped.items():
        assert load_config(name) == load_config(path), name


def test_shipped_configs_resolve_by_name_from_any_directory(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    want = load_config(ROOT / "covers_dist" / "configs" / "quickstart.yaml")
    for name in ("quickstart", "quickstart.yaml", "configs/quickstart.yaml"):
        assert resolve_config_path(name) == shipped_configs()["quickstart"]
        assert load_config(name) == want, name
    # a file in the working directory wins over a shipped name
    (tmp_path / "quickstart.yaml").write_text("seed: 7\n")
    assert load_config("quickstart.yaml").seed == 7 and load_config("quickstart").seed == want.seed
    for bad in ("quickstrat", "nope.yaml", "elsewhere/quickstart.yaml"):
        with pytest.raises(ConfigError, match=r"does not exist.*quickstart, smoke"):
            load_config(bad)
    assert main(["config", "--config", "smoke"]) == 0
    assert capsys.readouterr().out.startswith("name: smoke\n")
    assert main(["config", "--config", "quickstrat"]) == 2
    err = capsys.readouterr().err
    assert "config 'quickstrat' does not exist" in err and "demo" in err and "paper_cpu" in err


def test_config_list_names_every_shipped_config(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["config", "list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines] == list(shipped_configs())
    assert all(len(line.split()) > 1 for line in lines)  # each with its one-line purpose


def test_shipped_configs_are_package_data_and_the_repository_path_still_works():
    import tomllib

    data = tomllib.loads((ROOT / "pyproject.toml").read_text())
    patterns = data["tool"]["setuptools"]["package-data"]["covers_dist"]
    assert "configs/*.yaml" in patterns
    shipped = shipped_configs()
    assert all(p.parent == ROOT / "covers_dist" / "configs" for p in shipped.values())
    # the repository's top-level configs/ (README, Makefile, deploy/) reaches the same files
    assert sorted(p.name for p in (ROOT / "configs").glob("*.yaml")) == sorted(p.name for p in shipped.values())
    assert (ROOT / "configs" / "demo.yaml").read_text() == shipped["demo"].read_text()


def test_stream_fast_is_stream_cpu_with_the_measured_overrides():
    # docs/RESULTS.md's runs with the coarser stem ran stream_cpu with these overrides (their time limit
    # of 85 minutes, not reached, aside)
    measured = ["env.success_bonus=100", "env.success_bonus_once=true", "env.success_bonus_radius=0.5",
                "network.space_to_depth=4", "runtime.total_env_steps=1500000", "runtime.time_limit_minutes=90",
                "runtime.run_dir=runs/stream-fast", "name=stream-fast"]  # fmt: skip
    assert load_config("stream_fast") == load_config("stream_cpu", measured)


def test_stream_fast_builds_on_stream_cpu_by_its_base_key():
    # the file holds only what differs, so the two cannot drift apart
    data = yaml.safe_load(shipped_configs()["stream_fast"].read_text())
    assert data["base"] == "stream_cpu" and "clustering" not in data and "ppo" not in data


def test_group_fast_is_quickstart_with_the_measured_overrides():
    # docs/research/learning.md's per-group runs with stream_fast's settings ran `bench learn` (on quickstart) with these,
    # but for the clustering's feature source (colors then; the learned joint features and healing since)
    measured = ["ppo.epochs=4", "ppo.minibatch_size=200", "network.init_log_std=0.0", "clustering.feature_source=joint",
                "clustering.merge_threshold=1.0", "clustering.tie_margin=0.2",
                "env.max_episode_steps=150", "ppo.target_kl=0.01", "ppo.kl_reference=update_start",
                "clustering.assign_at=reset", "clustering.false_split_rate=1e-4", "env.success_bonus=100",
                "env.success_bonus_once=true", "env.success_bonus_radius=0.5", "network.space_to_depth=4",
                "runtime.run_dir=runs/group-fast", "name=group-fast"]  # fmt: skip
    assert load_config("group_fast") == load_config("quickstart", measured)


def test_group_alone_is_group_fast_with_the_measured_overrides():
    # docs/research/learning.md's separate-critic runs ran `bench learn` with group_fast's settings and these
    measured = ["ppo.target_kl=0.02", "ppo.lr_schedule=linear", "network.critic=separate",
                "runtime.run_dir=runs/group-alone", "name=group-alone"]  # fmt: skip
    assert load_config("group_alone") == load_config("group_fast", measured)
    # the falling rate needs the run's length: a learner's ppo gets it from the run's budget
    cfg = load_config("group_alone")
    assert cfg.ppo.total_updates is None and cfg.learner_ppo.total_updates == cfg.updates_per_run > 0


def test_a_base_file_gives_every_value_the_file_does_not_set(tmp_path):
    (tmp_path / "parent.yaml").write_text(
        "seed: 5\nppo:\n  lr: 1.0e-4\n  epochs: 7\nnetwork:\n  channels: [4, 8, 8, 16, 16, 16]\n"
    )
    child = tmp_path / "child.yaml"
    child.write_text("base: parent\nppo:\n  epochs: 2\nnetwork:\n  channels: [8, 8]\n")
    cfg = load_config(child)
    assert cfg.seed == 5 and cfg.ppo.lr == 1e-4  # from the base
    assert cfg.ppo.epochs == 2 and cfg.network.channels == [8, 8]  # the file's own win; a list replaced whole
    assert load_config(child, ["ppo.epochs=3"]).ppo.epochs == 3  # --set still has the last word
    # a chain of bases, and a base by a shipped config's name
    (tmp_path / "grandchild.yaml").write_text("base: child.yaml\nseed: 9\n")
    g = load_config(tmp_path / "grandchild.yaml")
    assert (g.seed, g.ppo.lr, g.ppo.epochs) == (9, 1e-4, 2)
    (tmp_path / "on_smoke.yaml").write_text("base: smoke\nseed: 4\n")
    assert load_config(tmp_path / "on_smoke.yaml") == load_config("smoke", ["seed=4"])


@pytest.mark.parametrize(
    "files, match",
    [
        ({"a.yaml": "base: nowhere\n"}, r"a.yaml.*its base 'nowhere' was not found"),
        ({"a.yaml": "base: 3\n"}, r"a.yaml.*base must name another config file, got 3"),
        ({"a.yaml": "base: b\n", "b.yaml": "base: a.yaml\n"}, r"b.yaml.*its base chain loops \(.*a.yaml -> .*b.yaml -> .*a.yaml\)"),
        ({"a.yaml": "base: a\n"}, r"its base chain loops"),
        ({"a.yaml": "base: b\n", "b.yaml": "ppo:\n  epoch: 2\n"}, r"unknown config key\(s\) \['ppo.epoch'\]"),
    ],
)
def test_bad_base_keys_name_the_file(tmp_path, files, match):
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_config(tmp_path / "a.yaml")


def test_a_base_is_never_looked_for_in_the_working_directory(tmp_path, monkeypatch):
    # a file of the same name in the directory a command runs from must not change what a config means
    (tmp_path / "conf").mkdir()
    owner = tmp_path / "conf" / "mine.yaml"
    owner.write_text("base: parent\nseed: 3\n")
    (tmp_path / "parent.yaml").write_text("seed: 5\n")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match=r"mine.yaml.*its base 'parent' was not found: no such file beside it"):
        load_config(owner)
    # an absolute path and the repository path of a shipped config still work
    owner.write_text(f"base: {tmp_path / 'parent.yaml'}\n")
    assert load_config(owner).seed == 5
    owner.write_text("base: configs/smoke.yaml\nseed: 4\n")
    assert load_config(owner) == load_config("smoke", ["seed=4"])


def test_overrides_parse_values_as_yaml():
    cfg = load_config(ROOT / "configs/smoke.yaml", ["ppo.lr=1e-4", "env.tasks=[reach, push]", "ppo.target_kl=null"])
    assert cfg.ppo.lr == 1e-4 and cfg.env.tasks == ["reach", "push"] and cfg.ppo.target_kl is None
    assert load_config(None, ["clustering.metric=euclidean"]).threshold == DEFAULT_THRESHOLDS["euclidean"]


@pytest.mark.parametrize(
    "data, match",
    [
        ({"ppo": {"lrr": 1}}, r"unknown config key\(s\) \['ppo.lrr'\]"),
        ({"bogus": 1}, r"unknown config key\(s\) \['bogus'\]"),
        ({"ppo": {"epochs": "four"}}, r"ppo.epochs: expected an integer, got 'four'"),
        ({"ppo": {"epochs": 2.5}}, r"ppo.epochs: expected an integer"),
        ({"ppo": {"norm_adv": "yes"}}, r"ppo.norm_adv: expected true or false"),
        ({"ppo": {"lr": -1.0}}, r"ppo.lr=-1.0 must be > 0.0"),
        ({"clustering": {"metric": "cosine"}}, r"clustering.metric: expected one of"),
        ({"env": {"tasks": "reach"}}, r"env.tasks: expected a list"),
        ({"env": {"image_size": 4}}, r"env.image_size=4 must be >= 8"),
        ({"env": {"image_size": 40}}, r"image_size=40 with space_to_depth=1: conv block 4 of 4 would pool a 5 x 5 map"),
        ({"network": {"space_to_depth": 3}}, r"network.space_to_depth: expected one of"),
        ({"env": {"group": "D4"}, "network": {"group": "C4"}}, r"network.group=C4 does not contain env.group=D4"),
        ({"runtime": {"method": "cnn"}}, r"runtime.method=cnn needs network.kind=cnn"),
        ({"ppo": {"minibatch_size": 1000}, "clustering": {"update_every": 2}}, r"ppo.minibatch_size=1000 exceeds"),
        ({"env": {"tasks": ["reach", "reach"]}}, r"duplicate task names"),
        ({"ppo": []}, r"ppo: expected a mapping"),
        ({"network": {"proprio_norm": True}}, r"network.proprio_norm=true: env.suite=toy has no proprio statistics"),
        ({"network": {"proprio_norm": "on"}}, r"network.proprio_norm: expected true or false"),
        ({"network": {"action_mean": "sigmoid"}}, r"network.action_mean: expected one of"),
        ({"runtime": {"time_limit_minutes": 0}}, r"runtime.time_limit_minutes=0.0 must be > 0.0"),
        ({"eval": {"stop_at": 1.5, "every_iterations": 5}}, r"eval.stop_at=1.5 must be <= 1.0"),
        ({"eval": {"stop_at": 0.9}}, r"eval.stop_at=0.9 needs periodic greedy passes: eval.every_iterations > 0"),
        (
            {"eval": {"stop_at": 0.9, "every_iterations": 5, "modes": ["stochastic"]}},
            r"'greedy' in eval.modes \(got \['stochastic'\]\)",
        ),
        ({"eval": {"stop_groups": "most"}}, r"eval.stop_groups: expected one of"),
        ({"eval": {"held": 0}}, r"eval.held=0 must be >= 1"),
    ],
)
def test_bad_configs_name_the_field(data, match):
    with pytest.raises(ConfigError, match=match):
        config_from_dict(data)


@pytest.mark.parametrize(
    "override, match",
    [
        ("ppo.lr=nan", r"ppo.lr: expected a finite number, got nan"),
        ("ppo.lr=.nan", r"ppo.lr: expected a finite number, got nan"),
        ("ppo.lr=.inf", r"ppo.lr: expected a finite number, got inf"),
        ("ppo.lr=-.inf", r"ppo.lr: expected a finite number, got -inf"),
        ("clustering.threshold=.nan", r"clustering.threshold: expected a finite number, got nan"),
        ("runtime.time_limit_minutes=.inf", r"runtime.time_limit_minutes: expected a finite number, got inf"),
        ("api.host=not a host", r"api.host='not a host' is not an IP address or a host name"),
        ("api.host=-bad-.example", r"api.host='-bad-.example' is not an IP address or a host name"),
        ("api.host=''", r"api.host='' is not an IP address or a host name"),
    ],
)
def test_non_finite_numbers_and_bad_hosts_are_refused(override, match):
    with pytest.raises(ConfigError, match=match):
        load_config(None, [override])


@pytest.mark.parametrize("host", ["127.0.0.1", "::1", "0.0.0.0", "localhost", "api.internal.example", "covers-api"])
def test_addresses_and_host_names_are_valid_hosts(host):
    assert load_config(None, [f"api.host={host}"]).api.host == host


def test_bad_override_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="must look like section.field=value"):
        load_config(None, ["ppo.lr"])
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("ppo: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(bad)


def test_config_is_frozen_and_every_field_documented():
    cfg = load_config()
    with pytest.raises(Exception):
        cfg.ppo.lr = 1.0  # type: ignore[misc]
    for name, _tp, _default, doc in describe():
        assert doc, f"{name} has no docstring"


def test_cli_help_lists_subcommands(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for sub in ("config", "demo", "bench"):
        assert sub in out


def _all_parsers():
    import argparse

    from covers_dist.cli import build_parser

    def walk(parser, name):
        yield name, parser
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub, child in action.choices.items():
                    yield from walk(child, f"{name} {sub}")

    return list(walk(build_parser(), "covers-dist"))


def test_help_texts_show_no_restructuredtext():
    import re

    markup = re.compile(r"``|:(?:py:)?(?:func|mod|class|data|meth|attr|obj|exc|ref|doc):`")
    parsers = _all_parsers()
    assert len(parsers) > 10
    for name, parser in parsers:
        text = parser.format_help()
        assert not markup.search(text), (name, markup.findall(text))


def test_list_flags_are_comma_separated_and_accept_spaces_too():
    """One convention for list-valued flags: comma-separated, space-separated also accepted where a
    flag took several values before."""
    from covers_dist.cli import build_parser
    from covers_dist.commands._common import CommaList

    parser = build_parser()
    render = parser.parse_args(["bench", "render", "--tasks", "reach-v3,drawer-close-v3", "plate-slide-v3"])
    assert render.tasks == ["reach-v3", "drawer-close-v3", "plate-slide-v3"]
    assert parser.parse_args(["bench", "learn", "--merge", "a.json,b.json"]).merge == ["a.json", "b.json"]
    assert parser.parse_args(["bench", "learn", "--merge", "a.json", "b.json"]).merge == ["a.json", "b.json"]
    for name, p in _all_parsers():  # no flag takes a space-separated list only
        for action in p._actions:
            if action.option_strings and action.nargs in ("+", "*") and not isinstance(action, CommaList):
                raise AssertionError(f"{name} {action.option_strings}: nargs={action.nargs!r} without CommaList")


def test_cli_reports_config_errors(capsys):
    assert main(["config", "--set", "ppo.epochs=zero"]) == 2
    assert "ppo.epochs: expected an integer" in capsys.readouterr().err


# the installed console script starting (a subprocess): tests/test_plain_shell.py


def test_demo_writes_grid(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--episodes", "1", "--image-size", "16"]) == 0
    assert (tmp_path / "toy_grid.png").stat().st_size > 0
    assert "mismatches (image or reward): 0" in capsys.readouterr().out


def test_suites_with_proprio_statistics_agree_with_the_layouts():
    """The config's list (checked without importing any suite) matches what each suite's layout carries."""
    import typing

    from covers_dist.config import SUITES_WITH_PROPRIO_STATS, EnvConfig
    from covers_dist.envs import suite_layout

    suites = typing.get_args(typing.get_type_hints(EnvConfig)["suite"])
    assert set(SUITES_WITH_PROPRIO_STATS) <= set(suites)
    for suite in suites:
        assert suite_layout(suite, 64).has_proprio_stats == (suite in SUITES_WITH_PROPRIO_STATS), suite


def test_a_saved_run_that_predates_a_field_keeps_the_value_it_ran_with(tmp_path):
    """Runs saved before network.action_mean existed trained a linear mean: resuming, evaluating or
    serving them must not switch them to today's tanh default."""
    import yaml

    from covers_dist.config import config_to_dict, load_run_config

    data = config_to_dict(load_config())
    assert data["network"]["action_mean"] == "tanh"
    old = tmp_path / "old.yaml"
    del data["network"]["action_mean"]
    old.write_text(yaml.safe_dump(data))
    assert load_config(old).network.action_mean == "tanh"  # a config to start from: today's default
    assert load_run_config(old).network.action_mean == "linear"  # a saved run: what it ran with
    data["network"]["action_mean"] = "tanh"
    new = tmp_path / "new.yaml"
    new.write_text(yaml.safe_dump(data))
    assert load_run_config(new).network.action_mean == "tanh"
    with pytest.raises(ConfigError, match="does not exist"):
        load_run_config(tmp_path / "nope.yaml")
