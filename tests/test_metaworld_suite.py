"""The Meta-World suite: exact equivalence of g.T and T, observations, seeding, errors, checker."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from covers_dist.config import ConfigError, EnvConfig, config_from_dict
from covers_dist.envs import make_task, suite_layout, task_names, transform_obs
from covers_dist.envs.metaworld_suite import (
    DISC_RADIUS,
    SYMMETRY_CENTRE,
    TASKS,
    MetaWorldTask,
    metaworld_layout,
    register_metaworld_envs,
    register_task,
)
from covers_dist.envs.topdown_view import DISC_COLOR
from covers_dist.symmetry import D4_ELEMENTS, GroupElement

BASE_TASKS = ("reach-v3", "button-press-topdown-v3", "drawer-close-v3", "plate-slide-v3")
STEPS = 90  # long enough for the scripted expert to solve every task (drawer: about 80)
SEED = 7


def _scripted_actions(env: MetaWorldTask, steps: int, seed: int):
    """Base-frame trajectory: Meta-World's expert plus seeded noise; records what the agent saw."""
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    record = {"obs": [obs], "action": [], "reward": [], "success": [], "trunc": [], "target_ratio": []}
    for _ in range(steps):
        a = np.clip(env.expert_action() + rng.normal(0.0, 0.2, size=4), -1, 1).astype(np.float32)
        obs, r, term, trunc, info = env.step(a)
        assert term is False
        for k, v in (("obs", obs), ("action", a), ("reward", r), ("success", info["success"]), ("trunc", trunc)):
            record[k].append(v)
        record["target_ratio"].append(info.get("target_ratio"))
    return record


@pytest.mark.parametrize("task", BASE_TASKS)
def test_target_ratio_is_one_exactly_at_success(task, base_runs):
    """info["target_ratio"] (obj_to_target over the spec's success radius) is <= 1 on exactly the
    steps Meta-World counts as successes: the radius matches Meta-World's own threshold."""
    run = base_runs[task]
    ratios = run["target_ratio"]
    assert all(r is not None and np.isfinite(r) and r >= 0 for r in ratios)
    assert [s == 1.0 for s in run["success"]] == [r <= 1.0 for r in ratios]
    assert min(ratios) <= 1.0 < max(ratios)  # the expert's episode has both


def test_success_bonus_adds_to_the_reward_of_successful_steps_only():
    runs = {}
    for bonus in (0.0, 4.0):
        env = MetaWorldTask("reach-v3", "rf", max_episode_steps=STEPS, success_bonus=bonus)
        runs[bonus] = _scripted_actions(env, STEPS, SEED)
        env.close()
    plain, bonus = runs[0.0], runs[4.0]
    assert plain["success"] == bonus["success"] and max(plain["success"]) == 1.0 and min(plain["success"]) == 0.0
    np.testing.assert_allclose(np.array(bonus["reward"]) - np.array(plain["reward"]), 4.0 * np.array(plain["success"]))
    for bad in (-1.0, float("nan"), float("inf"), True, "1"):
        with pytest.raises(ValueError, match="success_bonus must be a finite number"):
            MetaWorldTask("reach-v3", success_bonus=bad)


def test_success_bonus_once_pays_the_first_successful_step_only():
    runs = {}
    for once in (False, True):
        env = MetaWorldTask("reach-v3", "rf", max_episode_steps=STEPS, success_bonus=4.0, success_bonus_once=once)
        runs[once] = [_scripted_actions(env, STEPS, SEED) for _ in range(2)]  # the second run: a new episode
        env.close()
    for every, once in zip(runs[False], runs[True]):
        success = np.array(every["success"])
        assert success.sum() >= 2  # the scripted expert stays inside for several steps
        first = np.zeros_like(success)
        first[int(np.argmax(success))] = 1.0
        np.testing.assert_allclose(np.array(every["reward"]) - np.array(once["reward"]), 4.0 * (success - first))
    with pytest.raises(TypeError, match="success_bonus_once must be True or False"):
        MetaWorldTask("reach-v3", success_bonus=1.0, success_bonus_once=1)


