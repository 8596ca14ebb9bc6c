"""GaussianMap: the structure-of-arrays Gaussian map (paper Sec. III-A).

A :class:`GaussianMap` holds N anisotropic 3D Gaussians as seven parallel tensors on one device.
Structural operations (``append``, ``prune``, ``subset``, ``cap``, ``densify``) never modify a map in
place: they return a new map built from gathered/concatenated tensors. They are plain tensor ops, so
if the input fields require grad the outputs are non-leaf tensors of the same graph; call
:meth:`GaussianMap.detach` (and re-wrap as parameters) to start a fresh optimisation.

PLY export/import follows the layout of the reference 3DGS implementation (Kerbl et al. 2023,
``GaussianModel.save_ply``) so the files open in common splat viewers, plus GaussLite's extra vertex
properties; see :meth:`GaussianMap.save_ply`.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Optional, Tuple, Union

import numpy as np
import torch
from plyfile import PlyData, PlyElement

logger = logging.getLogger(__name__)

#: Zeroth-order real spherical-harmonic constant, Y_0^0 = 1 / (2 sqrt(pi)). 3DGS stores the DC colour
#: as ``f_dc = (rgb - 0.5) / SH_C0``.
SH_C0 = 0.28209479177387814

#: Largest κ representable in the PLY ``kappa`` property (stored as ``uint32``); larger counts saturate.
PLY_KAPPA_MAX = 2**32 - 1

# Standard 3DGS vertex properties, in file order (SH degree 0: no f_rest_*).
_PLY_STD_PROPS = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    + [f"scale_{i}" for i in range(3)]
    + [f"rot_{i}" for i in range(4)]
)
_PLY_REQUIRED = [p for p in _PLY_STD_PROPS if p not in ("nx", "ny", "nz")]
_PLY_EXACT_RGB = ["rgb_0", "rgb_1", "rgb_2"]

IndexLike = Union[torch.Tensor, np.ndarray, list, slice]


def _logit(p: torch.Tensor) -> torch.Tensor:
    return torch.log(p) - torch.log1p(-p)


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from (w, x, y, z) quaternions.

    Args:
        quats: (N, 4) float tensor, not necessarily normalised (normalised here; an all-zero
            quaternion yields the identity matrix rather than NaN).
    Returns:
        (N, 3, 3) rotation matrices R with columns the Gaussian's local axes in the world frame.
    """
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    r = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return r.reshape(quats.shape[:-1] + (3, 3))


