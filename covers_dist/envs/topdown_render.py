"""Arm-free, top-down, orthographic rendering of a MuJoCo scene, rasterized in numpy.

The renderer reads MuJoCo's own geometry: every visible geom and site (groups 0-2, alpha > 0)
that is not part of the robot becomes a triangle mesh in its own frame (mesh geoms use the
model's vertices and faces; boxes, spheres, ellipsoids, cylinders and capsules are tessellated),
is posed each frame from ``data.geom_xpos/xmat`` (``site_xpos/xmat``), and is drawn with a
z-buffer as seen by an orthographic camera looking straight down. Only pixel centres are
sampled (no anti-aliasing), like MuJoCo's GL renderer without multisampling. Faces are lit with
the model's own lights (headlight from above plus the directional lights, diffuse only), so
colours follow what the GL camera shows, without textures, specular highlights or shadows.

Caches make it cheap: the geoms that cannot move (no joint in their body chain) are drawn once
into a static layer; the layer with the moving ones is redrawn only once one of their vertices
has moved by more than :data:`MAX_VERTEX_ERROR` (0.2 mm) since it was drawn, and their per-face
set-up is reused while their orientations stay within half that (slide joints never rotate).
So a frame may show moving objects up to 0.2 mm from their exact pose; identical histories
(a task and its transformed copy, or two runs with one seed) give identical frames.

The gripper is not drawn from geometry: like the real-robot in-painting of the COVERS paper, a
blue disc is painted at its (x, y) position (:mod:`covers_dist.envs.topdown_view` defines the
view, its pixel convention and the disc).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .tessellation import primitive_mesh
from .topdown_view import DISC_COLOR, TABLE_COLOR, VOID_COLOR, TopDownView, disc_pixels, draw_disc

__all__ = [
    "TopDownView",
    "TopDownRasterizer",
    "DISC_COLOR",
    "TABLE_COLOR",
    "VOID_COLOR",
    "MAX_VERTEX_ERROR",
    "draw_disc",
    "disc_pixels",
    "primitive_mesh",
    "subtree_bodies",
]

#: The moving geoms are redrawn once one of their vertices would be more than this far (metres;
#: 2% of a pixel at 64 px) from where it was drawn, so objects that rock in place (contact
#: chatter of about 1e-5 m and 2e-3 rad per step) do not force a redraw every step.
MAX_VERTEX_ERROR = 2e-4
_DEFAULT_RGBA = np.array([0.5, 0.5, 0.5, 1.0], dtype=np.float32)
_TABLE_RGBA = np.append(TABLE_COLOR / 255.0, 1.0).astype(np.float32)
_GEOM, _SITE = 0, 1
_PLANE, _HFIELD, _MESH = 0, 1, 7  # mjtGeom codes


# ---- the rasterizer ---------------------------------------------------------------------------
@dataclass
class _Item:
    kind: int  # _GEOM or _SITE
    index: int
    verts: np.ndarray  # (V, 3) in the item's frame
    faces: np.ndarray  # (F, 3)
    rgba: np.ndarray  # (4,) float
    dynamic: bool
    closed: bool = False  # a closed surface with outward faces: faces turned down are never seen

    def __post_init__(self) -> None:
        self.faces, self.closed = _orient(self.verts, self.faces)


def _orient(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, bool]:
    """``faces`` wound outwards if they form a closed, consistently wound surface, and whether they do.

    Then the surface seen from above is made of faces whose outward normal points up, so the
    others can be skipped; open or inconsistently wound meshes keep every face.
    """
    if len(faces) < 4 or len(np.unique(faces, axis=None)) < 4:
        return faces, False
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    n = int(faces.max()) + 1
    key, reverse = edges[:, 0] * n + edges[:, 1], edges[:, 1] * n + edges[:, 0]
    if len(np.unique(key)) != len(key) or not np.isin(reverse, key).all():
        return faces, False
    tri = verts[faces]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum()
    return (faces if volume > 0 else faces[:, ::-1].copy()), True


class _Batch:
    """Several items' triangles in one set of arrays, posed and drawn together."""

    def __init__(self, items: list[_Item]) -> None:
        self.geoms = np.array([it.index for it in items if it.kind == _GEOM], dtype=np.int64)
        self.sites = np.array([it.index for it in items if it.kind == _SITE], dtype=np.int64)
        ordered = [it for it in items if it.kind == _GEOM] + [it for it in items if it.kind == _SITE]
        self.empty = not ordered
        if self.empty:
            return
        offsets = np.cumsum([0] + [len(it.verts) for it in ordered])
        self.item_verts = [it.verts for it in ordered]
        self.faces = np.concatenate([it.faces + offsets[i] for i, it in enumerate(ordered)])
        self.fitem = np.concatenate([np.full(len(it.faces), i) for i, it in enumerate(ordered)])
        self.rgb = np.concatenate([np.repeat(it.rgba[None, :3], len(it.faces), 0) for it in ordered]).astype(np.float64)
        self.closed = np.concatenate([np.full(len(it.faces), it.closed) for it in ordered])
        self.ids = np.concatenate(
            [np.full(len(it.faces), it.index if it.kind == _GEOM else -2 - it.index, dtype=np.int32) for it in ordered]
        )
        # a rotation change dR moves a vertex at distance r from the origin by <= |dR|_F * r
        self.radius = np.array([float(np.linalg.norm(it.verts, axis=1).max()) for it in ordered])

    def poses(self, data: Any) -> tuple[np.ndarray, np.ndarray]:
        """Positions (N, 3) and rotation matrices (N, 9) of the items, geoms first (copies)."""
        if not len(self.sites):
            return data.geom_xpos[self.geoms], data.geom_xmat[self.geoms]
        pos = np.concatenate([data.geom_xpos[self.geoms], data.site_xpos[self.sites]])
        mat = np.concatenate([data.geom_xmat[self.geoms], data.site_xmat[self.sites]])
        return pos, mat


