"""Sim-to-real in-painting, tested on images rendered WITH the arm by MuJoCo's GL camera."""

import numpy as np
import pytest

from covers_dist.envs.gl_render import GLTopDownRenderer
from covers_dist.envs.metaworld_suite import DISC_RADIUS, MetaWorldTask, robot_bodies, table_geoms
from covers_dist.envs.topdown_render import subtree_bodies
from covers_dist.envs.sim2real import (
    arm_mask_from_joints,
    camera_projection,
    color_correct,
    inpaint_arm,
    project_points,
    topdown_projection,
)

ARM_LINKS = ("right_l0", "right_l1", "right_l2", "right_l3", "right_l4", "right_l5", "right_l6", "right_hand", "hand")


@pytest.fixture(scope="module")
def scene():
    """A reach episode seen by two GL cameras of the same view: with the arm and without it."""
    env = MetaWorldTask("reach-v3", "e")
    mw = env.unwrapped_metaworld
    model = mw.model
    robot = robot_bodies(model)
    free = GLTopDownRenderer(model, mw.data, env.view, robot, table_geoms(model))
    with_arm = GLTopDownRenderer(model, mw.data, env.view, set(), table_geoms(model))
    env.reset(seed=0)
    background = free.render()  # the empty scene, taken once before the arm moves in
    for _ in range(30):
        env.step(env.expert_action())
    seg = with_arm.segmentation()
    arm = subtree_bodies(model, robot)
    robot_geoms = [i for i in range(model.ngeom) if int(model.geom_bodyid[i]) in arm]
    out = {
        "env": env,
        "background": background,
        "live": with_arm.render(),
        "arm_mask": np.isin(seg, robot_geoms),
        "reference": free.render(mw.tcp_center, DISC_RADIUS),  # what simulation shows the agent
        "gripper": np.asarray(mw.tcp_center).copy(),
        "joints": np.array([mw.data.body(n).xpos for n in ARM_LINKS] + [mw.tcp_center]),
        "projection": topdown_projection(env.view),
        "disc_px": DISC_RADIUS / env.view.pitch,
    }
    free.close()
    with_arm.close()
    yield out
    env.close()


def _errors(a, b):
    diff = np.abs(a.astype(int) - b.astype(int))
    return float(diff.mean()), float((diff.max(-1) > 10).mean())


def test_arm_is_in_view_before_inpainting(scene):
    assert scene["arm_mask"].mean() > 0.05
    mae, frac = _errors(scene["live"], scene["reference"])
    assert mae > 3.0 and frac > 0.05


def test_inpainting_with_a_mask_recovers_the_arm_free_image(scene):
    out = inpaint_arm(
        scene["live"], scene["background"], scene["gripper"], scene["projection"],
        arm_mask=scene["arm_mask"], disc_radius_px=scene["disc_px"],
    )
    mae, frac = _errors(out, scene["reference"])
    assert mae < 0.1 and frac < 0.002, (mae, frac)


def test_inpainting_from_joint_positions(scene):
    out = inpaint_arm(
        scene["live"], scene["background"], scene["gripper"], scene["projection"],
        joints=scene["joints"], arm_radius_px=8.0, disc_radius_px=scene["disc_px"],
    )
    mae, frac = _errors(out, scene["reference"])
    assert mae < 1.0 and frac < 0.01, (mae, frac)


def test_color_correction_matches_new_lighting(scene):
    """The live camera sees dimmer, warmer light than when the background was taken."""
    gain, offset = np.array([0.8, 0.75, 0.7]), np.array([12.0, 8.0, 4.0])

    def relight(img):
        return np.clip(np.round(img * gain + offset), 0, 255).astype(np.uint8)

    live, reference = relight(scene["live"]), relight(scene["reference"])
    kwargs = dict(arm_mask=scene["arm_mask"], disc_radius_px=scene["disc_px"])
    corrected = inpaint_arm(live, scene["background"], scene["gripper"], scene["projection"], **kwargs)
    plain = inpaint_arm(live, scene["background"], scene["gripper"], scene["projection"], correct_colors=False, **kwargs)
    m = scene["arm_mask"]
    err_corrected = np.abs(corrected[m].astype(int) - reference[m].astype(int)).mean()
    err_plain = np.abs(plain[m].astype(int) - reference[m].astype(int)).mean()
    assert err_corrected < 1.5 and err_plain > 10 * err_corrected, (err_corrected, err_plain)


def test_color_correct_by_hand():
    rng = np.random.default_rng(0)
    bg = rng.integers(0, 200, size=(8, 8, 3)).astype(np.uint8)
    img = np.clip(bg * 1.1 + 5, 0, 255).round().astype(np.uint8)
    out = color_correct(bg, img, np.ones((8, 8), dtype=bool))
    assert np.abs(out.astype(int) - img.astype(int)).max() <= 1


def test_projections(scene):
    env = scene["env"]
    pts = np.array([[0.0, 0.6, 0.3], [0.1, 0.5, 0.0]])
    np.testing.assert_allclose(project_points(pts, scene["projection"]), env.view.to_pixels(pts[:, :2]), atol=1e-9)
    mask = arm_mask_from_joints(np.array([[0.0, 0.6, 0.2], [0.1, 0.6, 0.2]]), scene["projection"], (64, 64), 2.0)
    centre = env.view.to_pixels(np.array([0.05, 0.6]))
    assert mask[int(round(centre[1])), int(round(centre[0]))] and mask.sum() < 200


def test_perspective_camera_projection_agrees_with_gl():
    """Meta-World's perspective top view: projected object centres land on the object's pixels."""
    import mujoco

    env = MetaWorldTask("button-press-topdown-v3", "e")
    env.reset(seed=0)
    mw = env.unwrapped_metaworld
    size = 96
    renderer = mujoco.Renderer(mw.model, size, size)
    try:
        renderer.enable_segmentation_rendering()
        renderer.update_scene(mw.data, camera="topview")
        seg = renderer.render()[..., 0]
    finally:
        renderer.close()
    proj = camera_projection(mw.model, mw.data, "topview", size, size)
    button = mw.model.geom("btnGeom").id
    col, row = project_points(mw.data.geom_xpos[button][None], proj)[0]
    rows, cols = np.nonzero(seg == button)
    assert len(rows) > 0
    assert abs(cols.mean() - col) < 2.0 and abs(rows.mean() - row) < 2.0
    env.close()


def test_bad_input(scene):
    live, bg = scene["live"], scene["background"]
    with pytest.raises(ValueError, match="exactly one of"):
        inpaint_arm(live, bg, scene["gripper"], scene["projection"])
    with pytest.raises(ValueError, match="exactly one of"):
        inpaint_arm(live, bg, scene["gripper"], scene["projection"], arm_mask=scene["arm_mask"], joints=scene["joints"])
    with pytest.raises(ValueError, match="background"):
        inpaint_arm(live, bg[:32], scene["gripper"], scene["projection"], arm_mask=scene["arm_mask"])
    with pytest.raises(ValueError, match="arm_mask"):
        inpaint_arm(live, bg, scene["gripper"], scene["projection"], arm_mask=scene["arm_mask"].astype(int))
    with pytest.raises(ValueError, match="3x4"):
        project_points(np.zeros((1, 3)), np.eye(3))
