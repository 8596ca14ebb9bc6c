"""Depth-camera effects of a structured-light RGB-D sensor (Kinect v1) for the synthetic sensor model.

The pieces :func:`gausslite.synthetic.sensor.depth_with_errors` applies when the model's parameters turn them on
(``make_scene(sensor_noise="tum")``; the ``"realistic"`` level leaves them all off). Each is a pure function of its
inputs and the generator it is handed, in pixels of the image it is given:

- :func:`quantise_disparity`: the Kinect v1 measures disparity in 1/8 pixel steps, so depth takes values on a lattice
  equally spaced in ``1 / z`` and its step grows as ``c * z^2`` (Khoshelham and Elberink, Sensors 2012, Sec. 3;
  ``c`` measured on TUM fr1 by ``python -m bench.sensor_calibration``, retired: docs/history.md#sensor_calibration);
- :func:`correlated_field`: axial noise that is correlated over a few pixels, as block-matched disparity is;
- :func:`border_holes`: the bands of the colour image the depth camera does not see after registration;
- :func:`dark_dropout`: no return from dark surfaces, a probability by grey level;
- :func:`edge_shadows`: runs of missing depth on the far side of a depth edge (the projector's shadow);
- :func:`flying_pixels`: pixels at a depth edge that take a depth between the two surfaces;
- :func:`warp_depth_rows`: the depth image of a camera whose rows are exposed at different poses (rolling shutter).
"""

from __future__ import annotations

from typing import Iterator, Sequence, Tuple

import cv2
import numpy as np

from gausslite.camera import Intrinsics

#: the four image directions (dv, du): down, up, right, left
DIRECTIONS = ((1, 0), (-1, 0), (0, 1), (0, -1))


def quantise_disparity(z: np.ndarray, step_per_m: float) -> np.ndarray:
    """Depth on the disparity lattice: ``1 / z`` rounded to a multiple of ``step_per_m``, so the depth step near
    ``z`` is ``step_per_m * z^2`` metres.

    Args:
        z: (H, W) float depth in metres, 0 (or below) = no depth.
        step_per_m: the lattice step of ``1 / z`` (1/m); 0 leaves the depth as it is.
    Returns:
        (H, W) float64 depth in metres, 0 where ``z <= 0``.
    Raises:
        ValueError: ``step_per_m < 0``.
    """
    if step_per_m < 0:
        raise ValueError(f"step_per_m must be >= 0, got {step_per_m}")
    z = np.asarray(z, np.float64)
    if step_per_m == 0:
        return np.where(z > 0, z, 0.0)
    inv = np.where(z > 0, 1.0 / np.maximum(z, 1e-9), 0.0)
    q = np.maximum(np.rint(inv / step_per_m), 1.0) * step_per_m
    return np.where(z > 0, 1.0 / q, 0.0)


def correlated_field(rng: np.random.Generator, shape: Tuple[int, int], corr_px: float) -> np.ndarray:
    """A Gaussian random field of unit standard deviation: white noise low-passed by a Gaussian of ``corr_px``
    pixels (white for ``corr_px <= 0``). Draws ``H * W`` standard normals from ``rng``.

    Returns:
        (H, W) float64.
    """
    n = rng.standard_normal(shape)
    if corr_px <= 0:
        return n
    s = cv2.GaussianBlur(n, (0, 0), float(corr_px), borderType=cv2.BORDER_REFLECT)
    return s / max(float(s.std()), 1e-12)


def border_holes(shape: Tuple[int, int], top: float, bottom: float, left: float, right: float) -> np.ndarray:
    """(H, W) bool: the bands along the image borders without depth, each a fraction of the image height (top,
    bottom) or width (left, right), rounded to whole pixels."""
    H, W = shape
    m = np.zeros((H, W), bool)
    t, b, lf, r = (int(round(f * n)) for f, n in ((top, H), (bottom, H), (left, W), (right, W)))
    m[:t] = True
    m[H - b:] = True
    m[:, :lf] = True
    m[:, W - r:] = True
    return m


