"""The set of Gaussians the project passes around: :class:`GaussianArrays` (numpy structure of arrays) and its
field spec :data:`GAUSSIAN_FIELDS` (paper Sec. III-A; the wire codec's record layout, ``docs/wire-format.md``).

Only numpy here; torch is touched only when converting from/to :class:`gausslite.gaussians.GaussianMap`.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, ClassVar, Mapping, Sequence, Tuple

import numpy as np

__all__ = ["GaussianArrays", "GAUSSIAN_FIELDS", "as_numpy"]

#: every field of :class:`GaussianArrays`, in wire order: name -> (dtype, shape of one row). Read-only.
GAUSSIAN_FIELDS: Mapping[str, Tuple[type, Tuple[int, ...]]] = MappingProxyType({
    "means": (np.float32, (3,)),
    "quats": (np.float32, (4,)),
    "log_scales": (np.float32, (3,)),
    "opacity_logits": (np.float32, ()),
    "colors": (np.float32, (3,)),
    "kappa": (np.int64, ()),
    "active": (np.bool_, ()),
})


def as_numpy(x: Any) -> np.ndarray:
    """``x`` as a numpy array: a torch tensor is detached and moved to the CPU (without importing torch here),
    anything else goes through ``np.asarray`` (no copy when it already is one)."""
    if hasattr(x, "detach"):  # torch.Tensor, without importing torch here
        return x.detach().cpu().numpy()
    return np.asarray(x)


@dataclass
class GaussianArrays:
    """A set of N Gaussians as numpy arrays (structure of arrays), the codec/fusion container.

    Mirrors :class:`gausslite.gaussians.GaussianMap` (paper Sec. III-A):

    Attributes:
        means: (N, 3) float32, world frame, metres.
        quats: (N, 4) float32, rotation quaternion (w, x, y, z), not necessarily normalised.
        log_scales: (N, 3) float32, natural log of per-axis standard deviation (metres).
        opacity_logits: (N,) float32, opacity = sigmoid(logit).
        colors: (N, 3) float32, RGB (nominally in [0, 1]).
        kappa: (N,) int64, active-optimisation count κ.
        active: (N,) bool, task flag a.

    Raises:
        ValueError: on inconsistent shapes (checked in ``__post_init__``).
    """

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    colors: np.ndarray
    kappa: np.ndarray
    active: np.ndarray

    #: the fields in wire order, name -> (dtype, per-row shape) (:data:`GAUSSIAN_FIELDS`)
    FIELDS: ClassVar[Mapping[str, Tuple[type, Tuple[int, ...]]]] = GAUSSIAN_FIELDS

    def __post_init__(self) -> None:
        n = None
        for name, (dtype, tail) in GAUSSIAN_FIELDS.items():
            arr = np.asarray(getattr(self, name))
            if arr.dtype != dtype:
                if name == "active" and arr.dtype != np.bool_:
                    arr = arr != 0
                else:
                    arr = arr.astype(dtype)
            if arr.ndim != 1 + len(tail) or tuple(arr.shape[1:]) != tail:
                raise ValueError(f"{name}: expected shape (N, {tail}) got {arr.shape}")
            if n is None:
                n = arr.shape[0]
            elif arr.shape[0] != n:
                raise ValueError(f"{name}: {arr.shape[0]} rows, expected {n}")
            object.__setattr__(self, name, arr)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @classmethod
    def from_any(cls, obj: Any) -> "GaussianArrays":
        """Convert a GaussianMap (torch tensors), a GaussianArrays, or a mapping of arrays.

        A mapping needs keys ``means, quats, log_scales, opacity_logits, colors, kappa``; ``active``
        is optional (default all False).  Values may be numpy arrays or torch tensors (moved to CPU).
        Conversion of float32/int64/bool CPU inputs is zero-copy.

        Raises:
            TypeError: unsupported object.  ValueError: bad shapes.
        """
        if isinstance(obj, GaussianArrays):
            return obj
        if isinstance(obj, Mapping):
            get = obj.__getitem__
            has = obj.__contains__
        elif all(hasattr(obj, k) for k in ("means", "quats", "log_scales", "kappa")):
            get = lambda k: getattr(obj, k)  # noqa: E731
            has = lambda k: hasattr(obj, k)  # noqa: E731
        else:
            raise TypeError(f"cannot convert {type(obj).__name__} to GaussianArrays")
        kw = {}
        for name in GAUSSIAN_FIELDS:
            if name == "active" and not has("active"):
                continue
            kw[name] = as_numpy(get(name))
        if "active" not in kw:
            kw["active"] = np.zeros(len(kw["means"]), dtype=bool)
        return cls(**kw)

    @classmethod
    def empty(cls) -> "GaussianArrays":
        """An empty set (N = 0)."""
        return cls(
            means=np.zeros((0, 3), np.float32), quats=np.zeros((0, 4), np.float32),
            log_scales=np.zeros((0, 3), np.float32), opacity_logits=np.zeros(0, np.float32),
            colors=np.zeros((0, 3), np.float32), kappa=np.zeros(0, np.int64),
            active=np.zeros(0, bool),
        )

    def take(self, idx: Any) -> "GaussianArrays":
        """Rows selected by an index array, boolean mask or slice."""
        return GaussianArrays(**{k: getattr(self, k)[idx] for k in GAUSSIAN_FIELDS})

    @classmethod
    def concat(cls, parts: Sequence["GaussianArrays"]) -> "GaussianArrays":
        """Row-wise concatenation (empty input gives :meth:`empty`)."""
        parts = list(parts)
        if not parts:
            return cls.empty()
        return cls(**{k: np.concatenate([getattr(p, k) for p in parts]) for k in GAUSSIAN_FIELDS})

    def equals(self, other: "GaussianArrays") -> bool:
        """Exact, bitwise equality of all fields (NaN-safe)."""
        return len(self) == len(other) and all(
            np.array_equal(
                np.ascontiguousarray(getattr(self, k)).view(np.uint8),
                np.ascontiguousarray(getattr(other, k)).view(np.uint8),
            )
            for k in GAUSSIAN_FIELDS
        )

    def to_gaussian_map(self, device: str = "cpu"):
        """Convert to :class:`gausslite.gaussians.GaussianMap` (torch tensors, copies)."""
        # lazy: keeps gausslite.core.arrays importable without torch
        import torch

        from gausslite.gaussians import GaussianMap

        return GaussianMap(**{
            k: torch.as_tensor(np.array(getattr(self, k)), device=device) for k in GAUSSIAN_FIELDS
        })