class TopDownRasterizer:
    """Renders ``data``'s current state of ``model`` top-down, without the robot.

    ``robot_bodies``: ids of the bodies (with their subtrees) not to draw. ``table_geoms``:
    geom ids drawn in :data:`TABLE_COLOR` instead of their (textured) material.
    :meth:`render` returns the colour image (S, S, 3) uint8; :attr:`last_ids` holds, per pixel,
    the drawn item as ``geom id`` (>= 0), ``-2 - site id`` for sites, or -1 where nothing is seen.
    Call :meth:`invalidate` after changing the model (a task reset moves static bodies).
    """

    def __init__(
        self,
        model: Any,
        data: Any,
        view: TopDownView,
        robot_bodies: set[int] | frozenset[int] = frozenset(),
        table_geoms: set[int] | frozenset[int] = frozenset(),
    ) -> None:
        self.model, self.data, self.view = model, data, view
        hidden = subtree_bodies(model, set(robot_bodies))
        items: list[_Item] = []
        for i in range(model.ngeom):
            body = int(model.geom_bodyid[i])
            gtype = int(model.geom_type[i])
            rgba = _TABLE_RGBA if i in table_geoms else _geom_rgba(model, i)
            if body in hidden or model.geom_group[i] > 2 or rgba[3] <= 0 or gtype in (_PLANE, _HFIELD):
                continue
            if gtype == _MESH:
                mid = int(model.geom_dataid[i])
                va, vn = int(model.mesh_vertadr[mid]), int(model.mesh_vertnum[mid])
                fa, fn = int(model.mesh_faceadr[mid]), int(model.mesh_facenum[mid])
                verts = np.asarray(model.mesh_vert[va : va + vn], dtype=np.float64)
                faces = np.asarray(model.mesh_face[fa : fa + fn], dtype=np.int64)
            else:
                verts, faces = primitive_mesh(gtype, model.geom_size[i])
            items.append(_Item(_GEOM, i, verts, faces, rgba, _moves(model, body)))
        for i in range(model.nsite):
            body = int(model.site_bodyid[i])
            rgba = _site_rgba(model, i)
            if body in hidden or model.site_group[i] > 2 or rgba[3] <= 0:
                continue
            verts, faces = primitive_mesh(int(model.site_type[i]), model.site_size[i])
            items.append(_Item(_SITE, i, verts, faces, rgba, _moves(model, body)))
        self.items = items
        self._static = _Batch([it for it in items if not it.dynamic])
        self._dynamic = _Batch([it for it in items if it.dynamic])
        self._ambient, self._light_dirs, self._light_diffuse = self._light_setup(model)
        s = view.size
        c = (s - 1) / 2.0
        self._x0 = view.centre[0] - c * view.pitch  # world x of column 0
        self._y0 = view.centre[1] + c * view.pitch  # world y of row 0
        self._static_layer: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._scene: tuple[np.ndarray, np.ndarray] | None = None
        self._prep: _Prepared | None = None  # per-face set-up of the moving geoms ...
        self._prep_mat = np.zeros((0, 9))  # ... for these orientations
        self._drawn_pos = np.zeros((0, 3))  # where they were last drawn
        self.last_ids = np.full((s, s), -1, dtype=np.int32)
        self.redraws = 0  # how often moving geoms forced a redraw (for benchmarks)

    # ---- public -------------------------------------------------------------------------------
    def invalidate(self) -> None:
        """Forget the cached layers (after the model changed, e.g. at a task reset)."""
        self._static_layer = None
        self._scene = None
        self._prep = None

    def render_scene(self) -> tuple[np.ndarray, np.ndarray]:
        """(colour, ids) of the scene without the gripper disc (cached: do not modify them)."""
        if self._static_layer is None:
            s = self.view.size
            color = np.empty((s * s, 3), dtype=np.uint8)
            color[:] = VOID_COLOR
            zbuf = np.full(s * s, -np.inf)
            ids = np.full(s * s, -1, dtype=np.int32)
            if not self._static.empty:
                pos, mat = self._static.poses(self.data)
                self._raster(self._prepare(self._static, mat), pos, color, zbuf, ids)
            self._static_layer = (color, zbuf, ids)
        if self._dynamic.empty:
            if self._scene is None:
                self._scene = self._finish(self._static_layer[0].copy(), self._static_layer[2].copy())
            return self._scene
        pos, mat = self._dynamic.poses(self.data)
        if self._prep is not None:
            # how far any vertex is from where it was drawn: position change + rotation change * radius
            turned = np.sqrt(((mat - self._prep_mat) ** 2).sum(1)) * self._dynamic.radius
            moved = np.sqrt(((pos - self._drawn_pos) ** 2).sum(1))
            if self._scene is not None and np.all(moved + turned <= MAX_VERTEX_ERROR):
                return self._scene
        if self._prep is None or np.any(turned > MAX_VERTEX_ERROR / 2):
            self._prep, self._prep_mat = self._prepare(self._dynamic, mat), mat
        color, zbuf, ids = (x.copy() for x in self._static_layer)
        self._raster(self._prep, pos, color, zbuf, ids)
        self._drawn_pos = pos
        self._scene = self._finish(color, ids)
        self.redraws += 1
        return self._scene

    def _finish(self, color: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = self.view.size
        return color.reshape(s, s, 3), ids.reshape(s, s)

    def render(self, disc_xy: np.ndarray | None = None, disc_radius: float = 0.03) -> np.ndarray:
        """The scene with a blue disc of radius ``disc_radius`` metres at world ``disc_xy``."""
        color, ids = self.render_scene()
        self.last_ids = ids
        img = color.copy()
        if disc_xy is not None:
            draw_disc(img, self.view.to_pixels(np.asarray(disc_xy)[:2]), disc_radius / self.view.pitch)
        return img

    # ---- internals ----------------------------------------------------------------------------
    @staticmethod
    def _light_setup(model: Any) -> tuple[float, np.ndarray, np.ndarray]:
        return light_setup(model)

    def _prepare(self, batch: _Batch, mat: np.ndarray) -> "_Prepared":
        """Per-face data that depends only on the items' orientations (not on their positions)."""
        inv_p = 1.0 / self.view.pitch
        rotated = [v @ m.reshape(3, 3).T for v, m in zip(batch.item_verts, mat)]
        tri = np.concatenate(rotated)[batch.faces]  # (F, 3, 3), each item's origin at 0
        col, row, z = tri[..., 0] * inv_p, -tri[..., 1] * inv_p, tri[..., 2]
        c0, c1, c2 = col[:, 0], col[:, 1], col[:, 2]
        r0, r1, r2 = row[:, 0], row[:, 1], row[:, 2]
        den = (c1 - c0) * (r2 - r0) - (c2 - c0) * (r1 - r0)
        # faces seen edge-on are skipped, and so are the down-turned faces of closed outward
        # surfaces (den < 0 <=> the face turns up, since rows grow downwards); every other face
        # may be the top surface somewhere (not all mesh files wind their faces consistently)
        keep = np.flatnonzero((np.abs(den) > 1e-12) & ((den < 0) | ~batch.closed))
        c0, c1, c2, r0, r1, r2, den = c0[keep], c1[keep], c2[keep], r0[keep], r1[keep], r2[keep], den[keep]
        z0 = z[keep, 0]
        dz1, dz2 = z[keep, 1] - z0, z[keep, 2] - z0
        # barycentric l1, l2 and the height as affine functions a * col + b * row + c of a pixel
        a1, b1 = (r2 - r0) / den, (c0 - c2) / den
        a2, b2 = (r0 - r1) / den, (c1 - c0) / den
        coef = np.empty((len(keep), 9))
        coef[:, 0], coef[:, 1], coef[:, 2] = a1, b1, -(a1 * c0 + b1 * r0)
        coef[:, 3], coef[:, 4], coef[:, 5] = a2, b2, -(a2 * c0 + b2 * r0)
        coef[:, 6], coef[:, 7] = a1 * dz1 + a2 * dz2, b1 * dz1 + b2 * dz2
        coef[:, 8] = z0 - coef[:, 6] * c0 - coef[:, 7] * r0
        cols, rows = col[keep], row[keep]
        extent = np.stack([cols.min(1), cols.max(1), rows.min(1), rows.max(1)], axis=1)
        colors = self._shade(batch.rgb[keep], tri[keep])
        return _Prepared(batch.fitem[keep], extent, coef, colors, batch.ids[keep])

    def _raster(self, prep: "_Prepared", pos: np.ndarray, color: np.ndarray, zbuf: np.ndarray, ids: np.ndarray) -> None:
        """Z-buffer the prepared faces, their items placed at ``pos``, sampling pixel centres."""
        if not len(prep.fitem):
            return
        s = self.view.size
        inv_p = 1.0 / self.view.pitch
        oc = ((pos[:, 0] - self._x0) * inv_p)[prep.fitem]  # each face's item origin, in pixels
        orow = ((self._y0 - pos[:, 1]) * inv_p)[prep.fitem]
        ext = prep.extent
        cmin = np.maximum(np.ceil(ext[:, 0] + oc), 0.0)
        cmax = np.minimum(np.floor(ext[:, 1] + oc), s - 1.0)
        rmin = np.maximum(np.ceil(ext[:, 2] + orow), 0.0)
        rmax = np.minimum(np.floor(ext[:, 3] + orow), s - 1.0)
        w, h = cmax - cmin + 1.0, rmax - rmin + 1.0
        sel = np.flatnonzero((w > 0) & (h > 0))
        if not len(sel):
            return
        coef = prep.coef[sel]
        ocs, ors = oc[sel], orow[sel]
        coef[:, 2] -= coef[:, 0] * ocs + coef[:, 1] * ors
        coef[:, 5] -= coef[:, 3] * ocs + coef[:, 4] * ors
        coef[:, 8] += pos[prep.fitem[sel], 2] - coef[:, 6] * ocs - coef[:, 7] * ors
        ww = w[sel].astype(np.int64)
        counts = ww * h[sel].astype(np.int64)
        t = np.repeat(np.arange(len(sel)), counts)
        k = np.arange(len(t)) - np.repeat(np.cumsum(counts) - counts, counts)
        wt = ww[t]
        pc = cmin[sel][t] + (k % wt)
        pr = rmin[sel][t] + (k // wt)
        g = coef[t]
        l1 = g[:, 0] * pc + g[:, 1] * pr + g[:, 2]
        l2 = g[:, 3] * pc + g[:, 4] * pr + g[:, 5]
        inside = (l1 >= -1e-9) & (l2 >= -1e-9) & (l1 + l2 <= 1.0 + 1e-9)
        t, pc, pr, g = t[inside], pc[inside], pr[inside], g[inside]
        if not len(t):
            return
        z = g[:, 6] * pc + g[:, 7] * pr + g[:, 8]
        pix = (pr * s + pc).astype(np.int64)
        before = zbuf[pix]
        np.maximum.at(zbuf, pix, z)
        win = np.flatnonzero((z > before) & (z == zbuf[pix]))
        if not len(win):
            return
        faces = sel[t[win]]
        color[pix[win]] = prep.colors[faces]
        ids[pix[win]] = prep.ids[faces]

    def _shade(self, rgb: np.ndarray, tri: np.ndarray) -> np.ndarray:
        """Diffuse lighting of faces seen from above: colours (N, 3) uint8."""
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        n = np.empty_like(e1)
        n[:, 0] = e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1]
        n[:, 1] = e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2]
        n[:, 2] = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        n *= (np.sign(n[:, 2]) / np.sqrt((n * n).sum(1)))[:, None]  # unit normals facing up
        light = self._ambient + np.maximum(n @ self._light_dirs.T, 0.0) @ self._light_diffuse
        return (np.minimum(rgb * light[:, None], 1.0) * 255.0 + 0.5).astype(np.uint8)


