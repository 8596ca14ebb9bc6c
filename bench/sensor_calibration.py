"""Sensor calibration: the statistics of a real Kinect v1 (TUM RGB-D fr1/rpy) that the synthetic sensor model is
calibrated against, measured the same way on TUM and on the synthetic walk rendered with each sensor level
(``make_scene(sensor_noise=...)``, :mod:`gausslite.synthetic.sensor`; docs/mapper.md, "The synthetic sensor
calibrated on TUM fr1").

Not to be confused with ``bench.calibration`` (which intrinsics, distortion and depth scale each dataset layout
reads). Frames are read as ``bench.odometry`` reads them: TUM fr1/rpy at 320×240 (``--downscale 2``, undistorted,
ground-truth poses interpolated at the colour timestamps, depth not re-aligned in time), the synthetic walk (robot A,
``--walk-frames`` frames at 30 fps, 320×240) as ``make_scene`` writes it. Every statistic is a function of the frames
alone (:data:`STATS`), so TUM and the walk are measured by the same code:

- ``quantisation``: the depth step (m) between neighbouring occupied depth values in bins of z (values seen at
  least 20 times), and ``c`` of ``step = c z²`` (the median of step / z² over the bins): the Kinect's disparity
  lattice (Khoshelham and Elberink, Sensors 2012);
- ``noise``: the residual standard deviation (mm) of a least-squares plane fitted to every fully valid 3×3 and 5×5
  window of depth, the median per bin of z (planar surfaces dominate the median; a 5×5 residual above the 3×3 one
  means the noise is correlated over pixels);
- ``holes``: the share of pixels without depth; ``border``: pixels without depth in at least 95 % of the frames (the
  bands the registered depth does not cover, also given per side as the share of rows or columns); ``interior``:
  the rest; ``by_grey``: the share of interior pixels without depth by the colour's grey level (dark surfaces);
- ``edges``: along rows and columns, each pair of consecutive valid pixels whose depths differ by more than
  ``max(5 cm, 4 % z)`` with at most 6 pixels without depth between them: the share with a run of holes between them
  and the runs' mean length (px); and each pixel between two flat two-pixel plateaus across such a jump: the share
  that is near, far, flying (more than ``max(2 cm, 2 % z)`` from both sides) or a hole;
- ``misregistration``: the offset (px; + = right, down) of the colour gradient peak from depth edges (bilinear in 1/8
  px steps, the peak of the mean score refined by a parabola), on the frames whose image moves slower than 100 px/s
  at its centre (from the reference poses), and the Theil–Sen slope of the per-frame offsets against the image
  velocity: minus the delay (ms) of the depth image after the colour image;
- ``time_offset`` (TUM only): the depth timestamp minus the colour timestamp of each frame pair (ms);
- ``exposure``: the log gain between frames ``i`` and ``i + g``, each pixel of frame ``i``'s depth moved into frame
  ``i + g`` with the reference poses (kept when the depth there agrees within 5 %), the median log ratio per channel
  over pixels in 15..240; the robust (1.4826 MAD) spread of the mean over channels and of the channels around it,
  for gaps of 1/15 to 16/15 s, and a fit of ``sqrt(2) s sqrt(1 - exp(-tau² / (4 T²)))`` (the spread of a log gain of
  standard deviation ``s``, Gaussian white noise smoothed over ``T`` seconds, as
  :func:`gausslite.synthetic.sensor.exposure_track` draws it);
- ``blur``: the exposure time (ms) that explains each frame's ratio of image gradients along and across its motion
  (from the reference poses and depth) by line blur of length speed × exposure, the ratio's curve against the blur
  length calibrated on the sequence's own sharpest tenth of frames (in 2.5 ms steps; it needs images that move: on
  the 525-frame walk the blur is about a pixel, so it is measured on a fast walk, the same 7 m in
  ``--fast-walk-frames`` frames, whose images move about as fast as TUM's);
- ``colour_noise``: the noise standard deviation (grey levels) by Immerkær's estimator (CVIU 1996) on the flattest
  fifth of each frame, the median over frames;
- ``motion``: the frame spacing and the median rotation and translation per frame and per second (reference
  poses);
- ``rolling_shutter`` (read from ``bench/results/rolling_shutter.json``, ``python -m bench.rolling_shutter``): the
  colour readout time that best warps TUM frames into each other.

The **scan walk** (``--scan-walk``, ``make_scene(trajectory="scan_walk")``) is the same walk at the ``tum`` level,
looking around as it goes: roll, pitch and yaw sweeps turn it at TUM fr1/rpy's median rate (about 52°/s, against the
walk's 17°/s), so that the effects that grow with the motion (the depth's delay, the rolling shutters, the blur) act
on it as hard as on TUM.

And what the sensor does to tracking: ``bench.odometry``'s tracking (default ``OdometryConfig``) of TUM from each
start frame of ``--starts`` and of the walk at each level for each seed of ``--seeds`` (the seed changes the scene,
the path's jitter and the sensor's noise), the ATE's mean and standard deviation over the runs.

Prints the comparison table and the model's parameters against the values fitted from TUM; writes
``bench/results/sensor_calibration.{json,md}``.

Usage::

    python -m bench.sensor_calibration [--levels tum,realistic] [--walk-frames 525] [--fast-walk-frames 90]
                                       [--scan-walk all|motion|] [--seeds 0,1,2] [--starts 0,1,2] [--no-odometry] [--work DIR]
                                       [--out bench/results/sensor_calibration.json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Callable, Dict, List, Optional

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import theilslopes
from tqdm import tqdm

from bench._results import DATASETS, write_results
from bench.odometry import track, walk_dir
from gausslite.datasets import load_dataset
from gausslite.datasets.tum import associate_nearest, read_file_list
from gausslite.synthetic import make_scene, sensor_model

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"
TUM = DATASETS / "TUM_rgbd_dataset_freiburg1_rpy"
#: depth bins (m) of the quantisation and noise statistics
Z_BINS = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0)
#: the gaps of the exposure statistic, seconds (TUM's kept frames are 1/15 s apart)
GAPS_S = (1 / 15, 2 / 15, 4 / 15, 8 / 15, 16 / 15)
#: grey-level bins of the holes-by-grey statistic
GREY_BINS = (0, 20, 40, 60, 90, 130, 256)
LEVELS = ("tum", "realistic", "none")


def jump(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Whether depths ``a`` and ``b`` (m) lie on two sides of a depth edge: apart by more than ``max(5 cm, 4 % z)``
    (the sensor model's edge threshold)."""
    return np.abs(b - a) > np.maximum(0.05, 0.04 * np.maximum(a, b))


