"""The arm-free top-down renderer: geometry by hand, agreement with MuJoCo's GL camera, caches, GL contexts."""

import gc
import json
import os
import subprocess
import sys

import mujoco
import numpy as np
import pytest

from covers_dist.bench.render import render_agreement
from covers_dist.envs.gl_render import GLTopDownRenderer, select_gl_backend
from covers_dist.envs.metaworld_suite import MetaWorldTask
from covers_dist.envs.topdown_render import TopDownRasterizer
from covers_dist.envs.topdown_view import DISC_COLOR, VOID_COLOR, TopDownView, draw_disc

SHAPES_XML = """
<mujoco>
  <worldbody>
    <geom name="floor_box" type="box" size="0.3 0.3 0.01" pos="0 0 -0.01" rgba="0.6 0.6 0.6 1"/>
    <geom name="tall" type="box" size="0.05 0.05 0.2" pos="0.1 0.1 0.2" rgba="1 0 0 1"/>
    <geom name="flat" type="box" size="0.05 0.025 0.01" pos="0.2 0.1 0.0" rgba="0 1 0 1"/>
    <geom name="ball" type="sphere" size="0.04" pos="-0.15 0.1 0.04" rgba="0 0 1 1"/>
    <geom name="can" type="cylinder" size="0.03 0.05" pos="-0.15 -0.15 0.05" rgba="1 1 0 1"/>
    <geom name="pill" type="capsule" size="0.02 0.06" pos="0.15 -0.15 0.03" euler="0 90 30" rgba="0 1 1 1"/>
    <geom name="egg" type="ellipsoid" size="0.06 0.03 0.02" pos="0 -0.2 0.02" euler="0 0 45" rgba="1 0 1 1"/>
    <geom name="tilted" type="box" size="0.04 0.02 0.02" pos="0 0.22 0.05" euler="20 30 40" rgba="1 0.5 0 1"/>
    <body name="slider" pos="-0.05 -0.05 0.02">
      <joint name="slide" type="slide" axis="1 0 0"/>
      <geom name="block" type="box" size="0.02 0.02 0.02" rgba="0.5 0 0.5 1"/>
    </body>
    <site name="marker" type="sphere" size="0.02" pos="0.25 0.25 0.0" rgba="0.2 0.8 0.2 1"/>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def shapes():
    model = mujoco.MjModel.from_xml_string(SHAPES_XML)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


def test_box_covers_the_pixels_computed_by_hand(shapes):
    model, data = shapes
    view = TopDownView((0.0, 0.0), 0.36, 64)
    raster = TopDownRasterizer(model, data, view)
    raster.render()
    ids = raster.last_ids
    flat = model.geom("flat").id
    # pixel centre (i, j) is at x = (j - 31.5) * p, y = (31.5 - i) * p with p = 0.72 / 64
    p, c = 0.72 / 64, 31.5
    cols = [j for j in range(64) if abs((j - c) * p - 0.2) <= 0.05]
    rows = [i for i in range(64) if abs((c - i) * p - 0.1) <= 0.025]
    assert np.array_equal(np.flatnonzero((ids == flat).any(0)), cols)
    assert np.array_equal(np.flatnonzero((ids == flat).any(1)), rows)
    assert (ids == flat).sum() == len(cols) * len(rows)
    # the tall box is seen from straight above: its footprint, not a perspective blow-up
    tall = ids == model.geom("tall").id
    assert tall.sum() == (np.abs((np.arange(64) - c) * p - 0.1) <= 0.05).sum() ** 2
    assert (ids == -1).sum() > 0 and np.all(raster.render()[ids == -1] == VOID_COLOR)


def test_disc_by_hand():
    img = np.zeros((7, 7, 3), dtype=np.uint8)
    draw_disc(img, np.array([3.0, 3.0]), 1.0)
    blue = np.all(img == DISC_COLOR, axis=-1)
    assert blue.sum() == 5 and blue[3, 2:5].all() and blue[2:5, 3].all()
    img = np.zeros((7, 7, 3), dtype=np.uint8)
    draw_disc(img, np.array([-5.0, 3.0]), 1.0)  # off the image: nothing drawn, no error
    assert not img.any()


def test_primitives_and_sites_match_the_gl_camera(shapes):
    model, data = shapes
    for size in (64, 128):
        view = TopDownView((0.0, 0.0), 0.3, size)
        raster = TopDownRasterizer(model, data, view)
        ours = raster.render()
        gl = GLTopDownRenderer(model, data, view, robot_bodies=set())
        try:
            seg, theirs = gl.segmentation(), gl.render()
        finally:
            gl.close()
        agree = (raster.last_ids == seg).mean()
        assert agree > 0.99, f"{size}px: only {agree:.4f} of pixels show the same geom"
        assert np.abs(ours.astype(int) - theirs.astype(int)).mean() < 2.0
        for name in ("tall", "flat", "ball", "can", "pill", "egg", "tilted", "block"):
            assert (raster.last_ids == model.geom(name).id).any(), name
        assert (raster.last_ids == -2 - model.site("marker").id).any()


def test_mesh_winding_does_not_change_the_image():
    """Closed meshes are drawn from their up-turned outward faces, whichever way the file winds them."""
    from covers_dist.envs.tessellation import BOX, primitive_mesh

    verts, faces = primitive_mesh(BOX, np.array([0.1, 0.05, 0.03]))
    images = []
    for wound in (faces, faces[:, ::-1], np.vstack([faces[:6], faces[6:, ::-1]])):  # out, in, mixed
        xml = (
            f'<mujoco><asset><mesh name="m" vertex="{" ".join(map(str, verts.ravel()))}" '
            f'face="{" ".join(map(str, wound.ravel()))}"/></asset><worldbody>'
            '<geom type="mesh" mesh="m" pos="0.05 0 0.03" euler="10 20 30"/></worldbody></mujoco>'
        )
        model = mujoco.MjModel.from_xml_string(xml)
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        raster = TopDownRasterizer(model, data, TopDownView((0.0, 0.0), 0.2, 64))
        images.append((raster.render(), raster.last_ids.copy()))
    assert (images[0][1] == 0).sum() > 300
    for img, ids in images[1:]:
        assert np.array_equal(ids, images[0][1]) and np.array_equal(img, images[0][0])


def test_moving_geoms_are_redrawn_and_static_cache_is_reused(shapes):
    model, data = shapes
    view = TopDownView((0.0, 0.0), 0.3, 64)
    raster = TopDownRasterizer(model, data, view)
    first = raster.render()
    assert raster.render_scene() is raster.render_scene()  # nothing moved: cached
    redraws = raster.redraws
    data.qpos[model.joint("slide").qposadr[0]] = 0.1
    mujoco.mj_forward(model, data)
    moved = raster.render()
    assert raster.redraws == redraws + 1 and not np.array_equal(first, moved)
    fresh = TopDownRasterizer(model, data, view).render()
    assert np.array_equal(moved, fresh)
    data.qpos[:] = 0
    mujoco.mj_forward(model, data)
    assert np.array_equal(raster.render(), first)


@pytest.mark.parametrize("task", ["reach-v3", "button-press-topdown-v3", "drawer-close-v3", "plate-slide-v3"])
def test_metaworld_tasks_match_the_gl_camera(task):
    result = render_agreement(task, image_size=64, states=5, seed=1)
    assert result["segmentation_agreement"] >= 0.995, result
    assert result["color_mae"] < 1.0, result


def test_no_black_frames_after_creating_and_closing_gl_envs():
    """One GL context per env, made current before each frame and freed on close."""
    reference = MetaWorldTask("drawer-close-v3", "r", render_backend="numpy")
    expected = reference.reset(seed=4)[0]["image"]
    reference.close()
    old = MetaWorldTask("drawer-close-v3", "r", render_backend="egl")
    old.reset(seed=4)
    for _ in range(3):
        new = MetaWorldTask("drawer-close-v3", "r", render_backend="egl")
        image = new.reset(seed=4)[0]["image"]
        old.close()  # freeing the older context after the newer one became current
        del old
        gc.collect()
        after = new.step(np.zeros(4, dtype=np.float32))[0]["image"]
        for img in (image, after):
            assert img.max() > 0, "black frame"
            assert np.abs(img.astype(int) - expected.astype(int)).mean() < 2.0
        old = new
    old.close()


def test_gl_backend_choice_errors():
    current = select_gl_backend("auto")
    assert current in ("egl", "osmesa")
    other = "osmesa" if current == "egl" else "egl"
    with pytest.raises(RuntimeError, match=f"MUJOCO_GL={other}"):
        select_gl_backend(other)
    with pytest.raises(ValueError, match="not a GL backend"):
        select_gl_backend("numpy")


def _run_python(code: str, mujoco_gl: str | None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    if mujoco_gl:
        env.update(MUJOCO_GL=mujoco_gl, PYOPENGL_PLATFORM=mujoco_gl)
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)


def test_osmesa_backend_renders_the_same_view():
    code = (
        "import numpy as np\n"
        "from covers_dist.envs.metaworld_suite import MetaWorldTask\n"
        "gl = MetaWorldTask('plate-slide-v3', 'rf', render_backend='osmesa')\n"
        "ref = MetaWorldTask('plate-slide-v3', 'rf', render_backend='numpy')\n"
        "a, b = gl.reset(seed=1)[0]['image'], ref.reset(seed=1)[0]['image']\n"
        "gl.close(); ref.close()\n"
        "print(np.abs(a.astype(int) - b.astype(int)).mean(), a.max())\n"
    )
    res = _run_python(code, "osmesa")
    assert res.returncode == 0, res.stderr[-2000:]
    mae, brightest = map(float, res.stdout.split())
    assert mae < 1.0 and brightest > 0


def test_auto_backend_choice_and_its_error():
    chosen = _run_python(
        "import os\nfrom covers_dist.envs.gl_render import select_gl_backend\n"
        "print(select_gl_backend('auto'), os.environ['MUJOCO_GL'])\n",
        None,
    )
    assert chosen.returncode == 0, chosen.stderr[-2000:]
    name, exported = chosen.stdout.split()
    assert name == exported and name in ("egl", "osmesa")
    failing = _run_python(
        "import covers_dist.envs.gl_render as g\n"
        "g.probe_gl_backend = lambda name, timeout_s=60: 'cannot open display'\n"
        "g.select_gl_backend('auto')\n",
        None,
    )
    assert failing.returncode != 0
    assert "no working MuJoCo GL backend (egl: cannot open display; osmesa: cannot open display)" in failing.stderr


def test_bench_render_cli_prints_the_table_keys(capsys, tmp_path):
    from covers_dist.cli import main

    argv = ["bench", "render", "--tasks", "reach-v3", "--policy", "random", "--steps", "20", "--stock-steps", "5"]
    assert main(argv + ["--repeats", "1", "--json"]) == 0
    row = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("task", "image_size", "physics_steps_per_s", "rendered_steps_per_s", "stock_rendered_steps_per_s", "rendered_to_physics"):
        assert key in row
    assert row["task"] == "reach-v3" and row["image_size"] == 64 and row["rendered_steps_per_s"] > 0
    assert row["rendered_to_physics"] == pytest.approx(row["rendered_steps_per_s"] / row["physics_steps_per_s"], rel=1e-2)
    grid = tmp_path / "grid.png"
    assert main(["bench", "render", "--tasks", "reach-v3", "--grid", str(grid), "--image-size", "32"]) == 0
    from PIL import Image

    assert Image.open(grid).size[0] > 8 * 32
    with pytest.raises(SystemExit, match="unknown task"):
        main(["bench", "render", "--tasks", "reach-v9"])