@dataclass
class _Prepared:
    fitem: np.ndarray  # (F,) item of each face
    extent: np.ndarray  # (F, 4) column min/max, row min/max relative to the item origin (pixels)
    coef: np.ndarray  # (F, 9) barycentric l1, l2 and height as affine functions of (column, row)
    colors: np.ndarray  # (F, 3) uint8 shaded colour
    ids: np.ndarray  # (F,) geom id or -2 - site id


def subtree_bodies(model: Any, roots: set[int]) -> set[int]:
    """``roots`` and every body below them."""
    out = set(roots)
    for b in range(model.nbody):
        a = b
        while a != 0 and a not in roots:
            a = int(model.body_parentid[a])
        if a in roots:
            out.add(b)
    return out


def _moves(model: Any, body: int) -> bool:
    """Whether a joint or a mocap body in the chain from ``body`` to the world can move it."""
    while body != 0:
        if model.body_jntnum[body] > 0 or model.body_mocapid[body] >= 0:
            return True
        body = int(model.body_parentid[body])
    return False


def _geom_rgba(model: Any, i: int) -> np.ndarray:
    """The colour MuJoCo draws a geom in: its own rgba, or its material's when rgba is the default."""
    rgba = np.asarray(model.geom_rgba[i], dtype=np.float32)
    mat = int(model.geom_matid[i])
    if mat >= 0 and np.array_equal(rgba, _DEFAULT_RGBA):
        return np.asarray(model.mat_rgba[mat], dtype=np.float32)
    return rgba


