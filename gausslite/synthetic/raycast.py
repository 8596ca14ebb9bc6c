"""Vectorised numpy ray caster for the synthetic scene: colour, depth and an object-id buffer.

One ray per pixel through the pixel centre (pixel (u, v) has its centre at integer coordinates,
matching :func:`gausslite.camera.backproject`). Rays are not normalised: their camera-frame
direction is ``((u - cx) / fx, (v - cy) / fy, 1)``, so the hit parameter ``t`` *is* the depth along
the camera z axis. Shading is Lambertian from the scene's point light plus an ambient term, without
shadows; textures are filtered over each pixel's footprint (see :mod:`.textures`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from gausslite.camera import Intrinsics, check_rigid
from gausslite.synthetic.scene import (
    CEILING_ID, FLOOR_ID, WALL_XMAX_ID, WALL_XMIN_ID, WALL_YMAX_ID, WALL_YMIN_ID, Primitive, Scene,
)
from gausslite.synthetic.textures import shade_material

_EPS = 1e-6
# (axis, side) of the room faces -> surface id; side 0 = lo plane, 1 = hi plane.
_ROOM_FACE_IDS = {(0, 0): WALL_XMIN_ID, (0, 1): WALL_XMAX_ID, (1, 0): WALL_YMIN_ID, (1, 1): WALL_YMAX_ID,
                  (2, 0): FLOOR_ID, (2, 1): CEILING_ID}


@dataclass
class RenderResult:
    """Output of :func:`render`.

    Attributes:
        rgb: (H, W, 3) uint8 colour, RGB order.
        depth: (H, W) float64 depth in metres along the camera z axis (> 0 everywhere: the room is closed).
        ids: (H, W) int16 id of the visible surface: object id (>= 1) or a negative room surface id
            (``FLOOR_ID``, ``CEILING_ID``, ``WALL_*_ID`` from :mod:`.scene`).
        normal: (H, W, 3) float64 unit world-frame normal of the visible surface (facing the camera's side for the
            room shell, outward for objects), or None.
    """

    rgb: np.ndarray
    depth: np.ndarray
    ids: np.ndarray
    normal: Optional[np.ndarray] = None


def camera_rays(intr: Intrinsics, c2w: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """World-frame rays through every pixel centre.

    Args:
        intr: pinhole intrinsics (pixels).
        c2w: (4, 4) camera-to-world pose (metres, OpenCV camera axes).

    Returns:
        origin (3,) float64 camera centre and directions (H*W, 3) float64, row-major pixel order,
        scaled so that a ray's parameter t equals the depth along camera z.
    """
    o, dT = _camera_rays_T(intr, c2w)
    return o, dT.T.copy()


def _camera_rays_T(intr: Intrinsics, c2w: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Like :func:`camera_rays` but directions as a contiguous (3, H*W) array."""
    xs = (np.arange(intr.width, dtype=np.float64) - intr.cx) / intr.fx
    ys = (np.arange(intr.height, dtype=np.float64) - intr.cy) / intr.fy
    dc = np.empty((3, intr.height, intr.width))
    dc[0] = xs[None, :]
    dc[1] = ys[:, None]
    dc[2] = 1.0
    return c2w[:3, 3].copy(), c2w[:3, :3] @ dc.reshape(3, -1)


def _safe_inv(d: np.ndarray) -> np.ndarray:
    return 1.0 / np.where(np.abs(d) < 1e-12, np.copysign(1e-12, d), d)


