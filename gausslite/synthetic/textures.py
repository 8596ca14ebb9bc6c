"""Procedural, anti-aliased surface textures for the synthetic scene.

Every texture is a pure function of 2D surface coordinates ``(u, v)`` in metres, a pixel footprint
``fw`` in metres (the width of one image pixel on the surface) and a :class:`Material`. Periodic
patterns are box-filtered analytically over the footprint and noise octaves finer than the
footprint fade to their mean, so textures stay detailed close up without aliasing far away.
All randomness comes from an integer hash of lattice coordinates and the material seed, so the
output is deterministic across runs and platforms.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

import numpy as np

RGB = Tuple[float, float, float]

#: Texture kinds understood by :func:`shade_material`.
KINDS = (
    "solid", "noise", "checker", "stripes", "diamond", "tiles", "planks", "wood", "fabric",
    "text", "painting", "brushed",
)


@dataclass(frozen=True)
class Material:
    """A procedural surface material.

    Attributes:
        kind: one of :data:`KINDS`.
        color_a: primary RGB colour, components in [0, 1] (display space).
        color_b: secondary RGB colour (stripes, grout, ink, ...), in [0, 1].
        scale: main pattern period or cell size in metres (> 0).
        seed: integer seed of the material's hash noise.

    Raises:
        ValueError: unknown ``kind`` or ``scale <= 0``.
    """

    kind: str
    color_a: RGB
    color_b: RGB = (0.0, 0.0, 0.0)
    scale: float = 0.1
    seed: int = 0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown material kind {self.kind!r}; expected one of {KINDS}")
        if not self.scale > 0:
            raise ValueError(f"material scale must be > 0, got {self.scale}")


def hash2(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic hash of integer lattice coordinates to floats in [0, 1).

    Args:
        ix, iy: integer arrays of the same shape (any int dtype, |value| < 2**30).
        seed: integer seed.

    Returns:
        float64 array of the broadcast shape with values in [0, 1).
    """
    return _avalanche(_lattice(np.asarray(ix), np.asarray(iy), seed))


