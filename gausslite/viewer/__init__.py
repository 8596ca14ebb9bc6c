"""Viewing and exporting Gaussian maps: map → splat arrays (:mod:`gausslite.viewer.splats`), the
standard ``.splat`` / ``.spz`` formats (:mod:`gausslite.viewer.export`) and the viser browser viewer
(:mod:`gausslite.viewer.app`, imported on demand: it needs the ``viser`` package)."""

from gausslite.viewer.export import FORMATS, export_map, load_map, read_splat, read_spz, write_splat, write_spz
from gausslite.viewer.splats import COLOR_MODES, SplatArrays, splat_arrays

__all__ = ["COLOR_MODES", "SplatArrays", "splat_arrays", "FORMATS", "export_map", "load_map", "read_splat",
           "read_spz", "write_splat", "write_spz"]