def quantisation(frames: list) -> dict:
    """The depth step between neighbouring occupied depth values per bin of z, and ``c`` of ``step = c z²``."""
    v = np.concatenate([f.depth[f.depth > 0].astype(np.float64) for f in frames])
    u, n = np.unique(np.round(v * 1e5) / 1e5, return_counts=True)  # float32 depths: 10 µm bins
    u = u[n >= 20]
    steps, ratios = {}, []
    for lo, hi in zip(Z_BINS[:-1], Z_BINS[1:]):
        g = np.diff(u[(u >= lo) & (u < hi)])
        if len(g) >= 3:
            steps[f"{lo}-{hi}"] = float(np.median(g))
            ratios.append(float(np.median(g)) / ((lo + hi) / 2) ** 2)
    return {"step_m": steps, "c_per_m": float(np.median(ratios)) if ratios else None}


def plane_residual(depth: np.ndarray, k: int) -> np.ndarray:
    """(H, W) residual standard deviation (m) of the least-squares plane ``z = a + b du + c dv`` over the k×k window
    around each pixel; NaN where the window is not fully valid."""
    r = k // 2
    U, V = np.meshgrid(np.arange(-r, r + 1.0), np.arange(-r, r + 1.0))
    su = float((U ** 2).sum())
    z = depth.astype(np.float64)

    def filt(x: np.ndarray, ker: np.ndarray) -> np.ndarray:
        return cv2.filter2D(x, -1, ker, borderType=cv2.BORDER_CONSTANT)

    box = np.full((k, k), 1.0 / (k * k))
    full = filt((z > 0).astype(np.float64), box) > 1 - 1e-9
    m1, m2 = filt(z, box), filt(z * z, box)
    bu, bv = filt(z, U / su), filt(z, V / su)
    var = (m2 - m1 ** 2 - (bu ** 2 + bv ** 2) * su / (k * k)) * (k * k) / (k * k - 3)
    return np.where(full, np.sqrt(np.maximum(var, 0.0)), np.nan)


def noise(frames: list) -> dict:
    """The median plane-fit residual (mm) per bin of z, for 3×3 and 5×5 windows."""
    out = {}
    for k in (3, 5):
        acc: Dict[str, list] = {f"{lo}-{hi}": [] for lo, hi in zip(Z_BINS[:-1], Z_BINS[1:])}
        for f in frames:
            res = plane_residual(f.depth, k)
            for lo, hi in zip(Z_BINS[:-1], Z_BINS[1:]):
                m = np.isfinite(res) & (f.depth >= lo) & (f.depth < hi)
                acc[f"{lo}-{hi}"].append(res[m])
        out[f"{k}x{k}_mm"] = {b: (1e3 * float(np.median(np.concatenate(v))) if sum(map(len, v)) >= 1000 else None)
                              for b, v in acc.items()}
    return out


def holes(frames: list) -> dict:
    """Shares of pixels without depth: all, the border bands (invalid in >= 95 % of frames; per side, the share of
    rows or columns that are invalid in more than half the frames), the interior and the interior by grey level."""
    inv = np.stack([f.depth <= 0 for f in frames])
    freq = inv.mean(axis=0)
    border = freq >= 0.95
    rows, cols = freq.mean(axis=1) > 0.5, freq.mean(axis=0) > 0.5

    def run(m: np.ndarray) -> int:
        return int(np.argmin(m)) if not m.all() else len(m)

    H, W = freq.shape
    grey = np.concatenate([cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY)[~border] for f in frames])
    hole = inv[:, ~border].reshape(-1)
    by_grey = {}
    for lo, hi in zip(GREY_BINS[:-1], GREY_BINS[1:]):
        m = (grey >= lo) & (grey < hi)
        by_grey[f"{lo}-{hi}"] = {"holes": float(hole[m].mean()) if m.any() else None, "share": float(m.mean())}
    return {"all": float(inv.mean()), "border": float(border.mean()), "interior": float(inv[:, ~border].mean()),
            "border_top": run(rows) / H, "border_bottom": run(rows[::-1]) / H, "border_left": run(cols) / W,
            "border_right": run(cols[::-1]) / W, "by_grey": by_grey}


def edge_runs(frames: list, kmax: int = 6) -> np.ndarray:
    """Counts of depth jumps between consecutive valid pixels along rows and columns by the number of invalid pixels
    between them (0..kmax)."""
    hist = np.zeros(kmax + 1, int)
    for f in frames:
        z = f.depth.astype(np.float64)
        for zz in (z, z.T):
            v, u = np.nonzero(zz > 0)  # row-major: consecutive entries of a row are consecutive valid pixels
            same = v[1:] == v[:-1]
            gap = (u[1:] - u[:-1] - 1)[same]
            a, b = zz[v[:-1], u[:-1]][same], zz[v[1:], u[1:]][same]
            j = jump(a, b) & (gap <= kmax)
            hist += np.bincount(gap[j], minlength=kmax + 1)[: kmax + 1]
    return hist


