"""Standard splat file formats other viewers read: ``.splat`` and ``.spz`` (plus our 3DGS ``.ply``).

* ``.splat`` — the fixed 32-byte record of antimatter15's WebGL viewer, read by most web splat
  viewers (SuperSplat, gsplat.js, Luma, …). Per Gaussian, little-endian: position float32×3 (m),
  linear scale float32×3 (m, standard deviations), colour uint8×4 (R, G, B, opacity; 0..255), rotation
  uint8×4 (w, x, y, z of the unit quaternion, each ``round(q·128 + 128)`` clipped to 0..255). Records
  are sorted by ``exp(Σ log_scale) · opacity``, largest first, as that viewer expects. No κ / a flag.
  The layout is a 32-byte struct: we write it with numpy (no library implements it for Python).
* ``.spz`` — Niantic's compressed format (gzip; 24-bit fixed-point positions, 8-bit log-scales,
  colours and opacities, smallest-three quaternions), written and read by :mod:`gausslite.viewer.spz`. SH degree 0.
  No κ / a flag.

Quantisation (both lossy): colour and opacity to 1/255 (``.splat``) or the SPZ 8-bit encodings;
``.splat`` quaternion components to 1/128; SPZ positions to 2^-12 m (``fractional_bits=12``).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Union

import numpy as np

from gausslite.core.arrays import GaussianArrays
from gausslite.viewer.splats import normalized_quats, sigmoid
from gausslite.viewer.spz import decode_spz, encode_spz

log = logging.getLogger(__name__)

#: Zeroth-order SH constant (3DGS DC colour = rgb - 0.5 over SH_C0).
SH_C0 = 0.28209479177387814
#: File formats of :func:`export_map` / :func:`load_map`.
FORMATS = ("splat", "spz", "ply")

SPLAT_DTYPE = np.dtype([("pos", "<f4", (3,)), ("scale", "<f4", (3,)), ("rgba", "u1", (4,)), ("rot", "u1", (4,))])
assert SPLAT_DTYPE.itemsize == 32

PathLike = Union[str, Path]


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(np.asarray(p, np.float64), 1e-6, 1 - 1e-6)
    return np.log(p / (1 - p)).astype(np.float32)


def to_splat_bytes(gaussians) -> bytes:
    """Encode Gaussians as ``.splat`` records (see the module docstring).

    Args:
        gaussians: GaussianArrays, GaussianMap or mapping of arrays.
    Returns:
        bytes of length 32·N.
    Raises:
        ValueError: non-finite means or scales.
    """
    g = GaussianArrays.from_any(gaussians)
    if len(g) and not (np.isfinite(g.means).all() and np.isfinite(g.log_scales).all()):
        raise ValueError("cannot write .splat: non-finite means or scales")
    opacity = sigmoid(g.opacity_logits)
    order = np.argsort(-(np.exp(g.log_scales.astype(np.float64).sum(axis=1)) * opacity), kind="stable")
    rec = np.zeros(len(g), SPLAT_DTYPE)
    rec["pos"] = g.means[order]
    rec["scale"] = np.exp(g.log_scales[order].astype(np.float64))
    rgba = np.concatenate([np.clip(g.colors[order], 0, 1), opacity[order, None]], axis=1)
    rec["rgba"] = np.clip(np.round(rgba * 255.0), 0, 255).astype(np.uint8)
    rec["rot"] = np.clip(np.round(normalized_quats(g.quats[order]) * 128.0 + 128.0), 0, 255).astype(np.uint8)
    return rec.tobytes()


def from_splat_bytes(data: bytes) -> GaussianArrays:
    """Decode ``.splat`` records. κ = 0 and a = False (the format has neither).

    Raises:
        ValueError: length not a multiple of 32 bytes, or non-positive scales.
    """
    if len(data) % SPLAT_DTYPE.itemsize:
        raise ValueError(f".splat data of {len(data)} bytes is not a whole number of 32-byte records")
    rec = np.frombuffer(data, SPLAT_DTYPE)
    if len(rec) and not (rec["scale"] > 0).all():
        raise ValueError(".splat data has non-positive scales")
    rgba = rec["rgba"].astype(np.float32) / 255.0
    quats = (rec["rot"].astype(np.float32) - 128.0) / 128.0
    return GaussianArrays(means=rec["pos"].copy(), quats=normalized_quats(quats).astype(np.float32),
                          log_scales=np.log(rec["scale"].astype(np.float64)).astype(np.float32),
                          opacity_logits=_logit(rgba[:, 3]), colors=rgba[:, :3].copy(),
                          kappa=np.zeros(len(rec), np.int64), active=np.zeros(len(rec), bool))


def write_splat(path: PathLike, gaussians) -> int:
    """Write a ``.splat`` file. Returns its size in bytes. Raises OSError / ValueError."""
    data = to_splat_bytes(gaussians)
    Path(path).write_bytes(data)
    return len(data)


def read_splat(path: PathLike) -> GaussianArrays:
    """Read a ``.splat`` file. Raises FileNotFoundError / ValueError."""
    return from_splat_bytes(Path(path).read_bytes())


def write_spz(path: PathLike, gaussians) -> int:
    """Write a Niantic ``.spz`` file (version 3, SH degree 0; :mod:`gausslite.viewer.spz`). Returns its size in bytes.

    Raises:
        ValueError: non-finite parameters, or positions beyond ±2048 m (the format's 24-bit positions at 2^-12 m).
        OSError: unwritable path.
    """
    g = GaussianArrays.from_any(gaussians)
    for name in ("means", "log_scales", "quats", "opacity_logits", "colors"):
        if len(g) and not np.isfinite(getattr(g, name)).all():
            raise ValueError(f"cannot write .spz: non-finite {name}")
    data = encode_spz(g.means, g.log_scales, normalized_quats(g.quats), g.opacity_logits,
                      (g.colors.astype(np.float64) - 0.5) / SH_C0)
    Path(path).write_bytes(data)
    return len(data)


def read_spz(path: PathLike) -> GaussianArrays:
    """Read a ``.spz`` file, versions 2 to 4 (higher SH bands, if any, are ignored). κ = 0, a = False.

    Raises:
        FileNotFoundError: missing file. ValueError: not an SPZ file, or one :func:`gausslite.viewer.spz.decode_spz`
        refuses (the message names the file).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"SPZ file not found: {p}")
    try:
        d = decode_spz(p.read_bytes())
    except ValueError as e:
        raise ValueError(f"{p} is not a readable SPZ file: {e}") from e
    n = len(d["means"])
    return GaussianArrays(means=d["means"], quats=d["quats_wxyz"], log_scales=d["log_scales"],
                          opacity_logits=d["opacity_logits"],
                          colors=(d["sh_dc"].astype(np.float64) * SH_C0 + 0.5).astype(np.float32),
                          kappa=np.zeros(n, np.int64), active=np.zeros(n, bool))