def test_success_bonus_radius_pays_inside_the_fraction_of_the_radius_only():
    """With success_bonus_radius < 1 the bonus is paid on the steps whose target ratio is within that
    fraction (not on every success), once per episode with success_bonus_once; 1 is the plain bonus."""
    runs = {}
    for radius, once in ((1.0, False), (0.5, False), (0.5, True)):
        env = MetaWorldTask(
            "plate-slide-v3", "r2f", max_episode_steps=STEPS, success_bonus=4.0, success_bonus_once=once,
            success_bonus_radius=radius,
        )
        runs[radius, once] = _scripted_actions(env, STEPS, SEED)
        env.close()
    plain, inner, inner_once = runs[1.0, False], runs[0.5, False], runs[0.5, True]
    success, ratio = np.array(plain["success"]), np.array(plain["target_ratio"])
    assert inner["success"] == plain["success"] and inner["target_ratio"] == plain["target_ratio"]
    deep = (ratio <= 0.5).astype(float)
    assert deep.sum() >= 2 and ((success == 1) & (ratio > 0.5)).any()  # the expert crosses the ring 0.5-1 radii
    base = np.array(plain["reward"]) - 4.0 * success  # Meta-World's own reward
    np.testing.assert_allclose(np.array(inner["reward"]) - base, 4.0 * deep, atol=1e-9)
    first = np.zeros_like(deep)
    first[int(np.argmax(deep))] = 1.0
    np.testing.assert_allclose(np.array(inner_once["reward"]) - base, 4.0 * first, atol=1e-9)
    for bad in (0.0, -0.5, 1.5, float("nan"), True, "0.5"):
        with pytest.raises(ValueError, match="success_bonus_radius must be a fraction"):
            MetaWorldTask("reach-v3", success_bonus=1.0, success_bonus_radius=bad)
    spec = register_task("push-v3", "Push")  # no success radius registered
    try:
        with pytest.raises(ValueError, match="registers no success radius"):
            MetaWorldTask("push-v3", success_bonus=1.0, success_bonus_radius=0.5)
        MetaWorldTask("push-v3", image_size=32, success_bonus=1.0).close()  # the plain bonus needs no radius
    finally:
        TASKS.pop(spec.name)


def test_success_bonus_config_is_checked():
    from covers_dist.config import load_config

    assert load_config("configs/stream_cpu.yaml", ["env.success_bonus=10"]).env.success_bonus == 10.0
    for value, words in (("-1", ">= 0"), ("nan", "finite"), ("inf", "finite")):
        with pytest.raises(ConfigError, match=words):
            load_config("configs/stream_cpu.yaml", [f"env.success_bonus={value}"])
    with pytest.raises(ConfigError, match="metaworld suite only"):
        load_config("configs/smoke.yaml", ["env.success_bonus=1"])
    cfg = load_config("configs/stream_cpu.yaml", ["env.success_bonus=100", "env.success_bonus_once=true"])
    assert cfg.env.success_bonus_once is True
    with pytest.raises(ConfigError, match="set env.success_bonus > 0"):
        load_config("configs/stream_cpu.yaml", ["env.success_bonus_once=true"])
    cfg = load_config("configs/stream_cpu.yaml", ["env.success_bonus=100", "env.success_bonus_radius=0.5"])
    assert cfg.env.success_bonus_radius == 0.5
    env = make_task(cfg.env, "reach-v3", "e")
    assert env.unwrapped.success_bonus_radius == 0.5
    env.close()
    for value, words in (("0", "> 0"), ("1.5", "<= 1"), ("nan", "expected a finite number")):
        with pytest.raises(ConfigError, match=words):
            load_config("configs/stream_cpu.yaml", ["env.success_bonus=1", f"env.success_bonus_radius={value}"])
    with pytest.raises(ConfigError, match="set env.success_bonus > 0"):
        load_config("configs/stream_cpu.yaml", ["env.success_bonus_radius=0.5"])