def dark_dropout(grey: np.ndarray, rng: np.random.Generator, knots: Sequence[Tuple[float, float]],
                 cell_px: int = 8) -> np.ndarray:
    """(H, W) bool: pixels whose surface returns no depth because it is dark. A pixel is dropped where a smooth
    uniform field (random values on a grid of ``cell_px`` pixels, interpolated bilinearly and mapped to uniform
    marginals by rank) lies below the probability interpolated linearly in ``knots`` (``(grey level 0..255,
    probability)`` pairs, grey levels increasing) at its grey level, so each pixel is dropped with that probability
    and the holes come in patches, as a dark surface's do. Draws ``ceil(H / cell_px) * ceil(W / cell_px)`` uniforms
    from ``rng`` (none when ``knots`` is empty)."""
    if not knots:
        return np.zeros(grey.shape, bool)
    H, W = grey.shape
    coarse = rng.random((max(-(-H // cell_px), 2), max(-(-W // cell_px), 2)))
    field = cv2.resize(coarse, (W, H), interpolation=cv2.INTER_LINEAR).ravel()
    u = np.empty(field.size)
    u[np.argsort(field, kind="stable")] = (np.arange(field.size) + 0.5) / field.size
    g, p = (np.asarray(v, np.float64) for v in zip(*knots))
    return u.reshape(H, W) < np.interp(np.asarray(grey, np.float64), g, p)


def jump_masks(z: np.ndarray, jump_m: float, jump_rel: float) -> Iterator[Tuple[Tuple[int, int], np.ndarray]]:
    """For each direction ``(dv, du)`` of :data:`DIRECTIONS`: the (H, W) bool mask of the pixels whose neighbour at
    ``(v + dv, u + du)`` is nearer by more than ``max(jump_m, jump_rel * z)`` (the far side of a depth edge, facing
    the foreground in that direction). Pixels without depth (0) are never on an edge."""
    H, W = z.shape
    for dv, du in DIRECTIONS:
        nb = np.zeros_like(z)
        ys = slice(max(dv, 0), H + min(dv, 0))
        xs = slice(max(du, 0), W + min(du, 0))
        yd = slice(max(-dv, 0), H + min(-dv, 0))
        xd = slice(max(-du, 0), W + min(-du, 0))
        nb[yd, xd] = z[ys, xs]
        far = (z > 0) & (nb > 0) & (z - nb > np.maximum(jump_m, jump_rel * z))
        yield (dv, du), far


def edge_shadows(z: np.ndarray, rng: np.random.Generator, p: float, mean_px: float, jump_m: float,
                 jump_rel: float) -> np.ndarray:
    """(H, W) bool: runs of missing depth on the far side of depth edges. Each far-side pixel (:func:`jump_masks`)
    starts a run with probability ``p``; the run goes away from the foreground for ``1 + G`` pixels, ``G``
    geometric with mean ``mean_px - 1``. Draws two (H, W) uniform arrays per direction from ``rng``.

    Raises:
        ValueError: ``mean_px < 1``.
    """
    if mean_px < 1:
        raise ValueError(f"mean_px must be >= 1, got {mean_px}")
    H, W = z.shape
    out = np.zeros((H, W), bool)
    q = 1.0 - 1.0 / mean_px  # the chance a run goes on for one more pixel
    kmax = int(np.ceil(np.log(1e-3) / np.log(q))) + 1 if q > 0 else 1
    for (dv, du), far in jump_masks(z, jump_m, jump_rel):
        start = far & (rng.random((H, W)) < p)
        u = rng.random((H, W))
        vs, us = np.nonzero(start)
        if q > 0:  # 1 + G, G geometric on {0, 1, ...} with P(G >= k) = q^k
            w = 1 + np.floor(np.log(np.maximum(u[vs, us], 1e-12)) / np.log(q)).astype(int)
        else:
            w = np.ones(len(vs), int)
        w = np.minimum(w, kmax)
        for k in range(int(w.max()) if len(w) else 0):
            m = w > k
            yy, xx = vs[m] - k * dv, us[m] - k * du
            ok = (yy >= 0) & (yy < H) & (xx >= 0) & (xx < W)
            out[yy[ok], xx[ok]] = True
    return out


def flying_pixels(z: np.ndarray, rng: np.random.Generator, p: float, jump_m: float,
                  jump_rel: float) -> np.ndarray:
    """The depth with mixed pixels at depth edges: each far-side pixel (:func:`jump_masks`; a pixel facing several
    nearer neighbours is tried once per direction) takes, with probability ``p``, the depth ``z_near + a (z_far -
    z_near)``, ``a`` uniform in (0, 1), between its own and its nearer neighbour's. Draws two (H, W) uniform arrays
    per direction from ``rng``.

    Returns:
        (H, W) float64 depth in metres.
    """
    out = np.asarray(z, np.float64).copy()
    H, W = z.shape
    for (dv, du), far in jump_masks(np.asarray(z, np.float64), jump_m, jump_rel):
        pick = far & (rng.random((H, W)) < p)
        a = rng.random((H, W))
        vs, us = np.nonzero(pick)
        near = z[vs + dv, us + du]
        out[vs, us] = near + a[vs, us] * (z[vs, us] - near)
    return out


def warp_depth_rows(depth: np.ndarray, intr: Intrinsics, c2w: np.ndarray, row_poses: np.ndarray) -> np.ndarray:
    """The depth image a camera whose row ``v`` sits at ``row_poses[v]`` would record, from ``depth`` rendered at
    ``c2w``: each pixel's point (at the render's depth of the same pixel, placed at its row's pose) projected into
    the render, the render's depth there (nearest pixel, so depths of two surfaces never mix) moved back into the
    row's camera. The first-order approximation of :func:`gausslite.synthetic.sensor.colour_with_errors`' warp.

    Args:
        depth: (H, W) float depth in metres (> 0) of the render at ``c2w``. intr: intrinsics (pixels).
        c2w: (4, 4) float64 camera-to-world pose of the render (metres). row_poses: (H, 4, 4) float64 c2w per row.
    Returns:
        (H, W) float64 depth in metres along each row camera's z, 0 where the point falls outside the render.
    """
    H, W = depth.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    z = np.asarray(depth, np.float64)
    cam = np.stack([(u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z], axis=-1)
    rel = np.linalg.inv(c2w)[None] @ row_poses  # (H, 4, 4): row camera -> render camera
    p = np.einsum("hij,hwj->hwi", rel[:, :3, :3], cam) + rel[:, None, :3, 3]
    zp = np.maximum(p[..., 2], 1e-6)
    mx = np.rint(intr.fx * p[..., 0] / zp + intr.cx).astype(int)
    my = np.rint(intr.fy * p[..., 1] / zp + intr.cy).astype(int)
    inside = (mx >= 0) & (mx < W) & (my >= 0) & (my < H)
    mx, my = np.clip(mx, 0, W - 1), np.clip(my, 0, H - 1)
    zs = z[my, mx]
    q = np.stack([(mx - intr.cx) / intr.fx * zs, (my - intr.cy) / intr.fy * zs, zs], axis=-1)
    back = np.linalg.inv(rel)  # render camera -> row camera
    zr = np.einsum("hj,hwj->hw", back[:, 2, :3], q) + back[:, None, 2, 3]
    return np.where(inside & (zs > 0) & (zr > 0), zr, 0.0)