def format_of(path: PathLike, fmt: str = "") -> str:
    """``fmt`` if given, else the file suffix without the dot. Raises ValueError when unsupported."""
    f = (fmt or Path(path).suffix.lstrip(".")).lower()
    if f not in FORMATS:
        raise ValueError(f"unsupported splat format {f!r} for {path}; choose one of {', '.join(FORMATS)}")
    return f


def load_map(path: PathLike) -> GaussianArrays:
    """Read a map from ``.ply`` (3DGS PLY, ours or another tool's), ``.splat`` or ``.spz``.

    Raises:
        FileNotFoundError: missing file. ValueError: unsupported suffix or unreadable content.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"map file not found: {p}")
    fmt = format_of(p)
    if fmt == "ply":
        # lazy: keeps gausslite.viewer.export importable without torch
        from gausslite.gaussians import GaussianMap

        return GaussianArrays.from_any(GaussianMap.load_ply(p))
    return read_splat(p) if fmt == "splat" else read_spz(p)


def write_map(gaussians, out: PathLike, fmt: str = "") -> int:
    """Write ``gaussians`` to ``out`` in format ``fmt`` (default: ``out``'s suffix). Returns the size in bytes.

    Raises:
        ValueError: unsupported format or non-finite parameters. OSError: unwritable path.
    """
    fmt = format_of(out, fmt)
    if fmt == "splat":
        return write_splat(out, gaussians)
    if fmt == "spz":
        return write_spz(out, gaussians)
    GaussianArrays.from_any(gaussians).to_gaussian_map().save_ply(out)
    return Path(out).stat().st_size


def export_map(src: PathLike, out: PathLike, fmt: str = "") -> int:
    """Convert the map file ``src`` (.ply/.splat/.spz) to ``out`` (see :func:`write_map`). Returns bytes written.

    Raises:
        FileNotFoundError / ValueError / OSError as :func:`load_map` and :func:`write_map`.
    """
    format_of(out, fmt)
    return write_map(load_map(src), out, fmt)


__all__ = ["FORMATS", "to_splat_bytes", "from_splat_bytes", "write_splat", "read_splat", "write_spz", "read_spz",
           "load_map", "write_map", "export_map", "format_of"]