def _site_rgba(model: Any, i: int) -> np.ndarray:
    rgba = np.asarray(model.site_rgba[i], dtype=np.float32)
    mat = int(model.site_matid[i])
    if mat >= 0 and np.array_equal(rgba, _DEFAULT_RGBA):
        return np.asarray(model.mat_rgba[mat], dtype=np.float32)
    return rgba


def light_setup(model: Any) -> tuple[float, np.ndarray, np.ndarray]:
    """(ambient, unit directions (L, 3) towards the lights, diffuse (L,)) as seen from above."""
    head = model.vis.headlight
    ambient = float(np.mean(head.ambient)) if head.active else 0.0
    dirs, diffuse = [], []
    if head.active:  # the headlight shines along the camera axis: straight down
        dirs.append([0.0, 0.0, 1.0])
        diffuse.append(float(np.mean(head.diffuse)))
    for i in range(model.nlight):
        if not model.light_active[i]:
            continue
        ambient += float(np.mean(model.light_ambient[i]))
        if model.light_directional[i]:
            d = -np.asarray(model.light_dir[i], dtype=np.float64)
            dirs.append(d / max(float(np.linalg.norm(d)), 1e-12))
            diffuse.append(float(np.mean(model.light_diffuse[i])))
    return ambient, np.asarray(dirs, dtype=np.float64).reshape(-1, 3), np.asarray(diffuse, dtype=np.float64)
