"""Sim-to-real preprocessing (COVERS paper, appendix B.1): paint the robot arm out of a camera image.

On the real robot the policy must see what it saw in simulation: the table and objects without
the arm, and a blue disc where the gripper is. :func:`inpaint_arm` does that to a camera image:

1. the arm's pixels are given as a binary mask, or computed from the arm's 3-D joint positions
   and the camera's 3x4 projection matrix (:func:`arm_mask_from_joints`: thick segments between
   consecutive joints);
2. those pixels are replaced by a background image of the scene taken without the arm, after a
   colour correction that maps the background's colours onto the current image's lighting
   (a per-channel gain and offset fitted on the pixels outside the mask, :func:`color_correct`);
3. a blue disc is drawn at the projected gripper position.

Projection matrices map homogeneous world points to homogeneous pixel coordinates
``(column, row, 1)`` with pixel centres at integers (row 0 at the top):
:func:`topdown_projection` for the orthographic top-down view, :func:`camera_projection` for a
MuJoCo (perspective) camera.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .topdown_view import DISC_COLOR, TopDownView, draw_disc

__all__ = [
    "inpaint_arm",
    "arm_mask_from_joints",
    "color_correct",
    "project_points",
    "topdown_projection",
    "camera_projection",
]


def project_points(points: np.ndarray, projection: np.ndarray) -> np.ndarray:
    """World points (N, 3) -> pixel (column, row) (N, 2) through a 3x4 projection matrix."""
    points = np.asarray(points, dtype=np.float64)
    projection = np.asarray(projection, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    if projection.shape != (3, 4):
        raise ValueError(f"projection must be a 3x4 matrix, got shape {projection.shape}")
    h = np.hstack([points, np.ones((len(points), 1))]) @ projection.T
    if np.any(h[:, 2] <= 0):
        raise ValueError("a point lies behind the camera (non-positive homogeneous depth)")
    return h[:, :2] / h[:, 2:3]


def topdown_projection(view: TopDownView) -> np.ndarray:
    """The 3x4 projection of the orthographic top-down ``view`` (height is ignored)."""
    c = (view.size - 1) / 2.0
    p = view.pitch
    return np.array(
        [
            [1.0 / p, 0.0, 0.0, c - view.centre[0] / p],
            [0.0, -1.0 / p, 0.0, c + view.centre[1] / p],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def camera_projection(model: Any, data: Any, camera: str | int, width: int, height: int) -> np.ndarray:
    """The 3x4 projection of a fixed MuJoCo camera (perspective, ``fovy`` from the model)."""
    import mujoco

    cam = camera if isinstance(camera, int) else mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    if cam < 0 or cam >= model.ncam:
        raise ValueError(f"unknown camera {camera!r}")
    if model.cam_orthographic[cam]:
        raise ValueError(f"camera {camera!r} is orthographic; use topdown_projection for orthographic views")
    fovy = np.deg2rad(float(model.cam_fovy[cam]))
    f = 0.5 * height / np.tan(fovy / 2.0)
    intrinsics = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    # MuJoCo cameras look along their -z axis with +y up; image rows grow downwards
    rot = np.asarray(data.cam_xmat[cam], dtype=np.float64).reshape(3, 3)
    world_to_cam = np.diag([1.0, -1.0, -1.0]) @ rot.T
    t = -world_to_cam @ np.asarray(data.cam_xpos[cam], dtype=np.float64)
    return intrinsics @ np.hstack([world_to_cam, t[:, None]])


def arm_mask_from_joints(
    joints: np.ndarray, projection: np.ndarray, shape: tuple[int, int], radius_px: float
) -> np.ndarray:
    """Binary mask of the arm: pixels within ``radius_px`` of the projected chain of joints (J, 3)."""
    if radius_px <= 0:
        raise ValueError(f"radius_px must be > 0, got {radius_px}")
    pts = project_points(joints, projection)
    h, w = shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    mask = np.zeros((h, w), dtype=bool)
    segments = list(zip(pts[:-1], pts[1:])) if len(pts) > 1 else [(pts[0], pts[0])]
    for a, b in segments:
        d = b - a
        length2 = float(d @ d)
        t = 0.0 if length2 == 0 else np.clip(((cols - a[0]) * d[0] + (rows - a[1]) * d[1]) / length2, 0.0, 1.0)
        dist2 = (cols - a[0] - t * d[0]) ** 2 + (rows - a[1] - t * d[1]) ** 2
        mask |= dist2 <= radius_px * radius_px
    return mask


def color_correct(background: np.ndarray, image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``background`` with per-channel gain and offset fitted so that it matches ``image`` on ``valid``."""
    bg = background.reshape(-1, background.shape[-1]).astype(np.float64)
    im = image.reshape(-1, image.shape[-1]).astype(np.float64)
    sel = valid.reshape(-1)
    out = bg.copy()
    if sel.sum() < 2:
        return background.copy()
    for ch in range(bg.shape[1]):
        x, y = bg[sel, ch], im[sel, ch]
        var = x.var()
        gain = ((x - x.mean()) * (y - y.mean())).mean() / var if var > 1e-9 else 1.0
        offset = y.mean() - gain * x.mean()
        out[:, ch] = gain * bg[:, ch] + offset
    return np.clip(np.round(out), 0, 255).astype(np.uint8).reshape(background.shape)


def inpaint_arm(
    image: np.ndarray,
    background: np.ndarray,
    gripper_xyz: np.ndarray,
    projection: np.ndarray,
    arm_mask: np.ndarray | None = None,
    joints: np.ndarray | None = None,
    arm_radius_px: float = 4.0,
    disc_radius_px: float = 3.0,
    correct_colors: bool = True,
    disc_color: np.ndarray = DISC_COLOR,
) -> np.ndarray:
    """The camera ``image`` with the arm replaced by ``background`` and a disc at the gripper.

    Give either ``arm_mask`` (bool (H, W)) or ``joints`` ((J, 3) world positions along the arm,
    projected with ``projection`` into a mask of thick segments of ``arm_radius_px``).
    ``gripper_xyz`` is projected with ``projection`` for the disc of ``disc_radius_px``.
    """
    image = np.asarray(image)
    background = np.asarray(background)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be uint8 (H, W, 3), got {image.dtype} {image.shape}")
    if background.shape != image.shape or background.dtype != np.uint8:
        raise ValueError(
            f"background must be uint8 of the image's shape {image.shape}, got {background.dtype} {background.shape}"
        )
    if (arm_mask is None) == (joints is None):
        raise ValueError("give exactly one of arm_mask or joints")
    if arm_mask is None:
        arm_mask = arm_mask_from_joints(np.asarray(joints), projection, image.shape[:2], arm_radius_px)
    arm_mask = np.asarray(arm_mask)
    if arm_mask.shape != image.shape[:2] or arm_mask.dtype != bool:
        raise ValueError(f"arm_mask must be bool of shape {image.shape[:2]}, got {arm_mask.dtype} {arm_mask.shape}")
    fill = color_correct(background, image, ~arm_mask) if correct_colors else background
    out = image.copy()
    out[arm_mask] = fill[arm_mask]
    centre = project_points(np.asarray(gripper_xyz, dtype=np.float64).reshape(1, 3), projection)[0]
    draw_disc(out, centre, disc_radius_px, disc_color)
    return out
