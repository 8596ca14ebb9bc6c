"""Map → splat arrays for viewers (paper Sec. III-A Gaussian parameters; 3DGS, Kerbl et al. 2023, Sec. 4).

A viewer needs, per Gaussian, a centre, a 3×3 world covariance Σ = R S Sᵀ Rᵀ, an RGB colour and an
opacity. :func:`splat_arrays` computes them from a :class:`gausslite.core.arrays.GaussianArrays` (or
anything :meth:`GaussianArrays.from_any` takes: a ``GaussianMap``, a mapping of arrays) in chunks,
reporting progress, so a map of millions of Gaussians converts with a live progress bar.

Colour modes (:data:`COLOR_MODES`):

* ``rgb`` — the map's own colours;
* ``kappa`` — κ, the active-optimisation count (paper Sec. III-D), on a log scale through the viridis
  colour map (κ = 0 dark purple, the largest κ of the map yellow);
* ``roi`` — the task flag a (paper Sec. III-C): active Gaussians keep their colour, tinted towards
  red; inactive ones are drawn in dim grey.

No mapping logic lives here: only the closed-form conversion of stored parameters.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from gausslite.core.arrays import GaussianArrays

#: Colour modes understood by :func:`splat_arrays`.
COLOR_MODES = ("rgb", "kappa", "roi")

#: Gaussians converted per progress step.
DEFAULT_CHUNK = 65536

ProgressFn = Callable[[int, int], None]


@dataclass
class SplatArrays:
    """Splats ready for a viewer (all float32, C-contiguous).

    Attributes:
        centers: (N, 3) world-frame centres, metres.
        covariances: (N, 3, 3) world-frame covariances Σ = R diag(s²) Rᵀ, square metres.
        rgbs: (N, 3) colours in [0, 1].
        opacities: (N, 1) opacities in [0, 1] (sigmoid of the stored logits).
    """

    centers: np.ndarray
    covariances: np.ndarray
    rgbs: np.ndarray
    opacities: np.ndarray

    def __len__(self) -> int:
        return int(self.centers.shape[0])


def sigmoid(x: np.ndarray) -> np.ndarray:
    """Numerically stable logistic function (float32 in, float32 out)."""
    x = np.asarray(x, np.float32)
    out = np.empty_like(x)
    pos = x >= 0
    out[pos] = 1.0 / (1.0 + np.exp(-x[pos]))
    e = np.exp(x[~pos])
    out[~pos] = e / (1.0 + e)
    return out


def normalized_quats(quats: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (w, x, y, z) → unit quaternions; zero rows become the identity (1, 0, 0, 0)."""
    q = np.asarray(quats, np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    out = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), np.array([1.0, 0, 0, 0]))
    return out