def test_success_radius_is_checked():
    for bad in (0.0, -0.05, float("nan"), float("inf"), True, "0.05"):
        with pytest.raises(ValueError, match="success_radius must be a positive distance"):
            register_task("push-v3", success_radius=bad)


@pytest.fixture(scope="module")
def base_runs():
    runs = {}
    for task in BASE_TASKS:
        env = MetaWorldTask(task, "e", max_episode_steps=STEPS)
        runs[task] = _scripted_actions(env, STEPS, SEED)
        env.close()
    return runs


@pytest.mark.parametrize("task", BASE_TASKS)
def test_transformed_tasks_are_exactly_equivalent(task, base_runs):
    """For every g: images pixel-equal to g(base image), proprio g-transformed, same rewards/success."""
    run = base_runs[task]
    layout = metaworld_layout(64)
    assert max(run["success"]) == 1.0, "the scripted trajectory should solve the task"
    for g in D4_ELEMENTS:
        env = MetaWorldTask(task, g, max_episode_steps=STEPS)
        obs, _ = env.reset(seed=SEED)
        for t in range(STEPS + 1):
            expected = transform_obs(layout, g, run["obs"][t])
            assert np.array_equal(obs["image"], expected["image"]), f"{task} {g.name} step {t}: image differs"
            np.testing.assert_array_equal(obs["proprio"], expected["proprio"])
            if t == STEPS:
                break
            obs, r, term, trunc, info = env.step(layout.transform_action(g, run["action"][t]))
            assert r == run["reward"][t] and info["success"] == run["success"][t] and trunc == run["trunc"][t]
        assert trunc, "the episode must be truncated at max_episode_steps"
        env.close()


@pytest.mark.parametrize("task", BASE_TASKS)
def test_transforms_give_visibly_different_tasks(task, base_runs):
    image = base_runs[task]["obs"][10]["image"]
    images = [g.apply_image(image) for g in D4_ELEMENTS]
    for i in range(8):
        for j in range(i):
            assert not np.array_equal(images[i], images[j]), (task, D4_ELEMENTS[i], D4_ELEMENTS[j])


def test_task_groups_look_different(base_runs):
    colours = {t: {tuple(c) for c in run["obs"][0]["image"].reshape(-1, 3)} for t, run in base_runs.items()}
    for a in BASE_TASKS:
        for b in BASE_TASKS:
            if a < b:
                assert colours[a] != colours[b]


def _blue_centroid(image: np.ndarray) -> np.ndarray:
    rows, cols = np.nonzero(np.all(image == DISC_COLOR, axis=-1))
    assert len(rows) >= 9, "the gripper disc should be visible"
    return np.array([cols.mean(), rows.mean()])


@pytest.mark.parametrize("g", [GroupElement.from_name(n) for n in ("e", "r", "r2f", "r3f")], ids=lambda g: g.name)
def test_blue_disc_follows_the_gripper(g):
    env = MetaWorldTask("reach-v3", g)
    obs, _ = env.reset(seed=3)
    size = env.image_size
    centre_px = (size - 1) / 2.0
    moves = [np.array([0.8, 0.4, 0.0, 0.0], np.float32)] * 20 + [np.array([-0.6, -1.0, 0.0, 0.0], np.float32)] * 20
    moved = 0.0
    for move in moves:
        hand = env.task_state()["hand"]  # gripper position relative to the symmetry centre, seen through g
        expected = np.array([centre_px + hand[0] / env.view.pitch, centre_px - hand[1] / env.view.pitch])
        np.testing.assert_allclose(_blue_centroid(obs["image"]), expected, atol=0.5)
        np.testing.assert_allclose(obs["proprio"][:2], hand[:2], atol=0.02)  # hand body vs gripper centre
        moved = max(moved, float(np.hypot(*hand[:2])))
        obs = env.step(move)[0]
    assert moved > 0.1
    env.close()


