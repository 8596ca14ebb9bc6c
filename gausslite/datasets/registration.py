"""Depth registration: re-project a depth image from its own camera into the colour camera.

Kinect-style sensors (and 7-Scenes, and many RealSense recordings with ``depth/image_rect_raw``) have
a depth camera with its own intrinsics and an optical centre a few centimetres from the colour
camera's; a depth pixel ``(u, v)`` then does not see what colour pixel ``(u, v)`` sees. Registration
(what ``depth_image_proc/register`` does in ROS):

1. back-project every valid depth pixel with the depth intrinsics (and distortion, undone with
   ``cv2.undistortPoints``): ``P_d = z * (x_n, y_n, 1)``;
2. move it to the colour optical frame, ``P_c = T_color_depth @ P_d``;
3. project it with the colour intrinsics (and the colour camera's plumb_bob distortion, so the result
   lines up with the raw colour pixels) and round to the nearest pixel;
4. z-buffer: where several points land on one colour pixel the nearest (smallest ``z_c``) wins, so
   a background surface never shows through a foreground one.

Colour pixels that no depth point lands on stay 0 (invalid). When the depth camera samples the scene
more coarsely than the colour camera (a smaller focal length in pixels), holes appear between the
splatted points; ``splat`` > 1 writes each point to a ``splat`` x ``splat`` footprint instead.

Frames: all cameras use optical axes (x right, y down, z forward; REP 103 ``*_optical_frame``),
``T_color_depth`` maps points in the depth optical frame to the colour optical frame (metres).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Sequence, Tuple

import cv2
import numpy as np

from gausslite.camera import Intrinsics
from gausslite.ros.transforms import make_transform

__all__ = ["DepthCamera", "register_depth", "project_plumb_bob", "parse_depth_camera"]


@dataclass(frozen=True)
class DepthCamera:
    """A depth camera that is not registered to the colour camera.

    Attributes:
        intrinsics: pinhole intrinsics of the depth images as stored (size = depth image size).
        T_color_depth: (4, 4) float64 pose of the depth optical frame in the colour optical frame.
        distortion: plumb_bob ``(k1, k2, p1, p2, k3)`` of the depth camera (zeros: none).
        splat: footprint in colour pixels of each re-projected depth sample (1 = nearest pixel).
    """

    intrinsics: Intrinsics
    T_color_depth: np.ndarray = field(default_factory=lambda: np.eye(4))
    distortion: Tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    splat: int = 1

    def __post_init__(self) -> None:
        T = np.asarray(self.T_color_depth, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"T_color_depth must be a finite 4x4 matrix, got shape {T.shape}")
        R = T[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0 or not np.allclose(T[3], [0, 0, 0, 1]):
            raise ValueError("T_color_depth is not a rigid transform")
        object.__setattr__(self, "T_color_depth", T)
        d = tuple(float(v) for v in self.distortion)
        if len(d) not in (4, 5, 8) or not all(np.isfinite(d)):
            raise ValueError(f"depth distortion must be 4, 5 or 8 finite plumb_bob/rational coefficients, got {d}")
        object.__setattr__(self, "distortion", d)
        if int(self.splat) < 1:
            raise ValueError(f"splat must be >= 1, got {self.splat}")

    def is_identity_for(self, color: Intrinsics) -> bool:
        """True when registration would be a no-op (same intrinsics and size, identity extrinsic, no distortion)."""
        return (self.intrinsics == color and np.allclose(self.T_color_depth, np.eye(4), atol=1e-12)
                and not any(self.distortion))


def project_plumb_bob(P: np.ndarray, K: np.ndarray, dist: Optional[Sequence[float]] = None) -> np.ndarray:
    """Project camera-frame points with a pinhole + plumb_bob (OpenCV ``k1 k2 p1 p2 k3``) model.

    Args:
        P: (N, 3) points in the optical frame, ``z > 0`` (metres).
        K: (3, 3) intrinsic matrix (pixels). dist: distortion coefficients or None.

    Returns:
        (N, 2) float64 pixel coordinates ``(u, v)``.
    """
    P = np.asarray(P, dtype=np.float64)
    x = P[:, 0] / P[:, 2]
    y = P[:, 1] / P[:, 2]
    if dist is not None and any(dist):
        k = list(dist) + [0.0] * (5 - len(dist))
        k1, k2, p1, p2, k3 = k[:5]
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        x, y = (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)
    return np.stack([K[0, 0] * x + K[0, 2], K[1, 1] * y + K[1, 2]], axis=1)


def register_depth(
    depth: np.ndarray,
    depth_camera: DepthCamera,
    color: Intrinsics,
    color_distortion: Optional[Sequence[float]] = None,
) -> np.ndarray:
    """Register a depth image to the colour camera (see the module docstring).

    Args:
        depth: (Hd, Wd) float depth in metres along the depth camera's z, 0 = invalid; its size must
            match ``depth_camera.intrinsics``.
        depth_camera: depth intrinsics, distortion and ``T_color_depth``.
        color: colour intrinsics (output size).
        color_distortion: plumb_bob coefficients of the colour images (None: undistorted images).

    Returns:
        (color.height, color.width) float32 depth in metres along the colour camera's z, 0 = no sample.

    Raises:
        ValueError: depth is not 2-D or its size differs from the depth intrinsics.
    """
    d = np.asarray(depth, dtype=np.float32)
    di = depth_camera.intrinsics
    if d.ndim != 2 or d.shape != (di.height, di.width):
        raise ValueError(f"depth image is {d.shape[::-1]} but the depth intrinsics are for {di.width}x{di.height}")
    out = np.full(color.height * color.width, np.inf, dtype=np.float32)
    v, u = np.nonzero(np.isfinite(d) & (d > 0))
    if len(u):
        z = d[v, u].astype(np.float64)
        if any(depth_camera.distortion):
            pts = np.stack([u, v], axis=1).astype(np.float64)[:, None, :]
            n = cv2.undistortPoints(pts, di.K, np.asarray(depth_camera.distortion)).reshape(-1, 2)
            xn, yn = n[:, 0], n[:, 1]
        else:
            xn, yn = (u - di.cx) / di.fx, (v - di.cy) / di.fy
        P = np.stack([xn * z, yn * z, z], axis=1)
        T = depth_camera.T_color_depth
        Pc = P @ T[:3, :3].T + T[:3, 3]
        front = Pc[:, 2] > 1e-6
        Pc = Pc[front]
        uv = project_plumb_bob(Pc, color.K, color_distortion)
        zc = Pc[:, 2].astype(np.float32)
        s = int(depth_camera.splat)
        offs = [(dy, dx) for dy in range(-((s - 1) // 2), s // 2 + 1) for dx in range(-((s - 1) // 2), s // 2 + 1)]
        ui = np.floor(uv[:, 0] + 0.5).astype(np.int64)
        vi = np.floor(uv[:, 1] + 0.5).astype(np.int64)
        for dy, dx in offs:
            uu, vv = ui + dx, vi + dy
            ok = (uu >= 0) & (uu < color.width) & (vv >= 0) & (vv < color.height)
            np.minimum.at(out, vv[ok] * color.width + uu[ok], zc[ok])
    out[~np.isfinite(out)] = 0.0
    return out.reshape(color.height, color.width)


def parse_depth_camera(intrinsics: Sequence[float], extrinsic: Optional[Sequence[float]] = None,
                       size: Optional[Tuple[int, int]] = None, splat: int = 1) -> DepthCamera:
    """Build a :class:`DepthCamera` from plain numbers (CLI / YAML settings).

    Args:
        intrinsics: ``(fx, fy, cx, cy)`` or ``(fx, fy, cx, cy, width, height)`` of the depth images.
        extrinsic: ``T_color_depth`` as ``(tx, ty, tz, qx, qy, qz, qw)`` (metres, Hamilton xyzw), 16
            row-major numbers, or None (identity: only the intrinsics differ).
        size: ``(width, height)`` when ``intrinsics`` has 4 numbers.

    Raises:
        ValueError: wrong counts or invalid values.
    """
    vals = [float(v) for v in intrinsics]
    if len(vals) == 6:
        size = (int(vals[4]), int(vals[5]))
    elif len(vals) != 4:
        raise ValueError(f"depth intrinsics must be fx,fy,cx,cy[,width,height], got {len(vals)} numbers")
    if size is None:
        raise ValueError("depth intrinsics need the depth image size (fx,fy,cx,cy,width,height)")
    intr = Intrinsics(*vals[:4], int(size[0]), int(size[1]))
    if extrinsic is None:
        T = np.eye(4)
    else:
        e = [float(v) for v in extrinsic]
        if len(e) == 7:
            T = make_transform(e[:3], e[3:])
        elif len(e) == 16:
            T = np.asarray(e).reshape(4, 4)
        else:
            raise ValueError(f"depth extrinsic must be tx,ty,tz,qx,qy,qz,qw or 16 numbers, got {len(e)}")
    return DepthCamera(intr, T, splat=splat)