def edge_pixels(frames: list) -> dict:
    """The pixel between two flat two-pixel plateaus across a depth jump (rows and columns): shares near, far,
    flying and hole."""
    cnt = {"near": 0, "far": 0, "flying": 0, "hole": 0}
    for f in frames:
        z = f.depth.astype(np.float64)
        for zz in (z, z.T):
            a2, a1, c, b1, b2 = zz[:, :-4], zz[:, 1:-3], zz[:, 2:-2], zz[:, 3:-1], zz[:, 4:]
            tol = np.maximum(0.01, 0.01 * np.minimum(a1, b1))
            e = ((a2 > 0) & (a1 > 0) & (b1 > 0) & (b2 > 0) & (np.abs(a2 - a1) < tol) & (np.abs(b2 - b1) < tol)
                 & jump(a1, b1))
            near, far = np.minimum(a1, b1), np.maximum(a1, b1)
            tolc = np.maximum(0.02, 0.02 * far)
            is_near = e & (c > 0) & (np.abs(c - near) <= tolc)
            is_far = e & (c > 0) & (np.abs(c - far) <= tolc) & ~is_near
            cnt["hole"] += int((e & (c <= 0)).sum())
            cnt["near"] += int(is_near.sum())
            cnt["far"] += int(is_far.sum())
            cnt["flying"] += int((e & (c > 0) & ~is_near & ~is_far).sum())
    n = max(sum(cnt.values()), 1)
    return {k: v / n for k, v in cnt.items()}


def edges(frames: list) -> dict:
    """:func:`edge_runs` and :func:`edge_pixels` as shares."""
    h = edge_runs(frames)
    with_holes = h[1:].sum()
    return {"jumps": int(h.sum()), "with_holes": float(with_holes / max(h.sum(), 1)),
            "run_mean_px": float((np.arange(1, len(h)) * h[1:]).sum() / max(with_holes, 1)),
            "runs": [int(x) for x in h], "pixel_between": edge_pixels(frames)}


def velocity(frames: list, i: int) -> tuple:
    """``(omega (3,) rad/s, v (3,) m/s)`` of frame ``i`` in its own camera frame: the central difference of its
    neighbours' reference poses."""
    a, b = max(i - 1, 0), min(i + 1, len(frames) - 1)
    rel = np.linalg.inv(frames[a].c2w) @ frames[b].c2w
    dt = max(frames[b].timestamp - frames[a].timestamp, 1e-9)
    return Rotation.from_matrix(rel[:3, :3]).as_rotvec() / dt, rel[:3, 3] / dt


def edge_score(frame, axis: int, shifts: np.ndarray) -> Optional[np.ndarray]:
    """Mean colour gradient at each ``shift`` (px) from the depth jumps between horizontally (``axis`` 1) or
    vertically (0) adjacent valid pixels; None with fewer than 20 jumps."""
    z = frame.depth.astype(np.float64)
    g = cv2.GaussianBlur(cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY).astype(np.float32), (3, 3), 0.7)
    if axis == 0:
        z, g = z.T, g.T
    a, b = z[:, :-1], z[:, 1:]
    vv, uu = np.nonzero((a > 0) & (b > 0) & jump(a, b))
    if len(vv) < 20:
        return None
    G = np.abs(np.diff(g, axis=1))  # between pixels u and u + 1, as the jump
    W = G.shape[1]
    out = []
    for s in shifts:
        x = uu + s
        x0 = np.floor(x).astype(int)
        w = x - x0
        m = (x0 >= 0) & (x0 + 1 < W)
        out.append(float(((1 - w[m]) * G[vv[m], x0[m]] + w[m] * G[vv[m], x0[m] + 1]).mean()))
    return np.array(out)


def peak(shifts: np.ndarray, score: np.ndarray) -> float:
    """The shift of the highest score, refined by a parabola through it and its neighbours."""
    i = int(np.argmax(score))
    if 0 < i < len(score) - 1:
        den = score[i - 1] - 2 * score[i] + score[i + 1]
        if den < 0:
            return float(shifts[i] + 0.5 * (score[i - 1] - score[i + 1]) / den * (shifts[1] - shifts[0]))
    return float(shifts[i])


def misregistration(frames: list, slow_px_s: float = 100.0) -> dict:
    """Offset (px) of colour edges from depth edges on slow frames, and the depth's delay (ms) from the per-frame
    offsets' slope against the image velocity at the centre."""
    shifts = np.arange(-5.0, 5.0 + 1e-9, 0.125)
    out = {}
    for axis, name in ((1, "x"), (0, "y")):
        scores, vel = [], []
        for i, f in enumerate(frames):
            s = edge_score(f, axis, shifts)
            if s is None:
                continue
            w, _ = velocity(frames, i)
            scores.append(s)
            vel.append((f.intrinsics.fx * w[1], -f.intrinsics.fy * w[0]))
        if not scores:
            out[name] = {"offset_px": None, "delay_ms": None, "frames": 0}
            continue
        vel = np.array(vel)
        slow = np.hypot(vel[:, 0], vel[:, 1]) < slow_px_s
        offset = peak(shifts, np.mean(np.array(scores)[slow], axis=0)) if slow.sum() >= 5 else None
        per = np.array([peak(shifts, s) for s in scores])
        v = vel[:, 1 - axis]
        keep = np.abs(per) < shifts[-1] - 0.1
        delay = -1e3 * float(theilslopes(per[keep], v[keep])[0]) if keep.sum() >= 10 and np.ptp(v[keep]) > 0 else None
        out[name] = {"offset_px": offset, "delay_ms": delay, "frames": len(scores), "slow_frames": int(slow.sum())}
    return out