def test_proprio_layout_and_contents():
    env = MetaWorldTask("drawer-close-v3", "r")
    obs, info = env.reset(seed=1)
    assert obs["image"].shape == (64, 64, 3) and obs["image"].dtype == np.uint8
    assert obs["proprio"].shape == (4,) and obs["proprio"].dtype == np.float32
    assert info == {"success": 0.0}
    mw = env.unwrapped_metaworld
    hand = mw.get_endeff_pos()
    base = np.array([hand[0] - SYMMETRY_CENTRE[0], hand[1] - SYMMETRY_CENTRE[1]])
    np.testing.assert_allclose(obs["proprio"][:2], GroupElement.from_name("r").apply_vectors(base), atol=1e-6)
    np.testing.assert_allclose(obs["proprio"][2], hand[2], atol=1e-6)
    assert 0.0 <= obs["proprio"][3] <= 1.0
    assert np.array_equal(obs["image"], GroupElement.from_name("r").apply_image(env.render_base()))
    state = env.task_state()
    assert set(state) == {"hand", "object", "goal", "hand_base", "object_base", "goal_base"}
    assert env.layout == metaworld_layout(64) == suite_layout("metaworld", 64)
    env.close()


def test_placement_is_seeded():
    env = MetaWorldTask("reach-v3")
    goals = []
    for seed in (5, 5, 6):
        obs, _ = env.reset(seed=seed)
        goals.append((env.task_state()["goal"].copy(), env.task_state()["object"].copy(), obs["image"].copy()))
    assert np.array_equal(goals[0][0], goals[1][0]) and np.array_equal(goals[0][2], goals[1][2])
    assert not np.array_equal(goals[0][0], goals[2][0])
    low, high = env.unwrapped_metaworld._random_reset_space.low, env.unwrapped_metaworld._random_reset_space.high
    goal_world = goals[2][0] + np.array([*SYMMETRY_CENTRE, 0.0])
    assert np.all(goal_world >= low[3:] - 1e-9) and np.all(goal_world <= high[3:] + 1e-9)
    # consecutive unseeded resets draw new placements from the same stream
    env.reset(seed=9)
    first = env.task_state()["goal"].copy()
    env.reset()
    assert not np.array_equal(first, env.task_state()["goal"])
    env.close()


def test_make_task_and_registry():
    assert set(BASE_TASKS) <= set(task_names("metaworld"))
    cfg = EnvConfig(suite="metaworld", tasks=list(BASE_TASKS), image_size=32, max_episode_steps=5)
    env = make_task(cfg, "plate-slide-v3", "rf", seed=0)
    assert isinstance(env, MetaWorldTask) and env.g.name == "rf" and env.image_size == 32
    for _ in range(5):
        _, _, _, trunc, _ = env.step(env.action_space.sample())
    assert trunc
    with pytest.raises(RuntimeError, match="call reset"):
        env.step(np.zeros(4, dtype=np.float32))
    env.close()
    assert TASKS["reach-v3"].label == "Goal Reach"
    spec = register_task("push-v3", "Push")
    try:
        assert "push-v3" in task_names("metaworld")
        extra = MetaWorldTask("push-v3", "f", image_size=32)
        extra.reset(seed=0)
        extra.step(extra.expert_action())
        extra.close()
    finally:
        TASKS.pop(spec.name)