def _lattice(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """The hash's linear start, ``ix·374761393 + iy·668265263 + seed'·1442695041`` modulo 2³², as uint32 (the
    products wrap in 32 bits exactly as the int64 sum's low 32 bits: the arithmetic is modulo 2³² either way)."""
    return (ix.astype(np.uint32) * np.uint32(374761393) + iy.astype(np.uint32) * np.uint32(668265263)
            + np.uint32((int(seed) % 1000003) * 1442695041 % 4294967296))


def _avalanche(x: np.ndarray) -> np.ndarray:
    """:func:`hash2`'s avalanche of the uint32 lattice value ``x`` (modulo 2³²), mapped to float64 in [0, 1)."""
    x = (x ^ (x >> np.uint32(13))) * np.uint32(1274126177)
    x = (x ^ (x >> np.uint32(16))) * np.uint32(2246822519)
    x = x ^ (x >> np.uint32(15))
    return x * (1.0 / 4294967296.0)


def value_noise(u: np.ndarray, v: np.ndarray, cell: float, seed: int) -> np.ndarray:
    """Smooth (C1) value noise on a square lattice of ``cell`` metres; float64 in [0, 1)."""
    x = u / cell
    y = v / cell
    ix = np.floor(x)
    iy = np.floor(y)
    fx = x - ix
    fy = y - iy
    sx = fx * fx * (3.0 - 2.0 * fx)
    sy = fy * fy * (3.0 - 2.0 * fy)
    # the four corners' lattice values differ by the constant steps of ix + 1 and iy + 1 (modulo 2**32)
    base = _lattice(ix.astype(np.int64), iy.astype(np.int64), seed)
    a = _avalanche(base)
    b = _avalanche(base + np.uint32(374761393))
    c = _avalanche(base + np.uint32(668265263))
    d = _avalanche(base + np.uint32(374761393 + 668265263))
    return (a * (1 - sx) + b * sx) * (1 - sy) + (c * (1 - sx) + d * sx) * sy


def fbm(u: np.ndarray, v: np.ndarray, cell: float, seed: int, fw: np.ndarray, octaves: int = 4) -> np.ndarray:
    """Fractal sum of :func:`value_noise` octaves (cell, cell/2, ...), footprint-filtered.

    Octaves whose cell is smaller than about three footprints ``fw`` (metres) fade to 0.5.
    Returns float64 in [0, 1].
    """
    total = np.zeros_like(u)
    amp, norm = 0.5, 0.0
    for o in range(octaves):
        c = cell / (2.0 ** o)
        w = np.clip(c / (3.0 * fw) - 0.5, 0.0, 1.0)
        n = value_noise(u, v, c, seed + 7919 * o)
        total += amp * (w * n + (1.0 - w) * 0.5)
        norm += amp
        amp *= 0.5
    return total / norm


def box_wave(x: np.ndarray, period: float, duty: float, fw: np.ndarray) -> np.ndarray:
    """Box-filtered square wave: 1 on the first ``duty`` fraction of each ``period``, else 0.

    Args:
        x: coordinates (metres).
        period: wave period (metres, > 0).
        duty: fraction of the period that is 1, in (0, 1).
        fw: filter width (metres), broadcastable to ``x``; the exact average of the wave over
            ``[x - fw/2, x + fw/2]`` is returned.

    Returns:
        float64 array in [0, 1].
    """
    s = x / period
    w = np.maximum(fw / period, 1e-6)

    def integral(t: np.ndarray) -> np.ndarray:
        f = np.floor(t)
        return f * duty + np.minimum(t - f, duty)

    return np.clip((integral(s + 0.5 * w) - integral(s - 0.5 * w)) / w, 0.0, 1.0)


def _mix(a: np.ndarray, b: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Blend colours ``a`` and ``b`` ((3,) or (M, 3)) with weights ``k`` (M,) -> (M, 3)."""
    return a * (1.0 - k[:, None]) + b * k[:, None]


def _text_ink(u: np.ndarray, v: np.ndarray, line_h: float, seed: int) -> np.ndarray:
    """Binary "printed text" ink mask (1 = ink) of 3x5-bit pseudo glyphs; float64 (M,)."""
    gw = 0.55 * line_h
    row = np.floor(-v / line_h)
    fv = -v / line_h - row
    col = np.floor(u / gw)
    fu = u / gw - col
    row_i = row.astype(np.int64)
    col_i = col.astype(np.int64)
    blank = hash2(col_i, row_i, seed + 11) < 0.2  # word gaps
    line_len = 25 + (hash2(row_i, row_i * 3, seed + 13) * 40).astype(np.int64)
    blank |= np.mod(col_i, 80) > line_len  # ragged line ends
    blank |= hash2(row_i, 5, seed + 17) < 0.12  # paragraph breaks
    gx = np.floor(fu * 4.0).astype(np.int64)
    gy = np.floor((fv - 0.18) / 0.64 * 5.0).astype(np.int64)
    inside = (gx < 3) & (gy >= 0) & (gy < 5)
    bit = hash2(col_i * 8 + gx, row_i * 8 + gy, seed) < 0.55
    return (inside & bit & ~blank).astype(np.float64)


def shade_material(mat: Material, u: np.ndarray, v: np.ndarray, fw: np.ndarray) -> np.ndarray:
    """Albedo of ``mat`` at surface coordinates ``(u, v)``.

    Args:
        mat: the material.
        u, v: (M,) float64 surface coordinates in metres (``v`` points up on vertical surfaces).
        fw: (M,) float64 pixel footprint on the surface in metres (> 0).

    Returns:
        (M, 3) float64 RGB albedo in [0, 1].
    """
    ca = np.asarray(mat.color_a, dtype=np.float64)
    cb = np.asarray(mat.color_b, dtype=np.float64)
    s = float(mat.scale)
    sd = int(mat.seed)
    k = mat.kind
    if u.size == 0:
        return np.zeros((0, 3), dtype=np.float64)
    if k == "solid":
        out = ca[None, :] * (0.9 + 0.2 * fbm(u, v, s, sd, fw, 3))[:, None]
    elif k == "noise":
        n = fbm(u, v, s, sd, fw, 5)
        out = _mix(ca, cb, np.clip((n - 0.5) * 2.2 + 0.5, 0.0, 1.0))
    elif k == "checker":
        sx = box_wave(u, 2 * s, 0.5, fw)
        sy = box_wave(v, 2 * s, 0.5, fw)
        out = _mix(ca, cb, sx + sy - 2 * sx * sy) * (0.92 + 0.16 * fbm(u, v, s, sd, fw, 3))[:, None]
    elif k == "stripes":
        main = box_wave(u, s, 0.45, fw)
        pin = box_wave(u + 0.7 * s, s, 0.06, fw)
        out = _mix(_mix(ca, cb, main), ca * 0.45, pin) * (0.93 + 0.14 * fbm(u, v, 4 * s, sd, fw, 4))[:, None]
    elif k == "diamond":
        a = (u + v) * 0.7071067811865476
        b = (u - v) * 0.7071067811865476
        sx = box_wave(a, 2 * s, 0.5, fw)
        sy = box_wave(b, 2 * s, 0.5, fw)
        dots = box_wave(a + 0.45 * s, s, 0.1, fw) * box_wave(b + 0.45 * s, s, 0.1, fw)
        out = _mix(_mix(ca, cb, sx + sy - 2 * sx * sy), cb * 0.5, dots)
        out *= (0.94 + 0.12 * fbm(u, v, 3 * s, sd, fw, 4))[:, None]
    elif k == "tiles":
        g = 0.06
        gx = box_wave(u + 0.5 * g * s, s, g, fw)
        gy = box_wave(v + 0.5 * g * s, s, g, fw)
        grout = 1.0 - (1.0 - gx) * (1.0 - gy)
        ix = np.floor(u / s).astype(np.int64)
        iy = np.floor(v / s).astype(np.int64)
        h = hash2(ix, iy, sd)
        speck = fbm(u, v, 0.08 * s, sd + 1, fw, 3)
        tile = ca[None, :] * (0.86 + 0.16 * h + 0.18 * (speck - 0.5))[:, None]
        out = _mix(tile, cb, grout)
    elif k == "planks":
        L = 7.0 * s
        row = np.floor(v / s).astype(np.int64)
        uu = u + hash2(row, 3, sd) * L
        col = np.floor(uu / L).astype(np.int64)
        h = hash2(col, row, sd + 5)
        warp = 0.02 * (fbm(uu, v, 0.35, sd + 9, fw, 3) - 0.5)
        grain = box_wave(v + warp + 0.5 * h * s, s / 9.0, 0.35, fw)
        tone = 0.25 + 0.5 * h + 0.25 * (fbm(uu * 0.15, v, 0.05, sd + 3, fw, 3) - 0.5)
        base = _mix(ca, cb, np.clip(tone, 0.0, 1.0)) * (1.0 - 0.18 * grain)[:, None]
        gap = 1.0 - (1.0 - box_wave(v, s, 0.03, fw)) * (1.0 - box_wave(uu, L, 0.004, fw))
        out = base * (1.0 - 0.7 * gap)[:, None]
    elif k == "wood":
        warp = 0.25 * s * (fbm(u * 0.2, v, 0.4, sd, fw, 3) - 0.5)
        grain = box_wave(v + warp, s, 0.4, fw)
        fine = box_wave(v + 0.6 * warp + 0.3 * s, s / 4.0, 0.3, fw)
        out = _mix(ca, cb, 0.65 * grain + 0.2 * fine) * (0.93 + 0.14 * fbm(u, v, 2 * s, sd + 1, fw, 3))[:, None]
    elif k == "fabric":
        sx = box_wave(u, s, 0.5, fw)
        sy = box_wave(v, s, 0.5, fw)
        weave = sx * sy + (1 - sx) * (1 - sy)
        out = _mix(ca, cb, 0.35 * weave + 0.4 * fbm(u, v, 8 * s, sd, fw, 4))
    elif k == "text":
        offs = (-0.25, 0.25)
        ink = np.zeros_like(u)
        for du in offs:
            for dv in offs:
                ink += _text_ink(u + du * fw, v + dv * fw, s, sd)
        ink *= 0.25
        fade = np.clip(fw / (0.25 * s) - 1.0, 0.0, 1.0)
        ink = ink * (1.0 - fade) + 0.18 * fade
        paper = ca[None, :] * (0.95 + 0.1 * fbm(u, v, 0.5, sd + 2, fw, 3))[:, None]
        out = _mix(paper, cb, ink)
    elif k == "painting":
        n1 = fbm(u, v, s, sd, fw, 5)
        n2 = fbm(u, v, 0.7 * s, sd + 31, fw, 5)
        cc = np.array([ca[2], ca[0], cb[1]])
        out = _mix(_mix(ca, cb, np.clip((n1 - 0.3) * 2.5, 0, 1)), cc, np.clip((n2 - 0.55) * 4.0, 0, 1))
        out *= (0.9 + 0.2 * box_wave(u + v, 0.6 * s, 0.15, fw))[:, None]
    elif k == "brushed":
        streak = fbm(u * 0.05, v * 4.0, 0.02, sd, fw * 0.05, 3)
        out = _mix(ca, cb, 0.2 + 0.6 * streak)
    else:  # pragma: no cover - Material validates kind
        raise ValueError(f"unknown material kind {k!r}")
    return np.clip(out, 0.0, 1.0)
