"""Triangle meshes of MuJoCo's primitive geom types, in the geom's own frame (outward faces)."""

from __future__ import annotations

import numpy as np

__all__ = ["primitive_mesh", "SPHERE", "CAPSULE", "ELLIPSOID", "CYLINDER", "BOX"]

# mjtGeom codes
SPHERE, CAPSULE, ELLIPSOID, CYLINDER, BOX = 2, 3, 4, 5, 6


def _uv_sphere(n_lon: int = 16, n_lat: int = 8) -> tuple[np.ndarray, np.ndarray]:
    lat = np.linspace(0.0, np.pi, n_lat + 1)[1:-1]
    lon = np.linspace(0.0, 2 * np.pi, n_lon, endpoint=False)
    ring = np.stack(
        [np.outer(np.sin(lat), np.cos(lon)), np.outer(np.sin(lat), np.sin(lon)), np.outer(np.cos(lat), np.ones(n_lon))],
        axis=-1,
    ).reshape(-1, 3)
    verts = np.vstack([[0, 0, 1], ring, [0, 0, -1]])
    top, bottom = 0, len(verts) - 1
    faces = []
    for j in range(n_lon):
        k = (j + 1) % n_lon
        faces.append((top, 1 + j, 1 + k))
        faces.append((bottom, 1 + (n_lat - 2) * n_lon + k, 1 + (n_lat - 2) * n_lon + j))
        for i in range(n_lat - 2):
            a, b = 1 + i * n_lon + j, 1 + i * n_lon + k
            c, d = a + n_lon, b + n_lon
            faces += [(a, c, b), (b, c, d)]
    return verts.astype(np.float64), np.array(faces, dtype=np.int64)


def _cylinder(radius: float, half_height: float, n: int = 16) -> tuple[np.ndarray, np.ndarray]:
    ang = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    circle = np.stack([radius * np.cos(ang), radius * np.sin(ang)], axis=-1)
    top = np.hstack([circle, np.full((n, 1), half_height)])
    bottom = np.hstack([circle, np.full((n, 1), -half_height)])
    verts = np.vstack([top, bottom, [[0, 0, half_height], [0, 0, -half_height]]])
    ct, cb = 2 * n, 2 * n + 1
    faces = []
    for j in range(n):
        k = (j + 1) % n
        faces += [(ct, j, k), (cb, n + k, n + j), (j, n + j, k), (k, n + j, n + k)]
    return verts, np.array(faces, dtype=np.int64)


def _box(size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    faces = np.array(
        [(0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3), (0, 1, 3), (0, 3, 2),
         (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1), (2, 3, 7), (2, 7, 6)],
        dtype=np.int64,
    )
    return corners * np.asarray(size[:3], dtype=np.float64), faces


def primitive_mesh(geom_type: int, size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and faces (F, 3) of a MuJoCo primitive in its own frame."""
    if geom_type == SPHERE:
        v, f = _uv_sphere()
        return v * float(size[0]), f
    if geom_type == ELLIPSOID:
        v, f = _uv_sphere()
        return v * np.asarray(size[:3], dtype=np.float64), f
    if geom_type == CYLINDER:
        return _cylinder(float(size[0]), float(size[1]))
    if geom_type == CAPSULE:
        v, f = _uv_sphere()
        v = v * float(size[0])
        v[:, 2] += np.sign(v[:, 2]) * float(size[1])  # stretch the sphere into a capsule
        return v, f
    if geom_type == BOX:
        return _box(size)
    raise ValueError(f"unsupported primitive geom type {geom_type}")