@dataclass(eq=False, repr=False)
class GaussianMap:
    """N anisotropic 3D Gaussians, structure of arrays, all tensors on one device.

    Fields (N = number of Gaussians):
        means: (N, 3) float32, world frame, metres.
        quats: (N, 4) float32, rotation quaternion (w, x, y, z), not necessarily normalised
            (normalised by the renderer).
        log_scales: (N, 3) float32, natural log of the per-axis standard deviation (metres).
        opacity_logits: (N,) float32, opacity = sigmoid(opacity_logits).
        colors: (N, 3) float32, RGB in [0, 1] (SH degree 0 stored as plain RGB; no activation).
        active: (N,) bool, task flag a_i set at seed time from the relevance map (paper III-A).
        kappa: (N,) int64, active-optimisation count κ_i (paper III-A, III-E).

    Construction validates shapes, dtypes and devices (``ValueError`` naming the offending field);
    values (finiteness, κ ≥ 0) are not checked here because that would force a device sync on every
    construction. ``save_ply`` rejects negative κ. ``==`` is identity (tensors have no single truth
    value) and ``repr`` is a one-line summary.
    """

    means: torch.Tensor
    quats: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    colors: torch.Tensor
    active: torch.Tensor
    kappa: torch.Tensor

    # ------------------------------------------------------------------ basics
    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, torch.Tensor):
                raise ValueError(f"GaussianMap.{f.name} must be a torch.Tensor, got {type(v).__name__}")
        if self.means.ndim != 2 or self.means.shape[1] != 3:
            raise ValueError(f"GaussianMap.means must have shape (N, 3), got {tuple(self.means.shape)}")
        n = self.means.shape[0]
        dev = self.means.device
        expected = {
            "means": ((n, 3), torch.float32),
            "quats": ((n, 4), torch.float32),
            "log_scales": ((n, 3), torch.float32),
            "opacity_logits": ((n,), torch.float32),
            "colors": ((n, 3), torch.float32),
            "active": ((n,), torch.bool),
            "kappa": ((n,), torch.int64),
        }
        for name, (shape, dtype) in expected.items():
            v = getattr(self, name)
            if tuple(v.shape) != shape:
                raise ValueError(
                    f"GaussianMap.{name} must have shape {shape} (N={n} from means), got {tuple(v.shape)}"
                )
            if v.dtype != dtype:
                raise ValueError(f"GaussianMap.{name} must have dtype {dtype}, got {v.dtype}")
            if v.device != dev:
                raise ValueError(
                    f"GaussianMap.{name} is on {v.device} but means is on {dev}; all fields must share a device"
                )

    def __repr__(self) -> str:
        n_active = int(self.active.sum()) if self.device.type != "meta" else -1
        return f"GaussianMap(N={len(self)}, active={n_active}, device={self.device})"

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def device(self) -> torch.device:
        """Device of every field."""
        return self.means.device

    @property
    def opacity(self) -> torch.Tensor:
        """(N,) float32 opacity in (0, 1) = sigmoid(opacity_logits)."""
        return torch.sigmoid(self.opacity_logits)

    @property
    def scales(self) -> torch.Tensor:
        """(N, 3) float32 per-axis standard deviations in metres = exp(log_scales)."""
        return torch.exp(self.log_scales)

    def _map(self, fn) -> "GaussianMap":
        return GaussianMap(**{f.name: fn(getattr(self, f.name)) for f in fields(self)})

    @classmethod
    def empty(cls, device: Union[str, torch.device] = "cpu") -> "GaussianMap":
        """A map with N = 0 on ``device``."""
        f = lambda *s: torch.zeros(s, dtype=torch.float32, device=device)  # noqa: E731
        return cls(
            means=f(0, 3), quats=f(0, 4), log_scales=f(0, 3), opacity_logits=f(0), colors=f(0, 3),
            active=torch.zeros(0, dtype=torch.bool, device=device),
            kappa=torch.zeros(0, dtype=torch.int64, device=device),
        )

    @classmethod
    def from_points(
        cls,
        means: torch.Tensor,
        colors: torch.Tensor,
        scales: Union[torch.Tensor, float],
        opacity: Union[torch.Tensor, float] = 0.5,
        active: Optional[Union[torch.Tensor, bool]] = None,
    ) -> "GaussianMap":
        """Isotropic/axis-aligned Gaussians seeded at points (e.g. back-projected depth pixels).

        Args:
            means: (N, 3) world-frame positions, metres (any float dtype; stored as float32).
            colors: (N, 3) RGB in [0, 1].
            scales: standard deviation(s) in metres, > 0: a scalar, (N,) (isotropic) or (N, 3).
            opacity: initial opacity in (0, 1) (scalar or (N,)); stored as its logit.
            active: task flags a_i: None (all False), a bool, or an (N,) bool tensor.
        Returns:
            A map on ``means.device`` with identity rotations (1, 0, 0, 0), ``log_scales =
            log(scales)``, κ = 0.
        Raises:
            ValueError: on shape mismatch, non-positive scales or opacity outside (0, 1).
        """
        means = torch.as_tensor(means)
        dev = means.device
        if means.ndim != 2 or means.shape[1] != 3:
            raise ValueError(f"means must have shape (N, 3), got {tuple(means.shape)}")
        n = means.shape[0]
        means = means.to(torch.float32)
        colors = torch.as_tensor(colors, device=dev).to(torch.float32)
        if tuple(colors.shape) != (n, 3):
            raise ValueError(f"colors must have shape ({n}, 3), got {tuple(colors.shape)}")
        s = torch.as_tensor(scales, device=dev).to(torch.float32)
        if s.ndim == 0:
            s = s.expand(n, 3)
        elif tuple(s.shape) == (n,):
            s = s[:, None].expand(n, 3)
        elif tuple(s.shape) != (n, 3):
            raise ValueError(f"scales must be a scalar, ({n},) or ({n}, 3), got {tuple(s.shape)}")
        if n and not bool((s > 0).all()):
            raise ValueError("scales must be > 0 (metres)")
        o = torch.as_tensor(opacity, device=dev).to(torch.float32)
        if o.ndim == 0:
            o = o.expand(n)
        elif tuple(o.shape) != (n,):
            raise ValueError(f"opacity must be a scalar or ({n},), got {tuple(o.shape)}")
        if n and not bool(((o > 0) & (o < 1)).all()):
            raise ValueError("opacity must lie strictly inside (0, 1)")
        if active is None:
            a = torch.zeros(n, dtype=torch.bool, device=dev)
        else:
            a = torch.as_tensor(active, device=dev)
            if a.ndim == 0:
                a = a.expand(n)
            if tuple(a.shape) != (n,):
                raise ValueError(f"active must be a bool or ({n},), got {tuple(a.shape)}")
            a = a.to(torch.bool)
        quats = torch.zeros(n, 4, dtype=torch.float32, device=dev)
        quats[:, 0] = 1.0
        return cls(
            means=means.clone(), quats=quats, log_scales=torch.log(s).contiguous(),
            opacity_logits=_logit(o).contiguous(), colors=colors.clone(), active=a.clone().contiguous(),
            kappa=torch.zeros(n, dtype=torch.int64, device=dev),
        )

    def to(self, device: Union[str, torch.device]) -> "GaussianMap":
        """Copy of the map on ``device`` (fields are shared if already there)."""
        return self._map(lambda t: t.to(device))

    def detach(self) -> "GaussianMap":
        """Map whose fields are detached from any autograd graph (storage shared)."""
        return self._map(lambda t: t.detach())

    def clone(self) -> "GaussianMap":
        """Deep copy (new storage, detached)."""
        return self._map(lambda t: t.detach().clone())

    # ------------------------------------------------------- structural ops
    def append(self, other: "GaussianMap") -> "GaussianMap":
        """Concatenation [self rows..., other rows...].

        Raises:
            ValueError: if ``other`` is on a different device.
        """
        if not isinstance(other, GaussianMap):
            raise ValueError(f"can only append a GaussianMap, got {type(other).__name__}")
        if other.device != self.device:
            raise ValueError(f"cannot append a map on {other.device} to a map on {self.device}")
        return GaussianMap(
            **{f.name: torch.cat([getattr(self, f.name), getattr(other, f.name)]) for f in fields(self)}
        )

    def _as_index(self, index_or_mask: IndexLike) -> torch.Tensor:
        n = len(self)
        if isinstance(index_or_mask, slice):
            return torch.arange(n, device=self.device)[index_or_mask]
        idx = torch.as_tensor(index_or_mask, device=self.device)
        if idx.dtype == torch.bool:
            if tuple(idx.shape) != (n,):
                raise ValueError(f"mask must have shape ({n},), got {tuple(idx.shape)}")
            return idx.nonzero().squeeze(1)
        if idx.dtype.is_floating_point or idx.dtype.is_complex:
            raise ValueError(f"index must be integer or bool, got {idx.dtype}")
        if idx.ndim != 1:
            raise ValueError(f"index must be 1-D, got shape {tuple(idx.shape)}")
        idx = idx.to(torch.int64)
        if idx.numel() and (int(idx.min()) < -n or int(idx.max()) >= n):
            raise ValueError(f"index out of range for a map of {n} Gaussians")
        return torch.where(idx < 0, idx + n, idx)

    def subset(self, index_or_mask: IndexLike) -> "GaussianMap":
        """Gathered copy of selected rows.

        Args:
            index_or_mask: (N,) bool mask, 1-D integer index (any order, repeats allowed, negative
                indices wrap), or a slice.
        Raises:
            ValueError: wrong mask length, non-integer index or out-of-range index.
        """
        idx = self._as_index(index_or_mask)
        return self._map(lambda t: t[idx])

    def prune(self, keep_mask: torch.Tensor) -> "GaussianMap":
        """Rows where ``keep_mask`` (N,) bool is True, in their original order."""
        km = torch.as_tensor(keep_mask, device=self.device)
        if km.dtype != torch.bool or tuple(km.shape) != (len(self),):
            raise ValueError(f"keep_mask must be a ({len(self)},) bool tensor, got {km.dtype} {tuple(km.shape)}")
        return self.subset(km)

    def cap(self, max_gaussians: int, score: Optional[torch.Tensor] = None) -> Tuple["GaussianMap", torch.Tensor]:
        """Enforce a global budget: keep the ``max_gaussians`` highest-scoring Gaussians.

        Args:
            max_gaussians: budget, >= 0.
            score: (N,) float score (higher = keep); default opacity (sigmoid of the logit). NaN scores
                rank below everything.
        Returns:
            (capped map in original row order, keep_mask (N,) bool). Ties are broken
            deterministically in favour of the lower row index. If N <= max_gaussians every row is
            kept (the returned map is a gathered copy either way).
        """
        if int(max_gaussians) != max_gaussians or max_gaussians < 0:
            raise ValueError(f"max_gaussians must be a non-negative integer, got {max_gaussians}")
        n = len(self)
        if score is None:
            score = self.opacity_logits  # sigmoid is monotonic
        score = torch.as_tensor(score, device=self.device).detach()
        if tuple(score.shape) != (n,):
            raise ValueError(f"score must have shape ({n},), got {tuple(score.shape)}")
        keep = torch.zeros(n, dtype=torch.bool, device=self.device)
        if n <= max_gaussians:
            keep[:] = True
        else:
            s = score.to(torch.float64)
            s = torch.where(torch.isnan(s), torch.full_like(s, -math.inf), s)
            order = torch.sort(s, descending=True, stable=True).indices
            keep[order[: int(max_gaussians)]] = True
        return self.prune(keep), keep

    def densify(
        self,
        clone_mask: torch.Tensor,
        split_mask: torch.Tensor,
        n_split: int = 2,
        generator: Optional[torch.Generator] = None,
        split_mode: str = "sample",
    ) -> Tuple["GaussianMap", torch.Tensor]:
        """Standard 3DGS clone/split densification (Kerbl et al. 2023, Sec. 5.2).

        * Clone: a copy of the Gaussian is appended (identical parameters; the optimiser's next step
          moves the two apart).
        * Split, ``split_mode="sample"`` (3DGS): the Gaussian is removed and replaced by ``n_split`` daughters
          whose means are sampled from the parent's distribution N(μ, R S Sᵀ Rᵀ) and whose log-scales are the
          parent's minus log(0.8 · n_split) (i.e. scale / (0.8 n)).
        * Split, ``split_mode="axis"`` (``n_split`` must be 2): two daughters on the parent's longest axis
          e (world frame, the column of R of the largest scale σ), at μ ± σ/2 · e, that axis's scale
          σ √3 / 2 and the others the parent's, so that the pair's second moment along e is the parent's
          (σ²/4 + 3σ²/4); each daughter's opacity is 1 − √(1 − α), so that where the two overlap they
          composite to the parent's α (the opacity correction of Rota Bulò et al., "Revising Densification
          in Gaussian Splatting", ECCV 2024). The rendered image barely changes at the split (sampled
          daughters, smaller on every axis, leave gaps: measured in docs/mapper.md, "Density control").
        * Every new row inherits the parent's quaternion, opacity logit, colour, ``active`` flag and
          κ (daughters start with the parent's κ).
        * A Gaussian in both masks is only split (split takes precedence; the clone flag is ignored),
          which matches the reference implementation where the two criteria are disjoint by size.

        Row order of the result:
            [kept originals (rows not split, original order)...,
             clones (cloned rows in index order)...,
             split daughters (parent-major: all n_split daughters of the first split parent, then the
             next parent, ...)].

        Args:
            clone_mask, split_mask: (N,) bool.
            n_split: daughters per split Gaussian, >= 1.
            generator: optional torch.Generator on this map's device for reproducible sampling.
        Returns:
            (new map, parent_index) where parent_index is (M,) int64 on the map's device giving for
            each result row the input row it derives from (use it to gather optimiser state).
        """
        n = len(self)
        dev = self.device
        cm = torch.as_tensor(clone_mask, device=dev)
        sm = torch.as_tensor(split_mask, device=dev)
        for name, m in (("clone_mask", cm), ("split_mask", sm)):
            if m.dtype != torch.bool or tuple(m.shape) != (n,):
                raise ValueError(f"{name} must be a ({n},) bool tensor, got {m.dtype} {tuple(m.shape)}")
        if int(n_split) != n_split or n_split < 1:
            raise ValueError(f"n_split must be an integer >= 1, got {n_split}")
        n_split = int(n_split)
        if split_mode not in ("sample", "axis"):
            raise ValueError(f"split_mode must be 'sample' or 'axis', got {split_mode!r}")
        if split_mode == "axis" and n_split != 2:
            raise ValueError(f"split_mode='axis' splits in 2, got n_split={n_split}")
        cm = cm & ~sm
        arange = torch.arange(n, device=dev)
        kept_idx = arange[~sm]
        clone_idx = arange[cm]
        split_idx = arange[sm]
        daughter_parent = split_idx.repeat_interleave(n_split)
        parent_index = torch.cat([kept_idx, clone_idx, daughter_parent])
        out = self.subset(parent_index)
        n_d = daughter_parent.numel()
        if n_d and split_mode == "axis":
            out = self._axis_daughters(out, daughter_parent, kept_idx.numel() + clone_idx.numel())
        elif n_d:
            start = kept_idx.numel() + clone_idx.numel()
            p_means = self.means[daughter_parent]
            p_scales = torch.exp(self.log_scales[daughter_parent])
            rot = quat_to_rotmat(self.quats[daughter_parent])
            z = torch.randn((n_d, 3), generator=generator, device=dev, dtype=torch.float32)
            offsets = torch.einsum("nij,nj->ni", rot, p_scales * z)
            means = torch.cat([out.means[:start], p_means + offsets])
            log_scales = torch.cat(
                [out.log_scales[:start], self.log_scales[daughter_parent] - math.log(0.8 * n_split)]
            )
            out = GaussianMap(
                means=means, quats=out.quats, log_scales=log_scales, opacity_logits=out.opacity_logits,
                colors=out.colors, active=out.active, kappa=out.kappa,
            )
        return out, parent_index

    def _axis_daughters(self, out: "GaussianMap", parent: torch.Tensor, start: int) -> "GaussianMap":
        """``out`` with its rows from ``start`` on (the daughters of ``parent`` (2K,), pairs in order) replaced by
        the axis split of :meth:`densify`."""
        n_d = parent.numel()
        log_scales = self.log_scales[parent].clone()
        k = log_scales.argmax(dim=1, keepdim=True)
        rot = quat_to_rotmat(self.quats[parent])
        axis = torch.gather(rot, 2, k[:, None, :].expand(n_d, 3, 1)).squeeze(2)  # column k: the longest axis
        sigma = log_scales.gather(1, k).exp()
        sign = torch.ones((n_d, 1), dtype=sigma.dtype, device=sigma.device)
        sign[1::2] = -1.0
        means = self.means[parent] + (0.5 * sigma * sign) * axis.to(sigma.dtype)
        log_scales.scatter_add_(1, k, torch.full_like(sigma, 0.5 * math.log(0.75)))
        alpha = torch.sigmoid(self.opacity_logits[parent])
        half = (1.0 - torch.sqrt(1.0 - alpha)).clamp(1e-6, 1.0 - 1e-6)
        return GaussianMap(
            means=torch.cat([out.means[:start], means]), quats=out.quats,
            log_scales=torch.cat([out.log_scales[:start], log_scales]),
            opacity_logits=torch.cat([out.opacity_logits[:start], torch.log(half) - torch.log1p(-half)]),
            colors=out.colors, active=out.active, kappa=out.kappa,
        )

    # ------------------------------------------------------------------ PLY
    def save_ply(self, path: Union[str, os.PathLike], exact_colors: bool = True) -> None:
        """Write a binary little-endian 3DGS PLY (one ``vertex`` element, N rows).

        Vertex properties, in order (all float32 unless noted):
            x, y, z                 means (world, metres)
            nx, ny, nz              zeros (kept for viewer compatibility)
            f_dc_0, f_dc_1, f_dc_2  (rgb - 0.5) / SH_C0 (SH degree 0; no f_rest_*)
            opacity                 opacity logit
            scale_0..2              log-scales
            rot_0..3                quaternion (w, x, y, z), as stored (not normalised)
            kappa                   uint32 ("uint"): κ saturated at PLY_KAPPA_MAX = 2**32 - 1.
                                    PLY has no 64-bit integer type, so int64 is not an option;
                                    a warning is logged when saturation happens.
            active                  uint8 ("uchar"): 1 = active
            rgb_0..2                (only if ``exact_colors``) the float32 colour itself. The f_dc
                                    transform is not exactly invertible in float32 (small RGB values
                                    lose bits), so these make the round trip bit-exact; viewers
                                    ignore unknown properties.

        Raises:
            ValueError: if any κ is negative.
            OSError: if the file cannot be written (e.g. missing parent directory).
        """
        t = self.detach().to("cpu")
        n = len(t)
        kappa = t.kappa.numpy()
        if n and kappa.min() < 0:
            raise ValueError("kappa must be >= 0 to be saved (it is a count)")
        if n and kappa.max() > PLY_KAPPA_MAX:
            logger.warning("kappa above %d saturated in PLY export", PLY_KAPPA_MAX)
        colors64 = t.colors.numpy().astype(np.float64)
        f_dc = ((colors64 - 0.5) / SH_C0).astype(np.float32)
        cols = {
            "x": t.means[:, 0].numpy(), "y": t.means[:, 1].numpy(), "z": t.means[:, 2].numpy(),
            "nx": np.zeros(n, np.float32), "ny": np.zeros(n, np.float32), "nz": np.zeros(n, np.float32),
            "f_dc_0": f_dc[:, 0], "f_dc_1": f_dc[:, 1], "f_dc_2": f_dc[:, 2],
            "opacity": t.opacity_logits.numpy(),
        }
        for i in range(3):
            cols[f"scale_{i}"] = t.log_scales[:, i].numpy()
        for i in range(4):
            cols[f"rot_{i}"] = t.quats[:, i].numpy()
        dtype = [(p, "<f4") for p in _PLY_STD_PROPS] + [("kappa", "<u4"), ("active", "u1")]
        cols["kappa"] = np.minimum(kappa, PLY_KAPPA_MAX).astype(np.uint32)
        cols["active"] = t.active.numpy().astype(np.uint8)
        if exact_colors:
            dtype += [(p, "<f4") for p in _PLY_EXACT_RGB]
            for i, p in enumerate(_PLY_EXACT_RGB):
                cols[p] = t.colors[:, i].numpy()
        arr = np.empty(n, dtype=dtype)
        for name, _ in dtype:
            arr[name] = cols[name]
        PlyData([PlyElement.describe(arr, "vertex")], text=False, byte_order="<").write(str(path))

    @classmethod
    def load_ply(cls, path: Union[str, os.PathLike], device: Union[str, torch.device] = "cpu") -> "GaussianMap":
        """Read a 3DGS PLY (ours, or a standard one from another 3DGS tool).

        Required vertex properties: x, y, z, f_dc_0..2, opacity, scale_0..2, rot_0..3 (any numeric
        PLY type; cast to float32). Optional: ``kappa`` (default 0), ``active`` (default False,
        nonzero = True), ``rgb_0..2`` (exact colours written by :meth:`save_ply`; used only if they
        agree with f_dc to 1e-4, otherwise the file was edited elsewhere and f_dc wins with a
        warning). Higher-order SH (``f_rest_*``) is ignored (only the DC term is used) with a debug
        log. Colour = f_dc * SH_C0 + 0.5 (not clamped).

        Raises:
            FileNotFoundError: ``path`` does not exist.
            ValueError: not a PLY, no ``vertex`` element, missing required properties, or negative κ.
        """
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"PLY file not found: {p}")
        try:
            ply = PlyData.read(str(p))
        except Exception as e:  # plyfile raises several exception types for malformed headers
            raise ValueError(f"{p} is not a readable PLY file: {e}") from e
        if "vertex" not in [el.name for el in ply.elements]:
            raise ValueError(f"{p}: PLY has no 'vertex' element")
        v = ply["vertex"].data
        names = set(v.dtype.names or ())
        missing = [q for q in _PLY_REQUIRED if q not in names]
        if missing:
            raise ValueError(f"{p}: PLY vertex element lacks required 3DGS properties {missing}")
        rest = sorted(q for q in names if q.startswith("f_rest_"))
        if rest:
            logger.debug("%s: ignoring %d higher-order SH properties (f_rest_*); using DC only", p, len(rest))
        n = len(v)
        col = lambda q: np.asarray(v[q], dtype=np.float32)  # noqa: E731
        means = np.stack([col("x"), col("y"), col("z")], 1)
        f_dc = np.stack([col(f"f_dc_{i}") for i in range(3)], 1).astype(np.float64)
        colors = (f_dc * SH_C0 + 0.5).astype(np.float32)
        if all(q in names for q in _PLY_EXACT_RGB):
            exact = np.stack([col(q) for q in _PLY_EXACT_RGB], 1)
            if n == 0 or np.all(np.abs(exact.astype(np.float64) - colors) <= 1e-4):
                colors = exact
            else:
                logger.warning("%s: rgb_* disagree with f_dc_* (edited elsewhere?); using f_dc_*", p)
        if "kappa" in names:
            kappa = np.asarray(v["kappa"]).astype(np.int64)
            if n and kappa.min() < 0:
                raise ValueError(f"{p}: negative kappa in PLY")
        else:
            kappa = np.zeros(n, np.int64)
        active = np.asarray(v["active"]) != 0 if "active" in names else np.zeros(n, bool)
        # fresh C-contiguous copies (views of a structured array have record-sized strides)
        t = lambda a: torch.from_numpy(np.array(a, copy=True, order="C")).to(device)  # noqa: E731
        return cls(
            means=t(means),
            quats=t(np.stack([col(f"rot_{i}") for i in range(4)], 1)),
            log_scales=t(np.stack([col(f"scale_{i}") for i in range(3)], 1)),
            opacity_logits=t(col("opacity")),
            colors=t(colors),
            active=t(active),
            kappa=t(kappa),
        )
