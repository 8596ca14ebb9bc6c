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

A SLAM-like pose error for robustness studies (:func:`perturb_trajectory`): drift that grows with the path travelled
plus per-frame jitter, scaled to a named level of ATE and rotation error (:data:`POSE_ERROR_LEVELS`).
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Optional, Sequence, Tuple, Union

import numpy as np

from gausslite.camera import rotation_angle_deg
from gausslite.ros.transforms import quat_to_rot

__all__ = ["read_tum_trajectory", "write_tum_trajectory", "rot_to_quat", "align_rigid", "ate_rmse", "rpe",
           "rotation_angle_deg", "POSE_ERROR_LEVELS", "JITTER_SHARE", "parse_pose_error_level", "pose_error_stats",
           "perturb_trajectory"]


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


# ------------------------------------------------------------------------------------------ SLAM-like pose error model
#: named pose error levels: name -> (ATE RMSE in metres, rotation RMSE in degrees) of the perturbed trajectory
POSE_ERROR_LEVELS = {"exact": (0.0, 0.0), "1cm_0.5deg": (0.01, 0.5), "3cm_1.5deg": (0.03, 1.5)}
#: share of a level's translation and rotation error given to per-frame jitter (RMS norm); the drift carries the rest
JITTER_SHARE = 0.2


def parse_pose_error_level(level: str) -> Tuple[float, float]:
    """``(ATE m, rotation deg)`` of a level name: ``"exact"`` or ``"<x>cm_<y>deg"`` (e.g. ``"3cm_1.5deg"``).

    Raises:
        ValueError: any other name, or a negative figure.
    """
    if level == "exact":
        return 0.0, 0.0
    m = re.fullmatch(r"(\d+(?:\.\d+)?)cm_(\d+(?:\.\d+)?)deg", str(level))
    if m is None:
        raise ValueError(f"unknown pose error level {level!r}: expected 'exact' or '<x>cm_<y>deg', e.g. '1cm_0.5deg'")
    return float(m.group(1)) / 100.0, float(m.group(2))


def pose_error_stats(est: np.ndarray, ref: np.ndarray) -> dict:
    """Error of an estimated trajectory against the reference.

    Args:
        est, ref: (N, 4, 4) float camera-to-world poses of the same N frames (metres).
    Returns:
        ``{"ate_m"}``: :func:`ate_rmse` (after rigid alignment); ``"rot_rmse_deg"``: RMS over frames of the angle of
        ``R_est R_ref^T`` (no alignment: both trajectories share the first frame's gauge); ``"trans_rmse_m"`` and
        ``"trans_max_m"``: RMS and largest position error without alignment, the error a map built at ``est`` shows
        when it is looked at from ``ref``.
    Raises:
        ValueError: different lengths, or no pose.
    """
    est, ref = np.asarray(est, np.float64), np.asarray(ref, np.float64)
    ate = ate_rmse(est, ref)
    rel = np.einsum("nij,nkj->nik", est[:, :3, :3], ref[:, :3, :3])
    from scipy.spatial.transform import Rotation  # noqa: PLC0415 - SciPy is not in the light fusion install

    ang = Rotation.from_matrix(rel).magnitude()
    d = np.linalg.norm(est[:, :3, 3] - ref[:, :3, 3], axis=1)
    return {"ate_m": ate, "rot_rmse_deg": float(np.degrees(np.sqrt(np.mean(ang ** 2)))),
            "trans_rmse_m": float(np.sqrt(np.mean(d ** 2))), "trans_max_m": float(d.max())}


