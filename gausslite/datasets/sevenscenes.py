"""Microsoft 7-Scenes sequences (Shotton et al., CVPR 2013).

Layout of one sequence folder (``seq-01``)::

    frame-NNNNNN.color.png (or .jpg)   colour, 640x480
    frame-NNNNNN.depth.png             uint16 depth in millimetres; 0 and 65535 = invalid
    frame-NNNNNN.pose.txt              4x4 camera-to-world matrix (4 lines of 4 numbers)

Intrinsics come from ``camera-intrinsics.txt`` (a 3x3 ``K``, 3 lines of 3 numbers) in the sequence
folder or its parent when present, else the published values fx = fy = 585, cx = 320, cy = 240 at
640x480. Caveat from the dataset documentation: the raw Kinect depth is *not* registered to the colour
camera, so colour/depth pixel correspondence is approximate unless the depth was re-rendered/registered.
Images are not undistorted. When both ``.color.png`` and ``.color.jpg`` exist for a frame, ``.png`` is used. Timestamps are ``frame_id / fps`` (the dataset has no clock); ``frame_id``
is the number in the file name.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Optional, Sequence, Tuple, Union

import numpy as np

from gausslite.camera import Intrinsics, check_rigid
from gausslite.datasets.annotations import load_annotations
from gausslite.datasets.registration import DepthCamera
from gausslite.datasets.common import PosedImageDataset, select_indices

__all__ = ["SevenScenesDataset", "SEVEN_SCENES_INTRINSICS", "read_matrix_file"]

#: Published 7-Scenes intrinsics (fx, fy, cx, cy) at 640x480.
SEVEN_SCENES_INTRINSICS = (585.0, 585.0, 320.0, 240.0)
_COLOR_RE = re.compile(r"^frame-(\d+)\.color\.(png|jpg|jpeg)$", re.IGNORECASE)
_EXT_RANK = {"png": 0, "jpg": 1, "jpeg": 2}


def read_matrix_file(path: Path, rows: int, cols: int) -> np.ndarray:
    """Read a whitespace-separated ``rows`` x ``cols`` matrix (blank lines and '#' lines skipped).

    Returns:
        (rows, cols) float64.

    Raises:
        FileNotFoundError: missing file. ValueError: wrong row/column count, non-numeric or non-finite
        value (message names the file and line).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"matrix file not found: {path}")
    out = []
    with open(path, "r", encoding="utf-8") as fh:
        for lineno, line in enumerate(fh, start=1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.split()
            if len(parts) != cols:
                raise ValueError(f"{path}:{lineno}: expected {cols} numbers, got {len(parts)}")
            try:
                vals = [float(p) for p in parts]
            except ValueError:
                raise ValueError(f"{path}:{lineno}: non-numeric value") from None
            if not all(math.isfinite(v) for v in vals):
                raise ValueError(f"{path}:{lineno}: NaN or infinite value")
            if len(out) == rows:
                raise ValueError(f"{path}:{lineno}: more than {rows} rows")
            out.append(vals)
    if len(out) != rows:
        raise ValueError(f"{path}: expected {rows} rows of {cols} numbers, got {len(out)}")
    return np.asarray(out, dtype=np.float64)


class SevenScenesDataset(PosedImageDataset):
    """7-Scenes sequence folder (see the module docstring).

    Args:
        path: sequence folder holding ``frame-NNNNNN.*`` files.
        downscale: factor >= 1 (int or float) for images and intrinsics.
        max_frames: keep at most this many frames (after ``stride``).
        stride: keep every ``stride``-th frame.
        intrinsics: override: an ``Intrinsics`` or ``(fx, fy, cx, cy)`` at ``image_size``.
        image_size: ``(width, height)`` of the images, used with a 3x3 ``K`` file or a tuple override.
        depth_scale: raw depth units per metre (1000: millimetres).
        fps: frame rate for timestamps (``frame_id / fps``).
        depth_camera: ``DepthCamera`` when the depth files are not registered to colour (e.g. 7-Scenes'
            Kinect depth at fx = fy = 585 with colour taken at 525); depth is registered on load.

    Raises:
        FileNotFoundError: missing folder, no colour frames, or a frame without depth/pose file.
        ValueError: malformed pose or intrinsics file (file:line), non-rigid/NaN poses, bad
            annotations or arguments. Frame access raises for unreadable images or sizes that
            disagree with the intrinsics.
    """

    def __init__(
        self,
        path: Union[str, Path],
        downscale: Union[int, float] = 1,
        max_frames: Optional[int] = None,
        stride: int = 1,
        intrinsics: Optional[Union[Intrinsics, Sequence[float]]] = None,
        image_size: Tuple[int, int] = (640, 480),
        depth_scale: float = 1000.0,
        fps: float = 30.0,
        depth_camera: Optional[DepthCamera] = None,
    ) -> None:
        seq = Path(path)
        if not seq.is_dir():
            raise FileNotFoundError(f"7-Scenes sequence folder not found: {seq}")
        if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be a positive number, got {fps!r}")
        w, h = (int(v) for v in image_size)
        self.intrinsics_path: Optional[Path] = None
        if isinstance(intrinsics, Intrinsics):
            intr = intrinsics
        elif intrinsics is not None:
            vals = [float(v) for v in intrinsics]
            if len(vals) != 4:
                raise ValueError(f"intrinsics override must be Intrinsics or (fx, fy, cx, cy), got {intrinsics!r}")
            intr = Intrinsics(*vals, w, h)
        else:
            intr = Intrinsics(*SEVEN_SCENES_INTRINSICS, w, h)
            for d in (seq, seq.parent):
                kp = d / "camera-intrinsics.txt"
                if kp.is_file():
                    K = read_matrix_file(kp, 3, 3)
                    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0 or K[0, 1] != 0:
                        raise ValueError(f"{kp}: not a pinhole K matrix [[fx 0 cx] [0 fy cy] [0 0 1]]")
                    try:
                        intr = Intrinsics.from_K(K, w, h)
                    except ValueError as e:
                        raise ValueError(f"{kp}: {e}") from None
                    self.intrinsics_path = kp
                    break

        by_num = {}
        for f in seq.iterdir():
            m = _COLOR_RE.match(f.name)
            if not m:
                continue
            num = int(m.group(1))
            rank = _EXT_RANK[m.group(2).lower()]
            if num not in by_num or rank < by_num[num][2]:
                by_num[num] = (f, m.group(1), rank)
        if not by_num:
            raise FileNotFoundError(f"no colour frames (frame-NNNNNN.color.png/.jpg) in {seq}")
        nums = sorted(by_num)
        idx = select_indices(len(nums), stride, max_frames)
        rgb_paths, depth_paths, poses, names = [], [], [], []
        # no pose file at all: a sequence without poses (odometry estimates them, gausslite.odometry.rgbd)
        posed = any(seq.glob("frame-*.pose.txt"))
        #: the pose files a sequence without poses lacks (for the error of pose_source "given")
        self.missing_poses = str(seq / "frame-NNNNNN.pose.txt")
        for i in idx:
            f, digits, _ = by_num[nums[i]]
            dp = seq / f"frame-{digits}.depth.png"
            pp = seq / f"frame-{digits}.pose.txt"
            if not dp.is_file():
                raise FileNotFoundError(f"depth image not found for {f.name}: {dp}")
            if posed and not pp.is_file():
                raise FileNotFoundError(f"pose file not found for {f.name}: {pp}")
            if posed:
                poses.append(check_rigid(read_matrix_file(pp, 4, 4), what=str(pp)))
            rgb_paths.append(f)
            depth_paths.append(dp)
            names.append(f"frame-{digits}")
        fids = [nums[i] for i in idx]
        super().__init__(
            path=seq,
            name=seq.name,
            rgb_paths=rgb_paths,
            depth_paths=depth_paths,
            poses=np.stack(poses) if posed else None,
            timestamps=[k / float(fps) for k in fids],
            frame_ids=fids,
            frame_names=names,
            native_intrinsics=intr,
            depth_scale=depth_scale,
            downscale=downscale,
            invalid_depth_values=(65535,),
            annotations=load_annotations(seq),
            depth_camera=depth_camera,
        )
