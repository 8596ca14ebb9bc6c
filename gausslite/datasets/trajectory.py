"""Camera trajectories: the TUM trajectory file, and tracking error as the TUM RGB-D benchmark measures it.

The TUM format (the TUM RGB-D file-format page, Sturm et al., IROS 2012) holds one pose per line,
``timestamp tx ty tz qx qy qz qw``: the camera-to-world pose (c2w) of the optical centre, translation in metres,
Hamilton unit quaternion with the scalar last; ``#`` lines are comments. GaussLite's poses use OpenCV camera axes
(x right, y down, z forward), as TUM's do.

Tracking error (the benchmark's ``evaluate_ate.py`` and ``evaluate_rpe.py``):

- ATE RMSE: the estimated positions are aligned to the reference ones by the rigid motion (rotation and
  translation, no scale) that minimises the squared error (Horn 1987 / Umeyama 1991 closed form, as
  ``evaluate_ate.py``'s ``align``), then the RMSE of the position differences.
- RPE (translational): for every pair of poses ``delta`` frames (or ``delta`` seconds) apart, the relative motion
  of the estimate against the reference's, ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)``; the RMSE of ``|trans(E)|``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional, Sequence, Tuple, Union

import numpy as np

from gausslite.ros.transforms import quat_to_rot

__all__ = ["read_tum_trajectory", "write_tum_trajectory", "rot_to_quat", "align_rigid", "ate_rmse", "rpe",
           "rotation_angle_deg"]


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(qx, qy, qz, qw)`` (Hamilton, scalar last, ``qw >= 0``) of a (3, 3) rotation matrix
    (Shepperd's method, numerically stable for every angle).

    Args:
        R: (3, 3) float rotation matrix.
    Returns:
        (4,) float64 unit quaternion, xyzw.
    """
    R = np.asarray(R, dtype=np.float64)
    t = np.trace(R)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.asarray(q, dtype=np.float64)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def write_tum_trajectory(path: Union[str, Path], timestamps: Sequence[float], poses: np.ndarray,
                         comment: Optional[str] = None) -> Path:
    """Write poses as a TUM trajectory file (``timestamp tx ty tz qx qy qz qw`` per line).

    Args:
        path: the file to write (its folder is created). The file is written whole or not at all (a temporary
            file renamed into place).
        timestamps: (N,) seconds.
        poses: (N, 4, 4) float camera-to-world poses (metres, OpenCV camera axes).
        comment: an optional first line, written after ``# ``.
    Returns:
        ``path``.
    Raises:
        ValueError: lengths differ, or a pose is not finite.
    """
    path = Path(path)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(poses) != len(timestamps):
        raise ValueError(f"{path}: {len(timestamps)} timestamps for {len(poses)} poses")
    if not np.all(np.isfinite(poses)):
        raise ValueError(f"{path}: a pose has NaN or infinite entries")
    lines = [f"# {comment}"] if comment else []
    lines.append("# timestamp tx ty tz qx qy qz qw")
    for t, T in zip(timestamps, poses):
        q = rot_to_quat(T[:3, :3])
        lines.append(f"{float(t):.6f} " + " ".join(f"{v:.7f}" for v in (*T[:3, 3], *q)))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    tmp.replace(path)
    return path


def read_tum_trajectory(path: Union[str, Path]) -> Tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file.

    Args:
        path: the file (``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments).
    Returns:
        ``(timestamps (N,) float64 seconds, poses (N, 4, 4) float64 camera-to-world)``, in file order.
    Raises:
        FileNotFoundError: no such file. ValueError: a malformed line (the message names the file and the line),
            or no pose.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"trajectory file not found: {path}")
    ts, poses = [], []
    for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            raise ValueError(f"{path}:{lineno}: non-numeric value in 'timestamp tx ty tz qx qy qz qw'") from None
        if len(vals) != 8 or not all(math.isfinite(v) for v in vals):
            raise ValueError(f"{path}:{lineno}: expected 8 finite numbers 'timestamp tx ty tz qx qy qz qw', "
                             f"got {len(vals)}")
        q = np.asarray(vals[4:8])
        if np.linalg.norm(q) < 1e-6:
            raise ValueError(f"{path}:{lineno}: zero quaternion")
        T = np.eye(4)
        T[:3, :3] = quat_to_rot(q / np.linalg.norm(q))
        T[:3, 3] = vals[1:4]
        ts.append(vals[0])
        poses.append(T)
    if not poses:
        raise ValueError(f"{path}: no poses")
    return np.asarray(ts, dtype=np.float64), np.stack(poses)