def _exp_se3(rotvec: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """(M, 4, 4) rigid transforms ``[Rot(rotvec) | trans]`` of (M, 3) rotation vectors (rad) and translations (m)."""
    out = np.repeat(np.eye(4)[None], len(rotvec), axis=0)
    from scipy.spatial.transform import Rotation  # noqa: PLC0415 - SciPy is not in the light fusion install

    out[:, :3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    out[:, :3, 3] = trans
    return out


def _perturbed(ref: np.ndarray, draws: dict, sr: float, st: float, jr: float, jt: float) -> np.ndarray:
    """The model of :func:`perturb_trajectory` for drift rates ``sr`` (rad/sqrt(m)), ``st`` (m/sqrt(m)) and jitter
    ``jr`` (rad), ``jt`` (m) per axis, with the unit normal ``draws``."""
    root = np.sqrt(draws["step_m"])[:, None]
    noise = _exp_se3(sr * root * draws["drift_rot"], st * root * draws["drift_trans"])
    rel = np.linalg.inv(ref[:-1]) @ ref[1:]
    drift = np.empty_like(ref)
    drift[0] = ref[0]
    for k in range(len(rel)):
        drift[k + 1] = drift[k] @ rel[k] @ noise[k]
    out = drift @ _exp_se3(jr * draws["jitter_rot"], jt * draws["jitter_trans"])
    out[0] = ref[0]
    return out


def _calibrate(f, target: float) -> float:
    """The smallest ``x >= 0`` with ``f(x) = target`` (``f`` increasing from ``f(0)``), or 0 if ``f(0) >= target``."""
    if f(0.0) >= target:
        return 0.0
    hi = 1e-3
    while f(hi) < target:
        hi *= 4.0
        if hi > 1e3:
            raise ValueError("pose error level out of reach for this trajectory")
    from scipy.optimize import brentq  # noqa: PLC0415 - SciPy is not in the light fusion install

    return float(brentq(lambda x: f(x) - target, 0.0, hi, xtol=1e-12, rtol=1e-10))


def perturb_trajectory(c2w: np.ndarray, level: Union[str, Tuple[float, float]], seed: int = 0) -> np.ndarray:
    """A SLAM-like estimate of a trajectory: drift that grows with the path travelled, plus per-frame jitter.

    The model (all draws from ``numpy.random.default_rng(seed)``, in this order: drift rotation, drift
    translation, jitter rotation, jitter translation, each (N - 1, 3) standard normal ``a_k, b_k, c_i, d_i``):

    - step ``k`` (frames k -> k+1) travels ``s_k = |t_{k+1} - t_k|`` metres;
    - drift, a random walk per metre travelled, in the new frame's camera axes (odometry error composed into every
      relative motion): ``D_0 = T_0``, ``D_{k+1} = D_k (T_k^-1 T_{k+1}) Exp(sigma_r sqrt(s_k) a_k,
      sigma_t sqrt(s_k) b_k)``, ``Exp(phi, rho) = [Rot(phi) | rho]``, so the drift's variance grows linearly with
      the path (rotation drift also moves the later positions, through the lever of the motion after it);
    - jitter, independent per frame: ``P_i = D_i Exp(j_r c_i, j_t d_i)`` for ``i >= 1``; ``P_0 = T_0`` (the first
      frame fixes the gauge, as in SLAM), with ``j_t = JITTER_SHARE * ATE / sqrt(3)`` and ``j_r = JITTER_SHARE * rot
      / sqrt(3)`` per axis (:data:`JITTER_SHARE` = 0.2 of the level's RMS);
    - calibration: ``sigma_r`` is solved (Brent's method) so that the RMS rotation error of ``P`` against ``T``
      (:func:`pose_error_stats` ``rot_rmse_deg``, no alignment) equals the level's degrees, then ``sigma_t`` so that
      the ATE (:func:`ate_rmse`, after the TUM benchmark's rigid alignment) equals the level's metres. If the rotation
      drift alone already exceeds the ATE, ``sigma_t = 0`` and the realised ATE is larger than the level's (check it
      with :func:`pose_error_stats`). The level is thus the realised error of this draw, not an expectation.

    Without alignment a map built at ``P`` is misplaced by more than the ATE (``trans_rmse_m`` of
    :func:`pose_error_stats`), as a SLAM map is, since the error starts at zero and grows along the path.

    Args:
        c2w: (N, 4, 4) float camera-to-world reference poses (metres, OpenCV camera axes), N >= 2.
        level: a :data:`POSE_ERROR_LEVELS` name or ``"<x>cm_<y>deg"`` (:func:`parse_pose_error_level`), or
            ``(ATE m, rotation deg)``; ``"exact"`` returns a copy.
        seed: the draw's seed.
    Returns:
        (N, 4, 4) float64 perturbed camera-to-world poses.
    Raises:
        ValueError: an unknown level, N < 2, a path shorter than 1 cm (no drift to scale), or a level out of reach.
    """
    ref = np.asarray(c2w, np.float64)
    if ref.ndim != 3 or ref.shape[1:] != (4, 4) or len(ref) < 2:
        raise ValueError(f"need (N, 4, 4) poses with N >= 2, got shape {ref.shape}")
    ate_t, rot_t = parse_pose_error_level(level) if isinstance(level, str) else (float(level[0]), float(level[1]))
    if ate_t == 0.0 and rot_t == 0.0:
        return ref.copy()
    step = np.linalg.norm(np.diff(ref[:, :3, 3], axis=0), axis=1)
    if step.sum() < 0.01:
        raise ValueError(f"the trajectory travels {step.sum():.4f} m: too short for a drift per metre")
    rng = np.random.default_rng(int(seed))
    n = len(ref) - 1
    draws = {"step_m": step, "drift_rot": rng.standard_normal((n, 3)), "drift_trans": rng.standard_normal((n, 3)),
             "jitter_rot": np.vstack([np.zeros((1, 3)), rng.standard_normal((n, 3))]),
             "jitter_trans": np.vstack([np.zeros((1, 3)), rng.standard_normal((n, 3))])}
    jr = JITTER_SHARE * np.deg2rad(rot_t) / np.sqrt(3.0)
    jt = JITTER_SHARE * ate_t / np.sqrt(3.0)
    sr = _calibrate(lambda x: pose_error_stats(_perturbed(ref, draws, x, 0.0, jr, 0.0), ref)["rot_rmse_deg"], rot_t)
    st = _calibrate(lambda x: ate_rmse(_perturbed(ref, draws, sr, x, jr, jt), ref), ate_t)
    return _perturbed(ref, draws, sr, st, jr, jt)
