"""Tiny procedural test scenes shared by several test modules (not a test module itself)."""

import numpy as np

from gausslite.camera import Intrinsics
from gausslite.datasets.base import Frame


def plane_frame(i: int, shift: float = 0.0, H: int = 40, W: int = 56) -> Frame:
    """A textured plane at z = 2 m seen head-on, camera shifted along world x by ``shift`` metres."""
    intr = Intrinsics(50.0, 50.0, (W - 1) / 2, (H - 1) / 2, W, H)
    c2w = np.eye(4)
    c2w[0, 3] = shift
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    xw = (u - intr.cx) / intr.fx * 2.0 + shift
    yw = (v - intr.cy) / intr.fy * 2.0
    checker = ((np.floor(xw / 0.4) + np.floor(yw / 0.4)) % 2).astype(np.float32)
    rgb = np.stack([0.2 + 0.6 * checker, 0.5 + 0.3 * np.sin(xw * 4), 0.3 + 0.4 * (yw > 0)], -1)
    return Frame(i, i / 30.0, (rgb * 255).astype(np.uint8), np.full((H, W), 2.0, np.float32), c2w, intr)


def plane_roi(H: int = 40, W: int = 56) -> np.ndarray:
    """(H, W) bool task region of :func:`plane_frame`'s image: the box of rows 10-25 and columns 14-33."""
    r = np.zeros((H, W), bool)
    r[10:26, 14:34] = True
    return r