def test_bad_input_gives_clear_errors():
    cfg = EnvConfig(suite="metaworld", tasks=["reach-v3"], image_size=64)
    with pytest.raises(ValueError, match="unknown metaworld task 'reach-v9'"):
        make_task(cfg, "reach-v9")
    with pytest.raises(ValueError, match="unknown Meta-World task"):
        MetaWorldTask("pick-and-teleport")
    with pytest.raises(ValueError, match="unknown Meta-World v3 environment"):
        register_task("not-a-task-v3")
    for size in (16, 31, 129, 256):
        with pytest.raises(ValueError, match="image_size"):
            MetaWorldTask("reach-v3", image_size=size)
    with pytest.raises(TypeError, match="image_size"):
        MetaWorldTask("reach-v3", image_size=64.0)
    with pytest.raises(ValueError, match="render_backend"):
        MetaWorldTask("reach-v3", render_backend="vulkan")
    with pytest.raises(ValueError, match="unknown D4 element"):
        MetaWorldTask("reach-v3", "r5")
    with pytest.raises(ValueError, match="camera_shift"):
        MetaWorldTask("reach-v3", camera_shift=-0.1)
    env = MetaWorldTask("reach-v3", image_size=32)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(4, dtype=np.float32))
    env.reset(seed=0)
    with pytest.raises(ValueError, match="4 finite numbers"):
        env.step(np.zeros(3, dtype=np.float32))
    with pytest.raises(ValueError, match="4 finite numbers"):
        env.step(np.array([np.nan, 0, 0, 0], dtype=np.float32))
    env.close()


@pytest.mark.parametrize("g", ["e", "r3f"])
def test_action_repeat_is_that_many_meta_world_steps_with_one_image(g):
    """An agent step with ``action_repeat=2`` is two steps of the same action: rewards summed,
    success if either was, the state (image and proprio) after the second; the episode ends
    after ``max_episode_steps`` agent steps."""
    cfg = EnvConfig(suite="metaworld", tasks=["button-press-topdown-v3"], image_size=32, max_episode_steps=6,
                    action_repeat=2)  # fmt: skip
    repeated = make_task(cfg, "button-press-topdown-v3", g)
    single = MetaWorldTask("button-press-topdown-v3", g, image_size=32, max_episode_steps=12)
    assert repeated.action_repeat == 2 and repeated.unwrapped_metaworld.max_path_length == 12
    rng = np.random.default_rng(SEED)
    obs_r, _ = repeated.reset(seed=SEED)
    obs_s, _ = single.reset(seed=SEED)
    for t in range(6):
        action = rng.uniform(-1, 1, size=4).astype(np.float32)
        obs_r, reward_r, _, trunc_r, info_r = repeated.step(action)
        rewards, successes = [], []
        for _ in range(2):
            obs_s, reward_s, _, trunc_s, info_s = single.step(action)
            rewards.append(reward_s)
            successes.append(info_s["success"])
        assert reward_r == pytest.approx(sum(rewards), abs=1e-9) and info_r["success"] == max(successes)
        np.testing.assert_array_equal(obs_r["image"], obs_s["image"])
        np.testing.assert_array_equal(obs_r["proprio"], obs_s["proprio"])
        assert trunc_r == (t == 5) and trunc_s == trunc_r
    with pytest.raises(RuntimeError, match="ended after 6 steps"):
        repeated.step(np.zeros(4, dtype=np.float32))
    repeated.close()
    single.close()


def test_action_repeat_bad_values_are_refused_by_name():
    with pytest.raises(ConfigError, match="env.action_repeat=2: action repeat applies to the metaworld suite only"):
        EnvConfig(suite="toy", tasks=["reach"], action_repeat=2)
    with pytest.raises(ConfigError, match="600 Meta-World steps per episode; Meta-World allows at most 500"):
        EnvConfig(suite="metaworld", tasks=["reach-v3"], image_size=64, max_episode_steps=300, action_repeat=2)
    with pytest.raises(ConfigError, match="env.action_repeat"):
        config_from_dict({"env": {"suite": "metaworld", "tasks": ["reach-v3"], "image_size": 64, "action_repeat": 0}})
    with pytest.raises(ValueError, match="action_repeat must be an integer >= 1"):
        MetaWorldTask("reach-v3", action_repeat=1.5)
    with pytest.raises(ValueError, match="Meta-World allows at most 500"):
        MetaWorldTask("reach-v3", max_episode_steps=200, action_repeat=3)