def align_rigid(src: np.ndarray, dst: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """The rotation ``R`` and translation ``t`` minimising ``sum |dst_i - (R src_i + t)|^2`` (Umeyama 1991 without
    scale; Horn's closed form, as the TUM benchmark's ``evaluate_ate.py`` aligns).

    Args:
        src, dst: (N, 3) float positions (metres), N >= 3 (fewer give the best of a degenerate set).
    Returns:
        ``(R (3, 3), t (3,))`` float64.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    S = (dst - mu_d).T @ (src - mu_s) / max(len(src), 1)
    U, _, Vt = np.linalg.svd(S)
    W = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        W[2, 2] = -1.0
    R = U @ W @ Vt
    return R, mu_d - R @ mu_s


def ate_rmse(est: np.ndarray, ref: np.ndarray) -> float:
    """Absolute trajectory error: RMSE (metres) of the positions after rigid alignment (:func:`align_rigid`).

    Args:
        est, ref: (N, 4, 4) camera-to-world poses of the same N frames (estimate, reference).
    Returns:
        the RMSE in metres.
    Raises:
        ValueError: different lengths, or no pose.
    """
    est, ref = np.asarray(est, np.float64), np.asarray(ref, np.float64)
    if len(est) != len(ref) or len(est) == 0:
        raise ValueError(f"ATE needs the same number of estimated and reference poses, got {len(est)} and {len(ref)}")
    R, t = align_rigid(est[:, :3, 3], ref[:, :3, 3])
    err = est[:, :3, 3] @ R.T + t - ref[:, :3, 3]
    return float(np.sqrt((err ** 2).sum(1).mean()))


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle (degrees) of a (3, 3) rotation matrix."""
    return float(np.degrees(np.arccos(np.clip((np.trace(np.asarray(R)[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))


def rpe(est: np.ndarray, ref: np.ndarray, timestamps: Optional[np.ndarray] = None, delta: float = 1,
        per_second: bool = False) -> dict:
    """Relative pose error over pairs ``delta`` frames apart, or ``delta`` seconds apart when ``per_second``
    (each frame paired with the first frame at least ``delta`` s later, as ``evaluate_rpe.py --delta_unit s``).

    Args:
        est, ref: (N, 4, 4) camera-to-world poses (estimate, reference).
        timestamps: (N,) seconds; needed when ``per_second``.
        delta: the pair distance, frames (int) or seconds.
        per_second: see above.
    Returns:
        ``{"trans_rmse_m", "rot_rmse_deg", "pairs"}``; the RMSEs are None when no pair fits.
    Raises:
        ValueError: different lengths, or ``per_second`` without timestamps.
    """
    est, ref = np.asarray(est, np.float64), np.asarray(ref, np.float64)
    if len(est) != len(ref):
        raise ValueError(f"RPE needs the same number of estimated and reference poses, got {len(est)} and {len(ref)}")
    if per_second:
        if timestamps is None:
            raise ValueError("RPE per second needs the frames' timestamps")
        ts = np.asarray(timestamps, np.float64)
        pairs = [(i, int(j)) for i in range(len(ts)) for j in [np.searchsorted(ts, ts[i] + delta - 1e-9)]
                 if j < len(ts)]
    else:
        d = int(delta)
        pairs = [(i, i + d) for i in range(len(est) - d)]
    tr, rot = [], []
    for i, j in pairs:
        E = np.linalg.inv(np.linalg.inv(ref[i]) @ ref[j]) @ (np.linalg.inv(est[i]) @ est[j])
        tr.append(np.linalg.norm(E[:3, 3]))
        rot.append(rotation_angle_deg(E))
    if not pairs:
        return {"trans_rmse_m": None, "rot_rmse_deg": None, "pairs": 0}
    return {"trans_rmse_m": float(np.sqrt(np.mean(np.square(tr)))),
            "rot_rmse_deg": float(np.sqrt(np.mean(np.square(rot)))), "pairs": len(pairs)}
