import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from covers_dist.config import EnvConfig
from covers_dist.envs import make_task, task_names, transform_obs
from covers_dist.envs.toy import TOY_TASKS, ToyTask, register_toy_envs
from covers_dist.symmetry import D4_ELEMENTS


@pytest.mark.parametrize("task", TOY_TASKS)
@pytest.mark.parametrize("g", D4_ELEMENTS, ids=lambda g: g.name)
def test_transformed_task_is_exactly_equivalent(task, g):
    base, moved = ToyTask(task, "e"), ToyTask(task, g)
    ob, _ = base.reset(seed=3)
    og, _ = moved.reset(seed=3)
    rng = np.random.default_rng(4)
    layout = base.layout
    for _ in range(60):
        exp = transform_obs(layout, g, ob)
        assert np.array_equal(og["image"], exp["image"])
        np.testing.assert_array_equal(og["proprio"], exp["proprio"])
        a = rng.uniform(-1.2, 1.2, size=2).astype(np.float32)
        ob, rb, tb, trb, ib = base.step(a)
        og, rg, tg, trg, ig = moved.step(layout.transform_action(g, a))
        assert rb == rg and tb == tg and trb == trg and ib == ig
        if trb:
            ob, _ = base.reset(seed=5)
            og, _ = moved.reset(seed=5)


@pytest.mark.parametrize("task", TOY_TASKS)
def test_transforms_give_visibly_different_tasks(task):
    images = [ToyTask(task, g).reset(seed=0)[0]["image"] for g in D4_ELEMENTS]
    for i in range(8):
        for j in range(i):
            assert not np.array_equal(images[i], images[j])


def test_groups_are_visually_distinct():
    colors = {}
    for task in TOY_TASKS:
        img = ToyTask(task).reset(seed=0)[0]["image"]
        colors[task] = {tuple(c) for c in img.reshape(-1, 3)}
    assert colors["reach"] != colors["push"] != colors["avoid"] != colors["reach"]


@pytest.mark.parametrize("task", TOY_TASKS)
def test_gymnasium_env_checker(task):
    ids = register_toy_envs()
    env = gym.make(ids[task], g="rf", render_mode="rgb_array")
    check_env(env.unwrapped)
    frame = env.unwrapped.render()
    assert frame.shape == (32, 32, 3) and frame.dtype == np.uint8


def test_observation_contents_and_episode_length():
    env = ToyTask("reach", "r", image_size=16, max_episode_steps=7)
    obs, info = env.reset(seed=0)
    assert obs["image"].shape == (16, 16, 3) and obs["image"].dtype == np.uint8
    assert obs["proprio"].shape == (4,) and obs["proprio"].dtype == np.float32
    assert "success" in info
    steps = 0
    while True:
        obs, r, term, trunc, info = env.step(np.zeros(2, dtype=np.float32))
        steps += 1
        if term or trunc:
            break
    assert steps == 7 and trunc and not term


def test_same_seed_same_episode():
    def rollout(seed):
        env = ToyTask("push", "r2f")
        obs, _ = env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        out = [obs["image"].copy()]
        for _ in range(20):
            obs, r, *_ = env.step(rng.uniform(-1, 1, 2))
            out.append(obs["image"].copy())
            out.append(np.array([r]))
        return out

    a, b = rollout(7), rollout(7)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))


def test_scripted_policy_succeeds_on_every_group():
    for task in TOY_TASKS:
        env = ToyTask(task, "e")
        env.reset(seed=1)
        success = 0.0
        s = env.base_state()
        for _ in range(50):
            s = env.base_state()
            if task == "push":
                u = (s["goal"] - s["block"]) / max(np.linalg.norm(s["goal"] - s["block"]), 1e-9)
                target = s["block"] - 0.1 * u
            elif task == "avoid":
                side = np.array([-s["goal"][1], s["goal"][0]])
                target = s["obstacle"] + 0.3 * side / np.linalg.norm(side) if env._t < 6 else s["goal"]
            else:
                target = s["goal"]
            a = np.clip((target - s["agent"]) / 0.1, -1, 1)
            _, _, _, _, info = env.step(a)
            success = max(success, info["success"])
        assert success == 1.0, task


def test_bad_inputs_give_clear_errors():
    with pytest.raises(ValueError, match="unknown toy task 'fly'"):
        ToyTask("fly")
    with pytest.raises(ValueError, match="even integer"):
        ToyTask("reach", image_size=31)
    env = ToyTask("reach")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="2 finite numbers"):
        env.step(np.array([np.nan, 0.0]))
    with pytest.raises(ValueError, match="unknown toy task 'fly'|unknown toy task"):
        make_task(EnvConfig(), "fly")
    with pytest.raises(ValueError, match="unknown task suite 'atari'"):
        task_names("atari")


def test_factory_builds_transformed_tasks():
    env = make_task(EnvConfig(image_size=16), "avoid", "r3", seed=0)
    assert env.g.name == "r3" and env.image_size == 16
