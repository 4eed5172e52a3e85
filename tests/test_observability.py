"""Every registered Meta-World task is observable: what decides success is in the first observation."""

import numpy as np
import pytest
from test_metaworld_suite import _scripted_actions

from covers_dist.envs import transform_obs
from covers_dist.envs.metaworld_suite import SYMMETRY_CENTRE, TASKS, MetaWorldTask, metaworld_layout, register_task
from covers_dist.envs.observability import check_observability
from covers_dist.symmetry import GroupElement

RESETS = 64
REACH_Z = 0.15


@pytest.fixture(scope="module")
def reach_envs():
    """Goal Reach as registered (goal height held) and with Meta-World's own goal sampling."""
    envs = {"fixed": MetaWorldTask("reach-v3"), "sampled": MetaWorldTask("reach-v3", observable=False)}
    yield envs
    for env in envs.values():
        env.close()


@pytest.mark.parametrize("task", list(TASKS))
def test_every_registered_task_is_observable(task):
    env = MetaWorldTask(task, image_size=64)
    report = check_observability(env, RESETS, seed=0)
    env.close()
    assert report.ok, str(report)
    assert report.keys == TASKS[task].success_state
    assert all(spread <= 1e-6 for spread in report.z_spread.values()), str(report)
    # placements do vary, so the check is not vacuous
    assert max(report.xy_spread.values()) > 0.1, str(report)
    assert report.distinct_observations >= RESETS - 2, str(report)
    assert not [c for c in report.collisions if not c.subpixel]


def test_success_state_follows_metaworld():
    assert TASKS["reach-v3"].success_state == ("goal",)  # the puck plays no role in reach-v3
    for task in ("button-press-topdown-v3", "drawer-close-v3", "plate-slide-v3"):
        assert TASKS[task].success_state == ("object", "goal")
    assert TASKS["reach-v3"].goal_z == REACH_Z
    assert all(TASKS[t].goal_z is None for t in TASKS if t != "reach-v3")


def test_metaworld_goal_sampling_is_flagged(reach_envs):
    report = check_observability(reach_envs["sampled"], RESETS, seed=0)
    assert not report.ok
    assert 0.15 < report.z_spread["goal"] <= 0.25 + 1e-9, str(report)  # Meta-World: z in 0.05..0.3
    assert any("goal: z varies" in v for v in report.violations)
    assert "NOT observable" in str(report)
    # direct twins: the same seeds with and without the held height give the same first
    # observation but goals at different heights
    twins = check_observability(reach_envs["fixed"], 16, seed=100, twin=reach_envs["sampled"])
    assert not twins.ok and twins.z_spread["goal"] == 0.0
    assert len([c for c in twins.collisions if not c.subpixel]) == 16, str(twins)


def test_held_goal_height_is_where_metaworld_looks(reach_envs):
    fixed, sampled = reach_envs["fixed"], reach_envs["sampled"]
    for seed in (0, 1, 2, 3):
        obs, _ = fixed.reset(seed=seed)
        other, _ = sampled.reset(seed=seed)
        # the agent sees the same thing; only the hidden height differs
        assert np.array_equal(obs["image"], other["image"]) and np.array_equal(obs["proprio"], other["proprio"])
        differs = np.flatnonzero(fixed._mw_obs != sampled._mw_obs)
        assert set(differs) <= {len(fixed._mw_obs) - 1}  # Meta-World's vector: only the goal's z
        goal = fixed.task_state()["goal_base"]
        np.testing.assert_array_equal(goal[:2], sampled.task_state()["goal_base"][:2])
        assert goal[2] == REACH_Z and fixed._mw_obs[-1] == REACH_Z
        mw = fixed.unwrapped_metaworld
        assert mw._target_pos[2] == REACH_Z
        np.testing.assert_allclose(mw.data.site("goal").xpos, goal + [*SYMMETRY_CENTRE, 0.0], atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_scripted_expert_reaches_the_held_goal(reach_envs, seed):
    """The expert reads the goal from Meta-World's vector and Meta-World judges success on its own
    target: success means both hold the same goal."""
    env = reach_envs["fixed"]
    env.reset(seed=seed)
    success = False
    for _ in range(150):
        _, _, _, _, info = env.step(env.expert_action())
        assert env._mw_obs[-1] == REACH_Z and env.unwrapped_metaworld._target_pos[2] == REACH_Z
        if info["success"] == 1.0:
            success = True
            break
    assert success, f"seed {seed}: the expert did not reach the goal within 150 steps"
    hand, goal = env.task_state()["hand_base"], env.task_state()["goal_base"]
    assert np.linalg.norm(hand - goal) <= 0.05 and abs(hand[2] - REACH_Z) <= 0.05


@pytest.mark.parametrize("g", ["r", "r2f"])
def test_transformed_reach_with_held_goal_is_exactly_equivalent(g):
    steps, seed = 60, 11
    layout = metaworld_layout(64)
    base = MetaWorldTask("reach-v3", "e", max_episode_steps=steps)
    run = _scripted_actions(base, steps, seed)
    base.close()
    assert max(run["success"]) == 1.0
    element = GroupElement.from_name(g)
    env = MetaWorldTask("reach-v3", element, max_episode_steps=steps)
    obs, _ = env.reset(seed=seed)
    assert env.task_state()["goal"][2] == REACH_Z
    for t in range(steps + 1):
        expected = transform_obs(layout, element, run["obs"][t])
        assert np.array_equal(obs["image"], expected["image"]), f"{g} step {t}: image differs"
        np.testing.assert_array_equal(obs["proprio"], expected["proprio"])
        if t == steps:
            break
        obs, r, _, trunc, info = env.step(layout.transform_action(element, run["action"][t]))
        assert r == run["reward"][t] and info["success"] == run["success"][t] and trunc == run["trunc"][t]
    env.close()


def test_goal_height_options_are_checked():
    with pytest.raises(ValueError, match="goal_z"):
        register_task("reach-v3", goal_z=float("nan"))
    with pytest.raises(ValueError, match="success_state"):
        register_task("reach-v3", success_state=("puck",))
    with pytest.raises(ValueError, match="success_state"):
        register_task("reach-v3", success_state=())
    with pytest.raises(TypeError, match="observable"):
        MetaWorldTask("reach-v3", observable=1)
    original = TASKS["button-press-topdown-v3"]
    register_task("button-press-topdown-v3", "Button Press", goal_z=0.1)
    try:  # the button's goal is its hole, derived from the button box: no height to hold
        with pytest.raises(ValueError, match="goal_z needs"):
            MetaWorldTask("button-press-topdown-v3")
    finally:
        TASKS["button-press-topdown-v3"] = original
    assert TASKS["reach-v3"].goal_z == REACH_Z  # the failed registrations changed nothing
