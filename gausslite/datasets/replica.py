"""Replica RGB-D renders in the NICE-SLAM / SplaTAM / Gaussian-SLAM layout.

Layout::

    <parent>/cam_params.json           {"camera": {"w","h","fx","fy","cx","cy","scale"}}
    <parent>/<seq>/traj.txt            one row-major 4x4 camera-to-world matrix (16 floats) per line
    <parent>/<seq>/results/frameNNNNNN.jpg (or .png)   colour
    <parent>/<seq>/results/depthNNNNNN.png             16-bit depth, depth_m = value / scale

``cam_params.json`` may also sit in the sequence folder (checked first). Frames are the
``frame*.jpg|png`` files sorted by number (``.jpg`` wins when both exist for a number); the k-th frame takes the k-th pose line of ``traj.txt``
(as NICE-SLAM/SplaTAM do), so a trajectory longer than the image set is fine (office0 ships 2000 poses
for 4 images) but a shorter one is an error. Poses use OpenCV camera axes. Replica has no clock:
timestamps are ``frame_id / fps``.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import List, Optional, Union

import numpy as np

from gausslite.camera import Intrinsics, check_rigid
from gausslite.datasets.annotations import load_annotations
from gausslite.datasets.registration import DepthCamera
from gausslite.datasets.common import PosedImageDataset, select_indices

__all__ = ["ReplicaDataset", "read_cam_params", "read_traj"]

_FRAME_RE = re.compile(r"^frame(\d+)\.(jpg|jpeg|png)$", re.IGNORECASE)
_EXT_RANK = {"jpg": 0, "jpeg": 1, "png": 2}


def read_cam_params(path: Path) -> tuple:
    """Parse a NICE-SLAM ``cam_params.json``.

    Returns:
        ``(Intrinsics, depth_scale)``; depth_m = raw / depth_scale.

    Raises:
        FileNotFoundError: missing file. ValueError: invalid JSON, missing ``camera`` keys
        (``w h fx fy cx cy scale``) or invalid values; the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"camera parameters not found: {path}")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: invalid JSON (line {e.lineno}): {e.msg}") from None
    cam = data.get("camera") if isinstance(data, dict) else None
    if not isinstance(cam, dict):
        raise ValueError(f"{path}: missing 'camera' object")
    missing = [k for k in ("w", "h", "fx", "fy", "cx", "cy", "scale") if k not in cam]
    if missing:
        raise ValueError(f"{path}: 'camera' is missing keys {missing}")
    try:
        w, h = cam["w"], cam["h"]
        if float(w) != int(w) or float(h) != int(h):
            raise ValueError(f"image size must be integers, got w={w} h={h}")
        intr = Intrinsics(float(cam["fx"]), float(cam["fy"]), float(cam["cx"]), float(cam["cy"]), int(w), int(h))
        scale = float(cam["scale"])
        if not math.isfinite(scale) or scale <= 0:
            raise ValueError(f"scale must be a positive number, got {cam['scale']!r}")
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: {e}") from None
    return intr, scale


