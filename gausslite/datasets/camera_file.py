"""The camera file: the intrinsics, depth scale and distortion of any RGB-D camera's image files.

A YAML (``camera.yaml``) or JSON (``camera.json``) mapping with ``width``, ``height`` (pixels), ``fx``, ``fy``,
``cx``, ``cy`` (pixels, OpenCV pinhole), ``depth_scale`` (depth units per metre: 1000 for millimetres, 5000 for
TUM RGB-D), and optionally ``distortion`` (OpenCV ``[k1, k2, p1, p2, k3]``, or a mapping of those names) and
``fps`` (frames per second, 30 by default). It describes the camera-file folder layout
(:mod:`gausslite.datasets.camera_folder`) and, beside a TUM RGB-D sequence, overrides its Freiburg camera.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Tuple, Union

import yaml

from gausslite.camera import Intrinsics

__all__ = ["CAMERA_FILES", "CameraFile", "find_camera_file", "read_camera_file"]

#: the camera file's names, in the order they are looked for
CAMERA_FILES = ("camera.yaml", "camera.yml", "camera.json")


@dataclass(frozen=True)
class CameraFile:
    """A camera file's content.

    Attributes:
        path: the file.
        intrinsics: pinhole intrinsics (pixels) of the image files.
        depth_scale: depth units per metre.
        distortion: OpenCV ``(k1, k2, p1, p2, k3)``; zeros: none.
        fps: frames per second (timestamps when the file names are not times).
    """

    path: Path
    intrinsics: Intrinsics
    depth_scale: float
    distortion: Tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    fps: float = 30.0


def find_camera_file(folder: Union[str, Path]) -> Optional[Path]:
    """The camera file (:data:`CAMERA_FILES`) in ``folder``, or None."""
    for name in CAMERA_FILES:
        if (Path(folder) / name).is_file():
            return Path(folder) / name
    return None


def _number(path: Path, data: dict, key: str, positive: bool = True, integer: bool = False) -> float:
    """``data[key]`` as a finite number (> 0 when ``positive``). Raises ValueError naming the file and the field."""
    if key not in data:
        raise ValueError(f"{path}: field '{key}' is missing")
    v = data[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (positive and v <= 0):
        raise ValueError(f"{path}: field '{key}' must be a {'positive ' if positive else ''}"
                         f"{'integer' if integer else 'number'}, got {v!r}")
    if integer and int(v) != v:
        raise ValueError(f"{path}: field '{key}' must be an integer, got {v!r}")
    return float(v)


def read_camera_file(path: Union[str, Path]) -> CameraFile:
    """Read a camera file (YAML or JSON; fields in the module docstring).

    Returns:
        the :class:`CameraFile`.
    Raises:
        FileNotFoundError: no such file. ValueError: unreadable YAML/JSON, or a missing or malformed field (one
            line naming the file and the field).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"camera file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
        data = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except (ValueError, yaml.YAMLError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: not valid {'JSON' if path.suffix.lower() == '.json' else 'YAML'} "
                         f"({str(e).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of fields (width, height, fx, fy, cx, cy, depth_scale)")
    unknown = sorted(set(data) - {"width", "height", "fx", "fy", "cx", "cy", "depth_scale", "distortion", "fps"})
    if unknown:
        raise ValueError(f"{path}: unknown field '{unknown[0]}' (fields: width, height, fx, fy, cx, cy, depth_scale, "
                         f"distortion, fps)")
    w, h = (int(_number(path, data, k, integer=True)) for k in ("width", "height"))
    fx, fy = (_number(path, data, k) for k in ("fx", "fy"))
    cx, cy = (_number(path, data, k, positive=False) for k in ("cx", "cy"))
    scale = _number(path, data, "depth_scale")
    dist = data.get("distortion") or [0.0] * 5
    if isinstance(dist, dict):
        dist = [dist.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")]
    if (not isinstance(dist, (list, tuple)) or len(dist) not in (4, 5)
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in dist)):
        raise ValueError(f"{path}: field 'distortion' must be [k1, k2, p1, p2] or [k1, k2, p1, p2, k3] (OpenCV), "
                         f"got {data.get('distortion')!r}")
    fps = _number(path, data, "fps") if "fps" in data else 30.0
    return CameraFile(path, Intrinsics(fx, fy, cx, cy, w, h), scale,
                      tuple(float(v) for v in (*dist, 0.0)[:5]), fps)  # type: ignore[arg-type]