def _box_t(ol: np.ndarray, dl: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Entry parameter of local rays (origin (3,), dirs (3, M)) into the box ``|x| <= half``; inf = miss."""
    tn = np.full(dl.shape[1], -np.inf)
    tf = np.full(dl.shape[1], np.inf)
    for k in range(3):
        inv = _safe_inv(dl[k])
        a = (-half[k] - ol[k]) * inv
        b = (half[k] - ol[k]) * inv
        np.maximum(tn, np.minimum(a, b), out=tn)
        np.minimum(tf, np.maximum(a, b), out=tf)
    return np.where((tf >= tn) & (tn > _EPS), tn, np.inf)


def _cylinder_t(ol: np.ndarray, dl: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Entry parameter into the local-z cylinder of radius ``half[0]``, ``|z| <= half[2]`` (dirs (3, M)); inf = miss."""
    r, hz = half[0], half[2]
    dx, dy, dz = dl[0], dl[1], dl[2]
    ox, oy, oz = ol
    a = dx * dx + dy * dy
    b = 2.0 * (ox * dx + oy * dy)
    c = ox * ox + oy * oy - r * r
    disc = b * b - 4.0 * a * c
    ok = (disc >= 0.0) & (a > 1e-18)
    ts = np.where(ok, (-b - np.sqrt(np.maximum(disc, 0.0))) / np.where(ok, 2.0 * a, 1.0), np.inf)
    zs = oz + ts * dz
    t = np.where((ts > _EPS) & (np.abs(zs) <= hz), ts, np.inf)
    inv = _safe_inv(dz)
    for zc in (hz, -hz):
        tc = (zc - oz) * inv
        x = ox + tc * dx
        y = oy + tc * dy
        good = (tc > _EPS) & (x * x + y * y <= r * r) & (np.abs(dz) > 1e-12)
        t = np.where(good & (tc < t), tc, t)
    return t


def _prim_t(p: Primitive, o: np.ndarray, dT: np.ndarray) -> np.ndarray:
    """Hit parameters of rays (origin (3,), dirs (3, M)) on primitive ``p``."""
    ol = p.rotation.T @ (o - p.center)
    dl = p.rotation.T @ dT
    return _box_t(ol, dl, p.half) if p.shape == "box" else _cylinder_t(ol, dl, p.half)


def _prim_surface(p: Primitive, o: np.ndarray, d: np.ndarray, t: np.ndarray):
    """World normals (M, 3) and texture coordinates u, v (M,) of hits on primitive ``p``."""
    ol = p.rotation.T @ (o - p.center)
    pl = ol + t[:, None] * (d @ p.rotation)
    m = pl.shape[0]
    n = np.zeros((m, 3))
    if p.shape == "box":
        rel = np.abs(pl) / p.half
        axis = np.argmax(rel, axis=1)
        n[np.arange(m), axis] = np.sign(pl[np.arange(m), axis])
        q = pl + p.half
        u = np.where(axis == 0, q[:, 1], q[:, 0])
        v = np.where(axis == 2, q[:, 1], q[:, 2])
    else:
        r, hz = p.half[0], p.half[2]
        cap = np.abs(np.abs(pl[:, 2]) - hz) < 1e-9
        n[:, 0] = np.where(cap, 0.0, pl[:, 0] / r)
        n[:, 1] = np.where(cap, 0.0, pl[:, 1] / r)
        n[:, 2] = np.where(cap, np.sign(pl[:, 2]), 0.0)
        u = np.where(cap, pl[:, 0], np.arctan2(pl[:, 1], pl[:, 0]) * r)
        v = np.where(cap, pl[:, 1], pl[:, 2] + hz)
    return n @ p.rotation.T, u + p.uv_offset[0], v + p.uv_offset[1]


def _room_hits(scene: Scene, o: np.ndarray, d: np.ndarray):
    """Exit parameter from the room box (N,), the face axis (N,) and side (N,) of every ray."""
    lo, hi = scene.room.lo, scene.room.hi
    if np.any(o <= lo) or np.any(o >= hi):
        raise ValueError(f"camera centre {o.tolist()} is outside the room {lo.tolist()}..{hi.tolist()}")
    n = d.shape[0]
    t = np.full(n, np.inf)
    axis = np.zeros(n, dtype=np.int64)
    side = np.zeros(n, dtype=np.int64)
    for k in range(3):
        dk = np.ascontiguousarray(d[:, k])
        pos = dk > 0
        tk = np.where(np.abs(dk) < 1e-12, np.inf, (np.where(pos, hi[k], lo[k]) - o[k]) * _safe_inv(dk))
        better = tk < t
        t = np.where(better, tk, t)
        axis[better] = k
        side[better] = pos[better]
    return t, axis, side


def _room_uv(axis: np.ndarray, p: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    u = np.where(axis == 0, p[:, 1], p[:, 0])
    v = np.where(axis == 2, p[:, 1], p[:, 2])
    return u, v


def _nearest_primitives(scene: Scene, o: np.ndarray, dT: np.ndarray, t_best: np.ndarray):
    """Intersect the rays (origin ``o`` (3,), directions ``dT`` (3, N), world frame) with every object's
    primitives (only rays that hit the object's hull before ``t_best``), lowering ``t_best`` (N,) in place.

    Returns:
        ``(prim_best (N,) int64, prims)``: per ray the index into ``prims`` of the nearest primitive (-1: the room
        shell), and every object's primitives in scene order.
    """
    prim_best = np.full(dT.shape[1], -1, dtype=np.int64)
    prims = []
    for obj in scene.objects:
        ht = _box_t(obj.rotation.T @ (o - obj.hull_center), obj.rotation.T @ dT, obj.hull_half)
        cand = np.nonzero(ht < t_best)[0]
        base = len(prims)
        prims.extend(obj.primitives)
        if cand.size == 0:
            continue
        dc = dT[:, cand]
        for k, p in enumerate(obj.primitives):
            t = _prim_t(p, o, dc)
            better = t < t_best[cand]
            if np.any(better):
                idx = cand[better]
                t_best[idx] = t[better]
                prim_best[idx] = base + k
    return prim_best, prims


def _footprint(nrm: np.ndarray, dnorm: np.ndarray, t: np.ndarray, f_mean: float) -> np.ndarray:
    """Pixel footprint on the surface (m) of rays with unit directions ``dnorm`` hitting at depth ``t`` (m) a
    surface of normal ``nrm`` (grazing angles capped at cos = 0.25); ``f_mean``: focal length (px)."""
    cos = np.abs(np.einsum("ij,ij->i", nrm, dnorm))
    return t / f_mean / np.maximum(cos, 0.25)


def _shade_room(scene: Scene, ax: np.ndarray, sd: np.ndarray, pts: np.ndarray, dnorm: np.ndarray, t: np.ndarray,
                f_mean: float):
    """Surface of the rays that hit the room shell (wall axis ``ax``, side ``sd``, hit points ``pts``, unit
    directions ``dnorm``, depths ``t``): face materials, baseboard and decals (with their frames).

    Returns:
        ``(normal (n, 3), surface id (n,) int16, albedo (n, 3))``.
    """
    n = len(ax)
    nr = np.zeros((n, 3))
    nr[np.arange(n), ax] = np.where(sd == 1, -1.0, 1.0)
    u, v = _room_uv(ax, pts)
    sid = np.zeros(n, dtype=np.int16)
    for (a_, s_), fid in _ROOM_FACE_IDS.items():
        sid[(ax == a_) & (sd == s_)] = fid
    fw = _footprint(nr, dnorm, t, f_mean)
    col = np.zeros((n, 3))
    for fid, mat in scene.room.materials.items():
        m = sid == fid
        if np.any(m):
            col[m] = shade_material(mat, u[m], v[m], fw[m])
    bb_h, bb_c = scene.room.baseboard
    wall = (ax != 2) & (v < bb_h)
    col[wall] = np.asarray(bb_c) * (0.9 + 0.1 * (v[wall] > bb_h - 0.01))[:, None]
    for dec in scene.room.decals:
        m = (sid == dec.surface_id) & (u >= dec.u0) & (u <= dec.u1) & (v >= dec.v0) & (v <= dec.v1)
        if not np.any(m):
            continue
        col[m] = shade_material(dec.material, u[m] - dec.u0, v[m] - dec.v0, fw[m])
        if dec.frame_color is not None:
            bw = 0.025
            edge = m & ((u - dec.u0 < bw) | (dec.u1 - u < bw) | (v - dec.v0 < bw) | (dec.v1 - v < bw))
            col[edge] = dec.frame_color
    return nr, sid, col


def render(scene: Scene, intr: Intrinsics, c2w: np.ndarray) -> RenderResult:
    """Ray-cast one view of ``scene``.

    Args:
        scene: the scene (see :func:`gausslite.synthetic.scene.build_default_scene`).
        intr: intrinsics (pixels) giving the image size H x W.
        c2w: (4, 4) float64 camera-to-world pose (metres, OpenCV camera axes).

    Returns:
        :class:`RenderResult` with rgb (H, W, 3) uint8, depth (H, W) float64 metres, ids (H, W) int16 and the
        surface normals (H, W, 3) float64.

    Raises:
        ValueError: ``c2w`` is not a rigid 4x4 transform, or the camera is outside the room.
    """
    c2w = check_rigid(c2w, what="render pose")
    o, dT = _camera_rays_T(intr, c2w)
    d = dT.T
    n_rays = d.shape[0]
    t_best, axis, side = _room_hits(scene, o, d)
    prim_best, prims = _nearest_primitives(scene, o, dT, t_best)

    pts = o + t_best[:, None] * d
    dnorm = d / np.sqrt(np.einsum("ij,ij->i", d, d))[:, None]
    albedo = np.zeros((n_rays, 3))
    normal = np.zeros((n_rays, 3))
    ids = np.zeros(n_rays, dtype=np.int16)
    f_mean = 0.5 * (intr.fx + intr.fy)
    room_sel = np.nonzero(prim_best < 0)[0]
    if room_sel.size:
        normal[room_sel], ids[room_sel], albedo[room_sel] = _shade_room(
            scene, axis[room_sel], side[room_sel], pts[room_sel], dnorm[room_sel], t_best[room_sel], f_mean)

    # primitives, grouped by primitive index
    obj_sel = np.nonzero(prim_best >= 0)[0]
    if obj_sel.size:
        order = obj_sel[np.argsort(prim_best[obj_sel], kind="stable")]
        keys = prim_best[order]
        starts = np.searchsorted(keys, np.arange(len(prims) + 1))
        for k, p in enumerate(prims):
            sel = order[starts[k]:starts[k + 1]]
            if sel.size == 0:
                continue
            nw, u, v = _prim_surface(p, o, d[sel], t_best[sel])
            normal[sel] = nw
            ids[sel] = p.object_id
            albedo[sel] = shade_material(p.material, u, v, _footprint(nw, dnorm[sel], t_best[sel], f_mean))

    to_light = scene.light - pts
    ndotl = np.einsum("ij,ij->i", normal, to_light) / np.maximum(np.sqrt(np.einsum("ij,ij->i", to_light, to_light)), 1e-9)
    shade = scene.ambient + (1.0 - scene.ambient) * np.clip(ndotl, 0.0, 1.0)
    rgb = np.clip(np.rint(albedo * shade[:, None] * 255.0), 0, 255).astype(np.uint8)
    H, W = intr.height, intr.width
    return RenderResult(rgb=rgb.reshape(H, W, 3), depth=t_best.reshape(H, W), ids=ids.reshape(H, W),
                        normal=normal.reshape(H, W, 3))


__all__ = ["RenderResult", "camera_rays", "render"]