def read_traj(path: Path, n: int) -> np.ndarray:
    """Read the first ``n`` poses of a ``traj.txt`` (16 floats per line, row-major 4x4 camera-to-world).

    Blank lines and lines starting with ``#`` are skipped; only the first ``n`` pose lines are parsed.

    Returns:
        (n, 4, 4) float64 poses.

    Raises:
        FileNotFoundError: missing file. ValueError: fewer than ``n`` pose lines, a line without 16
        numbers, or a non-rigid / NaN pose; the message names the file and line.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"trajectory not found: {path}")
    poses: List[np.ndarray] = []
    with open(path, "r", encoding="utf-8") as fh:
        for lineno, line in enumerate(fh, start=1):
            if len(poses) >= n:
                break
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.split()
            if len(parts) != 16:
                raise ValueError(f"{path}:{lineno}: expected 16 numbers (row-major 4x4), got {len(parts)}")
            try:
                T = np.array([float(x) for x in parts], dtype=np.float64).reshape(4, 4)
            except ValueError:
                raise ValueError(f"{path}:{lineno}: non-numeric value in pose line") from None
            poses.append(check_rigid(T, what=f"{path}:{lineno}"))
    if len(poses) < n:
        raise ValueError(f"{path}: has {len(poses)} poses but there are {n} frames (fewer poses than frames)")
    return np.stack(poses) if poses else np.zeros((0, 4, 4))


class ReplicaDataset(PosedImageDataset):
    """Replica sequence in the NICE-SLAM layout (see the module docstring).

    Args:
        path: sequence folder (``.../room0``) holding ``results/`` and ``traj.txt``. A parent folder
            holding exactly one such sequence folder is accepted too.
        downscale: factor >= 1 (int or float) for images and intrinsics (see ``loader`` module).
        max_frames: keep at most this many frames (after ``stride``).
        stride: keep every ``stride``-th frame.
        cam_params: explicit ``cam_params.json`` path (default: sequence folder, then parent).
        depth_scale: override for the ``scale`` of ``cam_params.json`` (raw units per metre).
        fps: frame rate used to make timestamps (``frame_id / fps``); Replica has no clock.
        depth_camera: ``DepthCamera`` when the depth files are not registered to colour; depth is
            registered on load.

    Attributes: see :class:`~gausslite.datasets.common.PosedImageDataset`; ``annotations`` is loaded
    from ``objects.json``/``tasks.json`` in the sequence folder or its parent (None when absent).

    Raises:
        FileNotFoundError: missing folder, ``results/``, ``traj.txt``, ``cam_params.json``, depth file
            for a frame, or no frames at all.
        ValueError: bad ``cam_params.json``, bad/too-short ``traj.txt`` (file:line), bad annotations.
        Frame access raises for unreadable images or sizes that disagree with the intrinsics.
    """

    def __init__(
        self,
        path: Union[str, Path],
        downscale: Union[int, float] = 1,
        max_frames: Optional[int] = None,
        stride: int = 1,
        cam_params: Optional[Union[str, Path]] = None,
        depth_scale: Optional[float] = None,
        fps: float = 30.0,
        depth_camera: Optional[DepthCamera] = None,
    ) -> None:
        seq = Path(path)
        if not seq.is_dir():
            raise FileNotFoundError(f"Replica sequence folder not found: {seq}")
        if not (seq / "results").is_dir():
            subs = [s for s in sorted(seq.iterdir()) if s.is_dir() and (s / "results").is_dir()]
            if len(subs) != 1:
                raise FileNotFoundError(f"Replica results folder not found: {seq / 'results'}")
            seq = subs[0]
        results = seq / "results"
        if cam_params is None:
            for d in (seq, seq.parent):
                if (d / "cam_params.json").is_file():
                    cam_params = d / "cam_params.json"
                    break
            else:
                raise FileNotFoundError(
                    f"cam_params.json not found in {seq} or {seq.parent}"
                )
        intr, scale = read_cam_params(Path(cam_params))
        if depth_scale is not None:
            scale = float(depth_scale)
        if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be a positive number, got {fps!r}")

        by_num = {}
        for f in results.iterdir():
            m = _FRAME_RE.match(f.name)
            if not m:
                continue
            num = int(m.group(1))
            prev = by_num.get(num)
            if prev is None or _EXT_RANK[m.group(2).lower()] < _EXT_RANK[_FRAME_RE.match(prev[0].name).group(2).lower()]:
                by_num[num] = (f, m.group(1))
        if not by_num:
            raise FileNotFoundError(f"no colour frames (frameNNNNNN.jpg/.png) in {results}")
        nums = sorted(by_num)
        n_all = len(nums)
        depth_all = [results / f"depth{by_num[k][1]}.png" for k in nums]
        for k, dp in zip(nums, depth_all):
            if not dp.is_file():
                raise FileNotFoundError(f"depth image not found for {by_num[k][0].name}: {dp}")
        # no traj.txt at all: a sequence without poses (odometry estimates them, gausslite.odometry.rgbd)
        poses_all = read_traj(seq / "traj.txt", n_all) if (seq / "traj.txt").exists() else None
        #: the pose file a sequence without poses lacks (for the error of pose_source "given")
        self.missing_poses = str(seq / "traj.txt")

        idx = select_indices(n_all, stride, max_frames)
        super().__init__(
            path=seq,
            name=seq.name,
            rgb_paths=[by_num[nums[i]][0] for i in idx],
            depth_paths=[depth_all[i] for i in idx],
            poses=None if poses_all is None else (poses_all[idx] if idx else np.zeros((0, 4, 4))),
            timestamps=[i / float(fps) for i in idx],
            frame_ids=idx,
            frame_names=[by_num[nums[i]][0].stem for i in idx],
            native_intrinsics=intr,
            depth_scale=scale,
            downscale=downscale,
            annotations=load_annotations(seq),
            depth_camera=depth_camera,
        )
        self.cam_params_path = Path(cam_params)