def time_offset(path: Path) -> dict:
    """TUM: depth minus colour timestamp (ms) of each kept colour frame and its nearest depth frame."""
    rgb_ts, _ = read_file_list(path / "rgb.txt")
    depth_ts, _ = read_file_list(path / "depth.txt")
    order = np.sort(depth_ts)
    idx, _ = associate_nearest(rgb_ts, order)
    dt = 1e3 * (order[idx] - rgb_ts)
    return {"mean_ms": float(dt.mean()), "std_ms": float(dt.std()), "median_ms": float(np.median(dt)),
            "pairs": int(len(dt))}


def log_gain(a, b) -> Optional[np.ndarray]:
    """(3,) median log ratio of frame ``b``'s colour to frame ``a``'s over ``a``'s depth pixels moved into ``b``
    with the reference poses (every second pixel; kept where ``b``'s depth agrees within 5 % and both colours lie in
    15..240); None with fewer than 500 such pixels."""
    K = a.intrinsics
    H, W = a.depth.shape
    vv, uu = np.mgrid[0:H:2, 0:W:2]
    z = a.depth[vv, uu].astype(np.float64)
    m = z > 0
    X = np.stack([(uu - K.cx) / K.fx * z, (vv - K.cy) / K.fy * z, z], axis=-1)[m]
    T = np.linalg.inv(b.c2w) @ a.c2w
    Y = X @ T[:3, :3].T + T[:3, 3]
    zc = np.maximum(Y[:, 2], 1e-6)
    u2, v2 = K.fx * Y[:, 0] / zc + K.cx, K.fy * Y[:, 1] / zc + K.cy
    ok = (Y[:, 2] > 0.1) & (u2 >= 0) & (u2 <= W - 1) & (v2 >= 0) & (v2 <= H - 1)
    iu, iv = np.rint(u2[ok]).astype(int), np.rint(v2[ok]).astype(int)
    zb = b.depth[iv, iu]
    agree = (zb > 0) & (np.abs(zb - Y[ok, 2]) < 0.05 * Y[ok, 2])
    ca = a.rgb[vv[m][ok][agree], uu[m][ok][agree]].astype(np.float64)
    cb = b.rgb[iv[agree], iu[agree]].astype(np.float64)
    good = np.all((ca > 15) & (ca < 240) & (cb > 15) & (cb < 240), axis=1)
    if good.sum() < 500:
        return None
    return np.median(np.log(cb[good] / ca[good]), axis=0)


def robust_std(x: np.ndarray) -> float:
    """1.4826 × the median absolute deviation: the standard deviation of a Gaussian, robust to outliers."""
    x = np.asarray(x, np.float64)
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if len(x) else float("nan")


def structure(tau: np.ndarray, s: float, T: float) -> np.ndarray:
    """The spread of ``g(t + tau) - g(t)`` for a log gain ``g`` of standard deviation ``s`` that is Gaussian white
    noise smoothed by a Gaussian of ``T`` seconds (autocorrelation ``exp(-tau² / (4 T²))``)."""
    return math.sqrt(2.0) * s * np.sqrt(1.0 - np.exp(-np.asarray(tau) ** 2 / (4.0 * T ** 2)))


