"""Core types shared by every layer: :class:`~gausslite.core.arrays.GaussianArrays` and its field spec."""

from gausslite.core.arrays import GAUSSIAN_FIELDS, GaussianArrays, as_numpy

__all__ = ["GaussianArrays", "GAUSSIAN_FIELDS", "as_numpy"]