def quat_to_rotmat(quats: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (w, x, y, z), any norm → (N, 3, 3) float64 rotation matrices."""
    w, x, y, z = normalized_quats(quats).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)


def covariances(quats: np.ndarray, log_scales: np.ndarray) -> np.ndarray:
    """World covariances Σ = R diag(exp(2·log_s)) Rᵀ.

    Args:
        quats: (N, 4) rotation quaternions (w, x, y, z), normalised here.
        log_scales: (N, 3) natural logs of the per-axis standard deviations (metres).
    Returns:
        (N, 3, 3) float32, symmetric positive semi-definite, square metres.
    """
    m = quat_to_rotmat(quats) * np.exp(np.asarray(log_scales, np.float64))[:, None, :]  # R diag(s)
    return np.matmul(m, m.transpose(0, 2, 1)).astype(np.float32)


def kappa_colors(kappa: np.ndarray, kappa_max: Optional[int] = None) -> np.ndarray:
    """κ → (N, 3) float32 viridis colours on a log scale: log1p(κ) / log1p(κ_max).

    Args:
        kappa: (N,) non-negative counts.
        kappa_max: count mapped to the top of the scale (default: the largest κ, at least 1).
    """
    # lazy: heavy optional dependency, loaded only on this path
    from matplotlib import colormaps

    k = np.asarray(kappa, np.float64)
    top = float(max(1, int(kappa_max) if kappa_max is not None else (int(k.max()) if k.size else 1)))
    t = np.clip(np.log1p(np.maximum(k, 0)) / np.log1p(top), 0.0, 1.0)
    return colormaps["viridis"](t)[:, :3].astype(np.float32)


def roi_colors(colors: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Task flag a → (N, 3) float32: active Gaussians tinted red (60 % colour + 40 % red), the rest grey."""
    c = np.clip(np.asarray(colors, np.float32), 0, 1)
    out = np.empty_like(c)
    a = np.asarray(active, bool)
    out[a] = 0.6 * c[a] + 0.4 * np.array([1.0, 0.1, 0.1], np.float32)
    grey = c[~a].mean(axis=1, keepdims=True) * 0.35 + 0.15
    out[~a] = np.repeat(grey, 3, axis=1)
    return out


def splat_colors(g: GaussianArrays, mode: str = "rgb", kappa_max: Optional[int] = None) -> np.ndarray:
    """(N, 3) float32 colours in [0, 1] of colour mode ``mode`` (see :data:`COLOR_MODES`).

    Raises:
        ValueError: unknown mode.
    """
    if mode == "rgb":
        return np.clip(g.colors, 0.0, 1.0).astype(np.float32)
    if mode == "kappa":
        return kappa_colors(g.kappa, kappa_max)
    if mode == "roi":
        return roi_colors(g.colors, g.active)
    raise ValueError(f"unknown colour mode {mode!r}; choose one of {', '.join(COLOR_MODES)}")


def splat_arrays(gaussians, mode: str = "rgb", *, chunk: int = DEFAULT_CHUNK,
                 progress: Optional[ProgressFn] = None) -> SplatArrays:
    """Convert a Gaussian map to viewer splats, ``chunk`` Gaussians at a time.

    Args:
        gaussians: GaussianArrays, GaussianMap or mapping of arrays (see ``GaussianArrays.from_any``).
        mode: colour mode, one of :data:`COLOR_MODES`.
        chunk: Gaussians per step (>= 1).
        progress: called as ``progress(done, total)`` after every chunk (Gaussians converted so far).
    Returns:
        SplatArrays.
    Raises:
        ValueError: unknown colour mode, chunk < 1, or non-finite means / scales / quaternions (a
            viewer would silently drop or smear such splats).
    """
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    g = GaussianArrays.from_any(gaussians)
    n = len(g)
    for name in ("means", "log_scales", "quats", "opacity_logits"):
        arr = getattr(g, name)
        if n and not np.isfinite(arr).all():
            bad = int((~np.isfinite(arr.reshape(n, -1))).any(axis=1).sum())
            raise ValueError(f"{bad} Gaussian(s) have non-finite {name}; refusing to display a corrupt map")
    rgbs = splat_colors(g, mode)
    cov = np.empty((n, 3, 3), np.float32)
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        cov[s:e] = covariances(g.quats[s:e], g.log_scales[s:e])
        if progress is not None:
            progress(e, n)
    if progress is not None and n == 0:
        progress(0, 0)
    return SplatArrays(
        centers=np.ascontiguousarray(g.means, np.float32),
        covariances=cov,
        rgbs=np.ascontiguousarray(rgbs, np.float32),
        opacities=np.ascontiguousarray(sigmoid(g.opacity_logits)[:, None], np.float32),
    )


def scene_bounds(centers: np.ndarray, quantile: float = 0.02) -> tuple[np.ndarray, float]:
    """Robust centre and radius of a point set (ignores the ``quantile`` tails on each axis).

    Args:
        centers: (N, 3) points, metres.
        quantile: tail fraction ignored per side.
    Returns:
        (centre (3,) float64, radius float metres, >= 0.1).
    """
    c = np.asarray(centers, np.float64)
    if c.shape[0] == 0:
        return np.zeros(3), 1.0
    lo = np.quantile(c, quantile, axis=0)
    hi = np.quantile(c, 1 - quantile, axis=0)
    return (lo + hi) / 2, max(0.1, float(np.linalg.norm(hi - lo) / 2))


__all__ = ["COLOR_MODES", "SplatArrays", "splat_arrays", "splat_colors", "covariances", "quat_to_rotmat",
           "kappa_colors", "roi_colors", "sigmoid", "scene_bounds", "normalized_quats"]