def exposure(frames: list) -> dict:
    """The spread of the log gain (mean over channels) and of the channels around it between frames ``tau``
    apart (:data:`GAPS_S`), and the ``(s, T)`` of :func:`structure` fitted to each (white balance: ``s`` of each
    channel's own term, whose deviation from the channels' mean has ``sqrt(2/3)`` of its spread)."""
    dt = float(np.median(np.diff([f.timestamp for f in frames])))
    spread, wb, taus = [], [], []
    for tau in GAPS_S:
        g = max(1, int(round(tau / dt)))
        if g >= len(frames):
            continue
        lg = [log_gain(frames[i], frames[i + g]) for i in range(0, len(frames) - g, max(1, g // 4))]
        lg = np.array([x for x in lg if x is not None])
        if len(lg) < 10:
            continue
        taus.append(g * dt)
        spread.append(robust_std(lg.mean(axis=1)))
        wb.append(robust_std((lg - lg.mean(axis=1, keepdims=True)).ravel()))
    taus, spread, wb = map(np.array, (taus, spread, wb))
    grid_s, grid_T = np.linspace(0.0, 0.4, 81), np.linspace(0.05, 3.0, 119)
    err = [[float(np.sum((structure(taus, s, T) - spread) ** 2)) for T in grid_T] for s in grid_s]
    i, j = np.unravel_index(int(np.argmin(err)), (len(grid_s), len(grid_T)))
    T = float(grid_T[j])
    err_wb = [float(np.sum((math.sqrt(2 / 3) * structure(taus, s, T) - wb) ** 2)) for s in grid_s]
    return {"gaps_s": taus.tolist(), "log_gain_spread": spread.tolist(), "white_balance_spread": wb.tolist(),
            "gain_log_std": float(grid_s[i]), "smooth_s": T, "white_balance_std": float(grid_s[int(np.argmin(err_wb))])}


def flow_sample(f, w: np.ndarray, v: np.ndarray, step: int = 4) -> tuple:
    """Image velocity (px/s) of a static scene at a grid over the central half of frame ``f`` moving with twist
    ``(w, v)`` (camera frame): ``(u, v, du, dv)`` grids."""
    K = f.intrinsics
    H, W = f.depth.shape
    vv, uu = np.mgrid[H // 4:3 * H // 4:step, W // 4:3 * W // 4:step]
    ok = f.depth > 0
    zm = float(np.median(f.depth[ok])) if ok.any() else 2.0
    z = np.where(f.depth[vv, uu] > 0, f.depth[vv, uu], zm).astype(np.float64)
    X = np.stack([(uu - K.cx) / K.fx * z, (vv - K.cy) / K.fy * z, z], axis=-1)
    Xd = -np.cross(w, X) - v
    du = K.fx * (Xd[..., 0] * z - X[..., 0] * Xd[..., 2]) / z ** 2
    dv = K.fy * (Xd[..., 1] * z - X[..., 1] * Xd[..., 2]) / z ** 2
    return uu, vv, du, dv


def anisotropy(grey: np.ndarray, uu: np.ndarray, vv: np.ndarray, du: np.ndarray, dv: np.ndarray,
               step: int = 4) -> float:
    """Mean |gradient| along the motion over mean |gradient| across it, over the grid's cells (each cell takes its
    sample's direction)."""
    g = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), 0.7)
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    n = np.hypot(du, dv) + 1e-9
    cx = np.kron(du / n, np.ones((step, step)))
    cy = np.kron(dv / n, np.ones((step, step)))
    sub = (slice(vv[0, 0], vv[0, 0] + cx.shape[0]), slice(uu[0, 0], uu[0, 0] + cx.shape[1]))
    along = np.abs(gx[sub] * cx + gy[sub] * cy)
    across = np.abs(-gx[sub] * cy + gy[sub] * cx)
    return float(along.mean() / max(float(across.mean()), 1e-9))


def line_blur(img: np.ndarray, length: float, theta: float) -> np.ndarray:
    """``img`` blurred by a line of ``length`` px at angle ``theta`` (rad; bilinear kernel)."""
    if length < 0.5:
        return img.astype(np.float32)
    k = int(math.ceil(length)) + 3
    k += 1 - k % 2
    ker = np.zeros((k, k), np.float32)
    for s in np.linspace(-length / 2, length / 2, max(int(length * 4), 2)):
        x, y = k // 2 + s * math.cos(theta), k // 2 + s * math.sin(theta)
        x0, y0 = int(math.floor(x)), int(math.floor(y))
        ax, ay = x - x0, y - y0
        for dx, dy, wgt in ((0, 0, (1 - ax) * (1 - ay)), (1, 0, ax * (1 - ay)), (0, 1, (1 - ax) * ay), (1, 1, ax * ay)):
            ker[y0 + dy, x0 + dx] += wgt
    return cv2.filter2D(img.astype(np.float32), -1, ker / ker.sum(), borderType=cv2.BORDER_REFLECT)


def blur(frames: list, seed: int = 0) -> dict:
    """The exposure time (s) that best explains each frame's gradient anisotropy by line blur of speed × exposure,
    the anisotropy's curve against the blur length taken from the sharpest tenth of the frames blurred in random
    directions; with the frames' median image speed (px/s)."""
    rng = np.random.default_rng(seed)
    speeds, ratios, greys = [], [], []
    for i, f in enumerate(frames):
        w, v = velocity(frames, i)
        uu, vv, du, dv = flow_sample(f, w, v)
        grey = cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY)
        speeds.append(float(np.median(np.hypot(du, dv))))
        ratios.append(anisotropy(grey, uu, vv, du, dv))
        greys.append(grey)
    speeds, ratios = np.array(speeds), np.array(ratios)
    lengths = np.arange(0.0, 16.01, 0.5)
    sharp = np.argsort(speeds)[: max(3, len(frames) // 10)]
    H, W = greys[0].shape
    vv, uu = np.mgrid[H // 4:3 * H // 4:4, W // 4:3 * W // 4:4]
    curve = []
    for L in lengths:
        vals = []
        for j in sharp:
            for th in rng.uniform(0.0, np.pi, 4):
                c, s = np.full(uu.shape, math.cos(th)), np.full(uu.shape, math.sin(th))
                vals.append(anisotropy(line_blur(greys[j], L, th), uu, vv, c, s))
        curve.append(float(np.mean(vals)))
    taus = np.arange(0.0, 0.0501, 0.0025)
    err = [float(np.mean((ratios - np.interp(speeds * t, lengths, curve)) ** 2)) for t in taus]
    return {"exposure_s": float(taus[int(np.argmin(err))]), "median_speed_px_s": float(np.median(speeds)),
            "median_anisotropy": float(np.median(ratios)), "curve": dict(zip(lengths[::4].tolist(), curve[::4]))}


def colour_noise(frames: list) -> dict:
    """Immerkær's noise estimate (grey levels) on the flattest fifth of each frame's pixels with colour (black
    undistortion borders left out), the median over frames."""
    N = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    out = []
    for f in frames:
        g = cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
        mag = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
        lit = cv2.erode((g > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        if lit.sum() < 1000:
            continue
        flat = lit & (mag <= np.percentile(mag[lit], 20))
        out.append(math.sqrt(math.pi / 2) / 6 * float(np.abs(cv2.filter2D(g, -1, N))[flat].mean()))
    return {"sigma_grey": float(np.median(out)) if out else None}


def motion(frames: list) -> dict:
    """The camera's motion between consecutive frames from the reference poses: the frame spacing (s), the median
    rotation (degrees) and translation (m) per frame and per second."""
    ts = np.array([f.timestamp for f in frames])
    rel = [np.linalg.inv(a.c2w) @ b.c2w for a, b in zip(frames[:-1], frames[1:])]
    rot = np.degrees([Rotation.from_matrix(r[:3, :3]).magnitude() for r in rel])
    tr = np.array([np.linalg.norm(r[:3, 3]) for r in rel])
    dt = np.diff(ts)
    return {"frame_spacing_s": float(np.median(dt)), "deg_per_frame": float(np.median(rot)),
            "deg_per_s": float(np.median(rot / dt)), "m_per_frame": float(np.median(tr)),
            "m_per_s": float(np.median(tr / dt))}


def odometry(runs: List[list]) -> dict:
    """``bench.odometry``'s tracking with the default ``OdometryConfig`` (:func:`bench.odometry.track`) of each
    frame list in ``runs``: per run the ATE of the corrected and of the online poses (m), loops accepted and false,
    frames tracked; their mean and sample standard deviation over the runs."""
    per = []
    for frames in tqdm(runs, desc="odometry runs", unit="run", leave=False):
        r = track(frames, {})
        per.append({"ate_rmse_m": r["ate_rmse_m"], "ate_online_m": r["ate_online_m"],
                    "loops": r["loops"]["accepted"], "false_loops": r["loops"]["false"],
                    "tracked_fraction": r["tracked_fraction"]})
    ate = np.array([p["ate_rmse_m"] for p in per])
    online = np.array([p["ate_online_m"] for p in per])
    sd = (lambda x: float(x.std(ddof=1)) if len(x) > 1 else None)
    return {"runs": per, "ate_rmse_m": float(ate.mean()), "ate_std_m": sd(ate), "ate_online_m": float(online.mean()),
            "ate_online_std_m": sd(online), "loops": float(np.mean([p["loops"] for p in per])),
            "false_loops": int(sum(p["false_loops"] for p in per))}


#: the statistics measured on every sequence: name -> function of the frames
STATS: Dict[str, Callable[[list], dict]] = {
    "quantisation": quantisation, "noise": noise, "holes": holes, "edges": edges,
    "misregistration": misregistration, "exposure": exposure, "blur": blur, "colour_noise": colour_noise,
    "motion": motion}


def tum_frames(path: Path) -> list:
    """TUM fr1/rpy as ``bench.odometry`` reads it (320×240, undistorted, poses at the colour timestamps, depth not
    re-aligned in time)."""
    ds = load_dataset(path, downscale=2, undistort=True, interpolate_poses=True, align_depth_time=False,
                      pose_source="given")
    return [ds[i] for i in tqdm(range(len(ds)), desc="read TUM", unit="frame", leave=False)]


def walk_frames(work: Path, level: str, frames: int, size: tuple, seed: int = 0, name: Optional[str] = None,
                trajectory: str = "walk") -> list:
    """Robot A's frames of the synthetic walk (``trajectory``) with sensor level ``level`` and seed ``seed``
    (rendered into ``work / name``, by default :func:`bench.odometry.walk_dir`, unless it is there)."""
    scene = work / name if name else walk_dir(work, level, seed, trajectory)
    if not (scene / "agent_a" / "traj.txt").is_file():
        make_scene(scene, seed=seed, frames=frames, width=size[0], height=size[1], trajectory=trajectory,
                   sensor_noise=level, agents=("agent_a",))
    ds = load_dataset(scene / "agent_a", pose_source="given")
    return [ds[i] for i in tqdm(range(len(ds)), desc=f"read walk ({level})", unit="frame", leave=False)]


def measure(frames: list, tum: Optional[Path] = None) -> dict:
    """Every statistic of :data:`STATS` over ``frames``, and the timestamps' offset when ``tum`` is the TUM sequence's
    folder."""
    out = {name: fn(frames) for name, fn in tqdm(STATS.items(), desc="statistics", unit="stat", leave=False)}
    if tum is not None:
        out["time_offset"] = time_offset(tum)
    return out


def measure_all(args: argparse.Namespace, levels: List[str], size: tuple, work: Path) -> tuple:
    """``(TUM's frames, {sequence: statistics})``: TUM, the walk at each level (seed 0), the scan walk at the ``tum``
    level (``--scan-walk``), the fast walk's blur, and, unless ``--no-odometry``, the odometry's ATE of TUM from each
    start frame of ``--starts`` and of each walk for each seed of ``--seeds``."""
    seeds = [int(v) for v in args.seeds.split(",") if v]
    tum = tum_frames(args.tum)
    results = {"TUM fr1/rpy": measure(tum, args.tum)}
    if not args.no_odometry:
        results["TUM fr1/rpy"]["odometry"] = odometry([tum[int(s):] for s in args.starts.split(",") if s])
    walks = [(f"walk, `{lv}`", lv, "walk", measure) for lv in levels]
    if "tum" in levels and args.scan_walk:  # the walk that turns at TUM's rate
        walks.append(("scan walk, `tum`", "tum", "scan_walk",
                      (lambda fr: {"motion": motion(fr)}) if args.scan_walk == "motion" else measure))
    for key, lv, trajectory, stats in walks:
        frames = walk_frames(work, lv, args.walk_frames, size, trajectory=trajectory)
        results[key] = stats(frames)
        if not args.no_odometry:
            results[key]["odometry"] = odometry(
                [frames if seed == 0 else walk_frames(work, lv, args.walk_frames, size, seed=seed,
                                                      trajectory=trajectory) for seed in seeds])
    if "tum" in levels and args.fast_walk_frames:  # the same 7 m in 3 s: TUM's image speed, for the blur
        fast = walk_frames(work, "tum", args.fast_walk_frames, size, name=f"walk_tum_{args.fast_walk_frames}")
        results[f"fast walk, `tum` ({args.fast_walk_frames} frames)"] = {"blur": blur(fast)}
    return tum, results


def fitted(stats: dict, fx: float, fy: float, readout_s: Optional[float]) -> dict:
    """The sensor model's parameters that the TUM statistics give directly (``fx``, ``fy``: TUM's focal lengths at
    the measured size, px): lattice step, border bands, dark-surface dropout (the excess of holes over the brightest
    grey bin), misregistration (mrad: the depth content's offset from the colour's), depth delay and jitter (from
    the timestamps), colour exposure track, exposure time and rolling-shutter readout."""
    h, mis, ex = stats["holes"], stats["misregistration"], stats["exposure"]
    grey = [(lo, hi, v["holes"]) for (lo, hi), v in zip(zip(GREY_BINS[:-1], GREY_BINS[1:]), h["by_grey"].values())
            if v["holes"] is not None]
    bright = grey[-1][2]
    knots = [[round((lo + min(hi, 255)) / 2, 1), round(max(0.0, (p - bright) / (1 - bright)), 3)] for lo, hi, p in grey]
    knots[-1][1] = 0.0

    def mrad(v: Optional[float], f: float) -> Optional[float]:
        return None if v is None else round(-1e3 * v / f, 2)

    return {"depth_quant_per_m": stats["quantisation"]["c_per_m"],
            **{k: round(h[k], 4) for k in ("border_top", "border_bottom", "border_left", "border_right")},
            "dark_dropout": knots,
            "misregistration_x_mrad": mrad(mis["x"]["offset_px"], fx),
            "misregistration_y_mrad": mrad(mis["y"]["offset_px"], fy),
            "depth_time_offset_s": round(stats["time_offset"]["mean_ms"] / 1e3, 4),
            "depth_time_jitter_s": round(stats["time_offset"]["std_ms"] / 1e3, 4),
            "gain_log_std": ex["gain_log_std"], "exposure_smooth_s": ex["smooth_s"],
            "white_balance_std": ex["white_balance_std"], "exposure_s": stats["blur"]["exposure_s"],
            "readout_s": readout_s}


def rolling_shutter_readout() -> Optional[float]:
    """The best colour readout time (s) of ``bench/results/rolling_shutter.json`` (``python -m
    bench.rolling_shutter``), or None when the file is absent."""
    p = RESULTS / "rolling_shutter.json"
    return float(json.loads(p.read_text())["best_readout_s"]) if p.is_file() else None


def _get(d, path: str):
    """The value at ``path`` (``/``-separated keys, or indices into lists) in ``d``, None where it is missing."""
    for k in path.split("/"):
        if isinstance(d, list):
            d = d[int(k)] if k.isdigit() and int(k) < len(d) else None
        elif isinstance(d, dict):
            d = d.get(k)
        if d is None:
            return None
    return d


def _fmt(v, scale: float = 1.0, digits: int = 2) -> str:
    return "—" if v is None else f"{scale * v:.{digits}f}"


#: the comparison table's rows: label, path into a sequence's statistics, scale, digits
ROWS = [("depth step, z 1.0–1.5 m (mm)", "quantisation/step_m/1.0-1.5", 1e3, 1),
        ("depth step, z 2.0–2.5 m (mm)", "quantisation/step_m/2.0-2.5", 1e3, 1),
        ("depth step, z 3.0–4.0 m (mm)", "quantisation/step_m/3.0-4.0", 1e3, 1),
        ("c of step = c z² (1/m)", "quantisation/c_per_m", 1e3, 2),
        *[(f"plane residual {k}, z {b} m (mm)", f"noise/{k}_mm/{b}", 1.0, 2)
          for k in ("3x3", "5x5") for b in ("1.0-1.5", "2.0-2.5", "3.0-4.0")],
        ("holes, all (%)", "holes/all", 100, 1), ("holes, border bands (%)", "holes/border", 100, 1),
        ("holes, interior (%)", "holes/interior", 100, 1),
        ("holes, interior, grey 0–20 (%)", "holes/by_grey/0-20/holes", 100, 1),
        ("holes, interior, grey 20–40 (%)", "holes/by_grey/20-40/holes", 100, 1),
        ("holes, interior, grey 130–255 (%)", "holes/by_grey/130-256/holes", 100, 1),
        ("depth jumps with holes between (%)", "edges/with_holes", 100, 1),
        ("mean hole run at a jump (px)", "edges/run_mean_px", 1.0, 2),
        ("edge pixels flying (%)", "edges/pixel_between/flying", 100, 2),
        ("edge pixels without depth (%)", "edges/pixel_between/hole", 100, 2),
        ("colour − depth edge offset, x (px)", "misregistration/x/offset_px", 1.0, 2),
        ("colour − depth edge offset, y (px)", "misregistration/y/offset_px", 1.0, 2),
        ("depth delay from edge offsets, x (ms)", "misregistration/x/delay_ms", 1.0, 1),
        ("depth delay from edge offsets, y (ms)", "misregistration/y/delay_ms", 1.0, 1),
        ("depth − colour timestamp, mean (ms)", "time_offset/mean_ms", 1.0, 1),
        ("depth − colour timestamp, std (ms)", "time_offset/std_ms", 1.0, 1),
        *[(f"log gain spread over {2 ** j}/15 s", f"exposure/log_gain_spread/{j}", 1.0, 3) for j in (0, 2, 4)],
        ("log gain std (fit)", "exposure/gain_log_std", 1.0, 3),
        ("log gain smoothing (fit, s)", "exposure/smooth_s", 1.0, 2),
        ("white balance std (fit)", "exposure/white_balance_std", 1.0, 3),
        ("median image speed (px/s)", "blur/median_speed_px_s", 1.0, 0),
        ("exposure time from blur (ms)", "blur/exposure_s", 1e3, 1),
        ("colour noise (grey levels)", "colour_noise/sigma_grey", 1.0, 2),
        ("frame spacing (ms)", "motion/frame_spacing_s", 1e3, 1),
        ("rotation per frame, median (°)", "motion/deg_per_frame", 1.0, 2),
        ("rotation speed, median (°/s)", "motion/deg_per_s", 1.0, 1),
        ("translation speed, median (m/s)", "motion/m_per_s", 1.0, 3),
        ("odometry ATE, default settings, mean over runs (cm)", "odometry/ate_rmse_m", 100, 2),
        ("odometry ATE, std over runs (cm)", "odometry/ate_std_m", 100, 2),
        ("odometry ATE online, mean (cm)", "odometry/ate_online_m", 100, 2),
        ("loops closed per run", "odometry/loops", 1.0, 1),
        ("false loops", "odometry/false_loops", 1.0, 0)]


def table(results: dict) -> str:
    """The Markdown comparison table: one row per statistic (:data:`ROWS`), one column per sequence."""
    cols = list(results)
    rows = ["| statistic | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for label, path, scale, digits in ROWS:
        cells = [_fmt(_get(results[c], path), scale, digits) for c in cols]
        rows.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def params_table(fit: dict, levels: List[str]) -> str:
    """The Markdown table of the model's parameters: fitted from TUM against each sensor level's value."""
    models = {lv: sensor_model(lv) for lv in levels if sensor_model(lv) is not None}
    names = list(fit) + [k for k in ("depth_sigma_a", "depth_sigma_b", "depth_noise_corr_px", "shadow_p",
                                     "shadow_mean_px", "flying_p", "blob_fraction", "speckle_fraction", "edge_drop_p",
                                     "depth_readout_s", "read_noise", "shot_noise", "offset_std") if k not in fit]
    rows = ["| parameter | fitted from TUM | " + " | ".join(f"`{lv}`" for lv in models) + " |",
            "|---|---|" + "---|" * len(models)]
    for n in names:
        f = fit.get(n)
        cells = [json.dumps(getattr(m, n)) if not isinstance(getattr(m, n), float) else f"{getattr(m, n):g}"
                 for m in models.values()]
        rows.append(f"| `{n}` | {'—' if f is None else json.dumps(f) if not isinstance(f, float) else f'{f:g}'} | "
                    + " | ".join(cells) + " |")
    return "\n".join(rows)


def main(argv: Optional[List[str]] = None) -> int:
    """Entry point: measure TUM and the walk at each level, print and write the tables and the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tum", type=Path, default=TUM, help="the TUM fr1/rpy folder")
    ap.add_argument("--levels", default="tum,realistic", help=f"comma-separated sensor levels, of {', '.join(LEVELS)}")
    ap.add_argument("--walk-frames", type=int, default=525, help="frames of the synthetic walk (525: 7 m at 30 fps)")
    ap.add_argument("--fast-walk-frames", type=int, default=90,
                    help="frames of a fast walk (the same 7 m) on which the tum level's blur is measured at about "
                         "TUM's image speed (0: none)")
    ap.add_argument("--size", default="320x240", help="WxH of the synthetic walk")
    ap.add_argument("--work", type=Path, default=None,
                    help="folder for the rendered walks, kept for the next run and for bench.odometry --work")
    ap.add_argument("--no-odometry", action="store_true", help="do not track the sequences with the odometry")
    ap.add_argument("--starts", default="0,1,2", help="the odometry's start frames on TUM, one run each")
    ap.add_argument("--seeds", default="0,1,2", help="the walk's seeds (scene, path and sensor noise) tracked, one "
                    "run each; the statistics are those of seed 0")
    ap.add_argument("--scan-walk", choices=("", "motion", "all"), default="all",
                    help="also the walk that looks around as it goes (--trajectory scan_walk, at the tum level): "
                         "every statistic (all), only its motion (motion), or not at all ('')")
    ap.add_argument("--out", type=Path, default=RESULTS / "sensor_calibration.json")
    args = ap.parse_args(argv)
    levels = [lv for lv in args.levels.split(",") if lv]
    bad = [lv for lv in levels if lv not in LEVELS]
    if bad:
        ap.error(f"unknown sensor level: {', '.join(bad)}")
    size = tuple(int(v) for v in args.size.lower().split("x"))
    t0 = time.perf_counter()
    import tempfile  # noqa: PLC0415 - only for a run without --work

    with tempfile.TemporaryDirectory(prefix="bench_sensor_") as tmp:
        tum, results = measure_all(args, levels, size, args.work or Path(tmp))
    fit = fitted(results["TUM fr1/rpy"], tum[0].intrinsics.fx, tum[0].intrinsics.fy, rolling_shutter_readout())
    md = table(results) + "\n\n" + params_table(fit, levels)
    doc = {"walk_frames": args.walk_frames, "size": list(size), "levels": levels, "seeds": args.seeds,
           "starts": args.starts, "statistics": results,
           "fitted_from_tum": fit, "models": {lv: (None if sensor_model(lv) is None else sensor_model(lv).to_json())
                                               for lv in levels}}
    details = f": {time.perf_counter() - t0:.0f} s; load average {os.getloadavg()[0]:.1f} after (2 cores)"
    write_results(args.out, "sensor_calibration", argv, details, md, doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
