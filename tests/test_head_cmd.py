"""`covers-dist head`: the documented local `ray job submit` recipe, run as written, and the
command's answers to bad input. Every head is stopped by its own command (its own PIDs)."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from covers_dist.commands.head import head_processes

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _env(state_dir):
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env["PATH"] = f"{BIN}:/usr/bin:/bin"
    env["COVERS_HEAD_DIR"] = str(state_dir)
    return env


def recipe() -> str:
    """The bash block after ``<!-- local-recipe -->`` in deploy/README.md."""
    text = (ROOT / "deploy" / "README.md").read_text()
    block = re.search(r"<!-- local-recipe -->\s*```bash\n(.*?)```", text, re.S)
    assert block, "deploy/README.md has no local-recipe block"
    return block.group(1)


def _head(state_dir, *args):
    return subprocess.run([str(BIN / "covers-dist"), "head", *args], env=_env(state_dir), capture_output=True,
                          text=True, timeout=300)  # fmt: skip


def _tiny_config(tmp_path):
    cfg = yaml.safe_load((ROOT / "configs" / "smoke.yaml").read_text())
    cfg["env"].update(episodes_per_task=8, max_episode_steps=20)
    cfg["clustering"]["update_every"] = 8
    cfg["ppo"].update(epochs=1, minibatch_size=80)
    # one iteration: the job trains on the head's actors and checkpoints; one rollout worker and no
    # learner started ahead (fewer processes to start: the recipe is under test, not the run's size)
    cfg["runtime"].update(total_env_steps=160, log_every_s=0.5, num_workers=1, learner_ahead=False)
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


@pytest.mark.slow
def test_the_documented_local_job_submit_recipe_works_as_written(tmp_path):
    """Slow tier (2-3 minutes on 2 cores: a Ray head, a job's own driver and actors): the default
    suite checks the recipe's commands against the CLI instead (the test below)."""
    script = recipe()
    run_dir = tmp_path / "job"
    # only the config (a tiny stream) and the run directory change; every command stays as written
    script = script.replace("configs/smoke.yaml", str(_tiny_config(tmp_path)))
    script = script.replace('"$PWD/runs/smoke-job"', str(run_dir))
    # with the head up: a second start is refused (checked here, where a head is running anyway)
    stop = "covers-dist head stop"
    assert script.count(stop) == 1
    second = tmp_path / "second-start.err"
    script = script.replace(stop, f"! covers-dist head start --port 0 --dashboard-port 0 2> {second}\n{stop}")
    state = tmp_path / "state"
    done = subprocess.run(["bash", "-e", "-c", script], cwd=ROOT, env=_env(state), capture_output=True, text=True,
                          timeout=900)  # fmt: skip
    temp = re.search(r"temp dir (\S+)", done.stdout)
    try:
        assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-4000:]
        assert "succeeded" in done.stdout + done.stderr
        assert "covers-dist head: running" in done.stdout and "stopped" in done.stdout
        assert any((run_dir / "checkpoints").iterdir())  # the job trained and checkpointed
        assert temp and head_processes(temp.group(1)) == []  # nothing of the head is left
        assert "already running" in second.read_text()
    finally:
        if (state / "head.json").is_file():
            _head(state, "stop")


def test_the_recipe_s_commands_are_the_cli_s(tmp_path):
    """The default suite's check of the documented recipe (run as written in the slow tier): its
    five lines, in order, and every ``covers-dist`` command in it, the job's entrypoint included,
    accepted by the CLI's own parser with the recipe's arguments."""
    import shlex

    from covers_dist.cli import build_parser
    from covers_dist.config import load_config

    lines = [line.split("#")[0].strip() for line in recipe().strip().splitlines()]
    assert [line.split()[:3] for line in lines] == [
        ["covers-dist", "head", "start"], ["eval", '"$(covers-dist', "head"], ["ray", "job", "submit"],
        ["covers-dist", "head", "status"], ["covers-dist", "head", "stop"],
    ]  # fmt: skip
    assert lines[1] == 'eval "$(covers-dist head env)"'
    submit = shlex.split(lines[2].replace("$PWD", str(tmp_path)))
    entry = submit[submit.index("--") + 1 :]
    assert submit[:5] == ["ray", "job", "submit", "--working-dir", "."] and entry[0] == "covers-dist"
    config = entry[entry.index("--config") + 1]
    load_config(str(ROOT / config))  # the job's config loads and validates
    parser = build_parser()
    for argv in (["head", "start"], ["head", "env"], entry[1:], ["head", "status"], ["head", "stop"]):
        args = parser.parse_args(argv)  # an unknown command or option exits 2 here
        assert callable(getattr(args, "func", None)), argv


def test_head_refuses_bad_input(tmp_path, capsys):
    """Without a head (in this process: argument and state checks start nothing): status, stop and
    env answer 3 and say why; a bad port is refused before anything starts. (A second start while
    a head runs: the recipe test above.)"""
    from covers_dist.cli import main

    state = ["--state-dir", str(tmp_path / "state")]
    assert main(["head", "status", *state]) == 3
    assert main(["head", "stop", *state]) == 3 and "nothing to stop" in capsys.readouterr().err
    assert main(["head", "env", *state]) == 3
    with pytest.raises(SystemExit, match=r"0\.\.65535"):
        main(["head", "start", *state, "--dashboard-port", "70000"])


def test_a_port_in_use_is_named(tmp_path):
    import socket

    from covers_dist.cli import main

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(SystemExit, match=rf"port {port} \(--dashboard-port\) is in use"):
            main(["head", "start", "--state-dir", str(tmp_path / "state"), "--dashboard-port", str(port)])