def test_gymnasium_env_checker():
    ids = register_metaworld_envs()
    env = gym.make(ids["button-press-topdown-v3"], g="r3", image_size=32, render_mode="rgb_array")
    check_env(env.unwrapped)
    frame = env.unwrapped.render()
    assert frame.shape == (32, 32, 3) and frame.dtype == np.uint8
    env.close()


def test_camera_shift_moves_the_view_not_the_robot():
    pitch = 2 * 0.36 / 64
    plain = MetaWorldTask("button-press-topdown-v3")
    shifted = MetaWorldTask("button-press-topdown-v3", camera_shift=3 * pitch, camera_shift_angle=0.0)
    a, _ = plain.reset(seed=2)
    b, _ = shifted.reset(seed=2)
    np.testing.assert_array_equal(a["proprio"], b["proprio"])
    # the camera moved 3 pixels to +x: the scene moves 3 columns to the left
    same = np.all(a["image"][:, 3:] == b["image"][:, :-3], axis=-1).mean()
    assert same > 0.99 and not np.array_equal(a["image"], b["image"])
    plain.close()
    shifted.close()


def test_disc_radius_is_about_three_pixels_at_64():
    assert 2.0 < DISC_RADIUS / (2 * 0.36 / 64) < 4.0


def test_set_element_matches_a_fresh_env():
    """An env switched to g in place runs exactly like one built with g (the rollout workers switch)."""
    switched = MetaWorldTask("plate-slide-v3", "r", max_episode_steps=20)
    _scripted_actions(switched, 5, seed=1)  # mid-episode under another element
    for g in ("rf", "e", "r3"):
        switched.set_element(g)
        with pytest.raises(RuntimeError, match="reset"):
            switched.step(np.zeros(4, np.float32))
        fresh = MetaWorldTask("plate-slide-v3", g, max_episode_steps=20)
        a, b = _scripted_actions(switched, 20, seed=3), _scripted_actions(fresh, 20, seed=3)
        fresh.close()
        assert switched.g.name == g
        for oa, ob in zip(a["obs"], b["obs"]):
            np.testing.assert_array_equal(oa["image"], ob["image"])
            np.testing.assert_array_equal(oa["proprio"], ob["proprio"])
        assert a["reward"] == b["reward"] and a["success"] == b["success"]
    with pytest.raises(TypeError, match="GroupElement"):
        switched.set_element(3)
    switched.close()


def test_eval_episodes_report_the_closest_approach():
    """run_eval_episodes keeps each episode's smallest target_ratio: <= 1 on success, and on a
    failure how far it stayed (here: a hand that never moves)."""
    from covers_dist.evaluation.episodes import run_eval_episodes

    envs = [MetaWorldTask("reach-v3", g, max_episode_steps=60) for g in ("e", "r3f")]

    class Expert:
        def act(self, obs, deterministic=True, generator=None):
            return np.stack([env.expert_action() for env in envs]).astype(np.float32), None, None

    class Still:
        def act(self, obs, deterministic=True, generator=None):
            return np.zeros((len(obs["proprio"]), 4), np.float32), None, None

    solved = run_eval_episodes(Expert(), envs, [5, 6])
    assert [ep["success"] for ep in solved] == [1.0, 1.0]
    assert all(ep["closest"] <= 1.0 for ep in solved)
    stayed = run_eval_episodes(Still(), envs, [5, 6])
    assert [ep["success"] for ep in stayed] == [0.0, 0.0]
    for env, seed, ep in zip(envs, (5, 6), stayed):  # the same episode stepped by hand: its smallest ratio
        env.reset(seed=seed)
        ratios = [env.step(np.zeros(4, np.float32))[4]["target_ratio"] for _ in range(60)]
        assert ep["closest"] == min(ratios) > 1.0
    for env in envs:
        env.close()
