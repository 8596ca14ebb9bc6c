"""Calibration checked: the intrinsics, distortion and depth scale each dataset layout reads, measured against the
dataset's published calibration by what they do downstream (docs/mapper.md, "Calibration").

TUM RGB-D fr1/rpy (``gausslite.datasets.tum``), each camera variant read through ``load_dataset`` at 320×240
(``--downscale 2``), ground-truth poses interpolated at the colour timestamps:

- ``fr1_undistorted``: the hand-held profile's reading (``gausslite.mapping.profiles``): TUM's published Freiburg-1
  colour intrinsics (517.3, 516.5, 318.6, 255.3), the images undistorted with the published k1, k2, p1, p2, k3, depth
  = value / 5000;
- ``fr1_distorted``: the same intrinsics on the images as stored (``undistort=False``, ``TUMDataset``'s own default);
- ``ros_default``: the ROS default camera (525, 525, 319.5, 239.5) that TUM's calibration page gives for turning any
  sequence's depth into a point cloud, no distortion;
- ``fr1_undistorted_ds1.035``: the profile's camera with TUM's depth correction for the Freiburg-1 Kinect, depth =
  value × 1.035 / 5000 (``depth_scale`` 5000 / 1.035).

Each variant is scored by

- **odometry ATE**: ``RGBDOdometry`` with the default ``OdometryConfig`` over the frames (the first tracked frame's
  ground-truth pose fixes the world frame; depth not re-aligned in time, as ``bench.odometry`` reads TUM), ATE RMSE
  after rigid alignment (:func:`~gausslite.datasets.trajectory.ate_rmse`), ``--runs`` runs, run ``r`` from frame
  ``r`` (a new start moves every keyframe), as a mean and a sample standard deviation; Open3D's odometry is
  multi-threaded, so the run from frame 0 is also repeated on the same input (its change is reported);
- **consistency with the ground truth** (:func:`warp_pair`, no estimation at all): frame ``i``'s depth pixels are
  back-projected with the variant's intrinsics, moved by the ground-truth relative pose into frame ``j`` and
  projected: the mean absolute colour difference against frame ``j`` (bilinear, 0–255) and the median relative
  difference between the moved depth and frame ``j``'s depth (%; relative, so that a depth scale does not scale the
  sensor's noise with it), with its signed median (a bias). Two sets of pairs, chosen by the ground-truth poses so
  that every variant is scored on the same ones: ``adjacent``, every ``(i, i + g)`` for the gaps ``--gaps`` (the
  intrinsics and distortion show in the rotation between neighbours), and ``wide``, pairs at least
  ``--min-baseline`` m apart with optical axes within 15° (a depth scale error moves a point by the baseline times
  the error; a rotation alone does not show it). The depth is re-projected from its own timestamp to the colour
  frame's (``align_depth_time``, the hand-held profile's reading). Each variant's figures are compared with the
  default's pair by pair (:func:`gausslite.stats.paired_gain`, 95 % interval).

The depth scale is also swept (``--depth-multipliers``, the default camera, consistency only): the multiplier at
which frame pairs agree best with the motion capture.

Replica room0 (``gausslite.datasets.replica``): the intrinsics and depth scale the loader reads against
``cam_params.json`` read directly (full size, and at ``--replica-downscale`` against the scaling rule of
``Intrinsics.scaled``), and the same consistency check over a depth-scale sweep (rendered depth and exact poses: the
file's scale should agree best, with next to no error).

Sources: Sturm et al., "A Benchmark for the Evaluation of RGB-D SLAM Systems", IROS 2012, and the benchmark's
"Intrinsic Camera Calibration of the Kinect" section of its file-format page (the Freiburg-1 colour intrinsics and
distortion, the ROS default camera, the Freiburg-1 depth correction factor 1.035).

Usage::

    python -m bench.calibration [--tum PATH] [--replica PATH] [--runs 3] [--gaps 1,3] [--max-frames N]
                                [--min-baseline 0.05] [--variants fr1_undistorted,...]
                                [--depth-multipliers 0.95,...] [--replica-multipliers 0.97,...]
                                [--out bench/results/calibration.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import cv2
import numpy as np
from tqdm import tqdm

from bench._results import DATASETS, write_results
from gausslite.camera import Intrinsics
from gausslite.datasets import load_dataset
from gausslite.datasets.odometry import OdometryConfig, RGBDOdometry
from gausslite.datasets.trajectory import ate_rmse
from gausslite.datasets.tum import TUM_DISTORTION, TUM_INTRINSICS
from gausslite.stats import fmt_gain, mean_std, paired_gain, significant

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"

#: the raw units per metre of TUM's depth files (the file-format page)
TUM_DEPTH_SCALE = 5000.0
#: TUM's depth correction factor of the Freiburg-1 Kinect: depth_m = value × 1.035 / 5000
FR1_DEPTH_CORRECTION = 1.035
#: the camera variants of TUM fr1: ``load_dataset`` keywords over :data:`TUM_READ`
VARIANTS: Dict[str, dict] = {
    "fr1_undistorted": {"undistort": True},
    "fr1_distorted": {"undistort": False},
    "ros_default": {"undistort": False, "intrinsics": TUM_INTRINSICS[None]},
    "fr1_undistorted_ds1.035": {"undistort": True, "depth_scale": TUM_DEPTH_SCALE / FR1_DEPTH_CORRECTION},
}
#: the variant the TUM layout reads by default (the hand-held profile's loader options)
DEFAULT_VARIANT = "fr1_undistorted"
#: what every TUM variant shares: the ground truth at the colour timestamps, read as given
TUM_READ = {"interpolate_poses": True, "pose_source": "given"}
DEPTH_MULTIPLIERS = (0.95, 0.97, 1.0, 1.0175, 1.035, 1.07)
REPLICA_MULTIPLIERS = (0.97, 0.99, 1.0, 1.01, 1.03)


def warp_pair(fi, fj) -> Optional[dict]:
    """Frame ``fi``'s depth pixels moved into frame ``fj`` by the poses and the intrinsics the frames carry.

    Args:
        fi, fj: frames (``rgb`` (H, W, 3) uint8, ``depth`` (H, W) float32 metres, ``c2w`` (4, 4) float64
            camera-to-world, OpenCV axes; the same ``intrinsics``).
    Returns:
        ``{"colour_l1": mean |fj's colour, bilinear, at the projections − fi's colour| over the pixels that land inside
        fj (0–255, channels averaged), "depth_rel_pct": median |z in fj − fj's depth| / fj's depth in % (fj's depth
        bilinear where its four neighbours all hold one; relative, so that a depth scale does not scale the sensor's
        noise with it), "depth_bias_pct": median (z in fj − fj's depth) / fj's depth in %, "covered": share of fi's pixels that land
        inside fj}``; None when no pixel lands inside fj with a depth there.
    """
    H, W = fi.depth.shape
    K = fi.intrinsics.K
    vv, uu = np.nonzero(fi.depth > 0)
    z = fi.depth[vv, uu].astype(np.float64)
    X = np.stack([(uu - K[0, 2]) / K[0, 0] * z, (vv - K[1, 2]) / K[1, 1] * z, z], 1)
    T = np.linalg.inv(fj.c2w) @ fi.c2w
    P = X @ T[:3, :3].T + T[:3, 3]
    zp = np.maximum(P[:, 2], 1e-6)
    u, v = K[0, 0] * P[:, 0] / zp + K[0, 2], K[1, 1] * P[:, 1] / zp + K[1, 2]
    ok = (P[:, 2] > 0.1) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    if not ok.any():
        return None
    mapx = np.full((H, W), -1.0, np.float32)
    mapy = np.full((H, W), -1.0, np.float32)
    mapx[vv[ok], uu[ok]], mapy[vv[ok], uu[ok]] = u[ok], v[ok]
    warped = cv2.remap(fj.rgb.astype(np.float32), mapx, mapy, cv2.INTER_LINEAR)
    colour = np.abs(warped[vv[ok], uu[ok]] - fi.rgb[vv[ok], uu[ok]].astype(np.float32)).mean()
    dj = cv2.remap(fj.depth.astype(np.float32), mapx, mapy, cv2.INTER_LINEAR)[vv[ok], uu[ok]].astype(np.float64)
    # a bilinear depth counts only where its four neighbours all hold a measurement (else it mixes in zeros)
    full = cv2.remap((fj.depth > 0).astype(np.float32), mapx, mapy, cv2.INTER_LINEAR)[vv[ok], uu[ok]] > 0.999
    if not full.any():
        return None
    rel = (P[ok, 2][full] - dj[full]) / dj[full]
    return {"colour_l1": float(colour), "depth_rel_pct": 100 * float(np.median(np.abs(rel))),
            "depth_bias_pct": 100 * float(np.median(rel)), "covered": float(ok.sum() / (H * W))}


def adjacent_pairs(n: int, gaps: Sequence[int]) -> List[tuple]:
    """Every pair ``(i, i + g)`` of ``n`` frames, ``g`` in ``gaps`` (indices into the frame list)."""
    return [(i, i + g) for g in gaps for i in range(n - g)]


def wide_pairs(frames: Sequence, min_baseline_m: float = 0.05, max_angle_deg: float = 15.0,
               max_pairs: int = 150) -> List[tuple]:
    """Pairs ``(i, j)`` of ``frames`` whose optical centres lie at least ``min_baseline_m`` apart (metres, by their
    ``c2w``) and whose optical axes are within ``max_angle_deg``: the pairs whose depth scale shows (a scale error
    moves a point by the baseline times the error; a rotation alone does not show it). At most ``max_pairs``, evenly
    spaced over the qualifying pairs in order."""
    out = []
    for i in range(len(frames)):
        for j in range(i + 1, len(frames)):
            a, b = frames[i].c2w, frames[j].c2w
            cos = float(np.clip(a[:3, 2] @ b[:3, 2], -1.0, 1.0))
            if np.linalg.norm(a[:3, 3] - b[:3, 3]) >= min_baseline_m and np.degrees(np.arccos(cos)) <= max_angle_deg:
                out.append((i, j))
    if len(out) > max_pairs:
        out = [out[k] for k in np.linspace(0, len(out) - 1, max_pairs).round().astype(int)]
    return out


def consistency(frames: Sequence, pairs: Sequence[tuple]) -> dict:
    """:func:`warp_pair` over ``pairs`` (indices into ``frames``): the per-pair figures keyed ``"i-j"`` by frame id
    (``pairs``) and their means over the pairs with the sample standard deviation (``colour_l1``, ``depth_rel_pct``,
    ``depth_bias_pct``, ``covered``: ``[mean, std]``)."""
    figures = {}
    for i, j in pairs:
        r = warp_pair(frames[i], frames[j])
        if r is not None:
            figures[f"{frames[i].frame_id}-{frames[j].frame_id}"] = r
    out: dict = {"n_pairs": len(figures), "pairs": figures}
    for k in ("colour_l1", "depth_rel_pct", "depth_bias_pct", "covered"):
        out[k] = list(mean_std(p[k] for p in figures.values()))
    return out


def odometry_ate(frames: Sequence, runs: int) -> dict:
    """ATE RMSE (m) of the default ``RGBDOdometry`` against the frames' ``c2w``, over ``runs`` runs: run ``r`` tracks
    frames ``r`` to the last (a new start moves every keyframe, so the runs spread as the odometry does over the
    same motion), and run 0 is repeated on the same input (``repeat_m``: the odometry is multi-threaded, so the
    repeat may differ from ``runs[0]``). Returns each run's figure, their mean and sample standard deviation, the
    start frames and the share of frames tracked per run."""
    def ate(start: int) -> tuple:
        part = frames[start:]
        odo = RGBDOdometry(OdometryConfig(), initial_pose=part[0].c2w)
        res = [odo.track(f) for f in part]
        est, ref = np.stack([r.c2w for r in res]), np.stack([f.c2w for f in part])
        return ate_rmse(est, ref), float(np.mean([r.ok for r in res]))

    out = [ate(r) for r in range(runs)]
    m, s = mean_std(a for a, _ in out)
    return {"runs": [a for a, _ in out], "start_frames": list(range(runs)), "mean_m": m, "std_m": s,
            "repeat_m": ate(0)[0], "tracked_fraction": [t for _, t in out]}


def read_tum(path: Path, downscale: float, max_frames: Optional[int], align_depth_time: bool, **kw) -> list:
    """The frames of the TUM sequence at ``path`` read with :data:`TUM_READ` and ``kw`` (``load_dataset`` keywords)."""
    ds = load_dataset(path, downscale=downscale, max_frames=max_frames, align_depth_time=align_depth_time,
                      progress=False, **TUM_READ, **kw)
    return [ds[i] for i in range(len(ds))]


def camera_of(path: Path, **kw) -> dict:
    """What a TUM variant reads at full size: the intrinsics of the images it yields (after undistortion), of the files,
    the distortion it undid and the depth scale."""
    ds = load_dataset(path, max_frames=1, progress=False, **TUM_READ, **kw)
    ni, ri = ds.native_intrinsics, getattr(ds, "raw_intrinsics", ds.native_intrinsics)
    return {"intrinsics": [ni.fx, ni.fy, ni.cx, ni.cy], "file_intrinsics": [ri.fx, ri.fy, ri.cx, ri.cy],
            "undistorted_with": list(ds.distortion) if ds.undistort else None, "depth_scale": ds.depth_scale,
            "size": [ni.width, ni.height]}


def pair_sets(frames: Sequence, gaps: Sequence[int], min_baseline_m: float) -> Dict[str, List[tuple]]:
    """The two sets of frame pairs every consistency figure is taken over: ``adjacent`` (:func:`adjacent_pairs`: the
    intrinsics and the distortion show in the rotation between neighbours) and ``wide`` (:func:`wide_pairs`: the
    depth scale shows across a baseline). Chosen by the ground-truth poses, so every variant is scored on the same
    pairs."""
    return {"adjacent": adjacent_pairs(len(frames), gaps), "wide": wide_pairs(frames, min_baseline_m)}


def tum_variants(path: Path, names: Sequence[str], downscale: float, max_frames: Optional[int], runs: int,
                 pairs: Dict[str, List[tuple]]) -> dict:
    """Per variant of :data:`VARIANTS`: the camera it reads (:func:`camera_of`), the odometry's ATE
    (:func:`odometry_ate`, depth as stored) and the consistency with the ground truth over each set of ``pairs``
    (:func:`consistency`, depth re-aligned in time)."""
    out = {}
    for name in tqdm(names, desc="TUM variants", unit="variant"):
        kw = VARIANTS[name]
        ate = odometry_ate(read_tum(path, downscale, max_frames, False, **kw), runs)
        frames = read_tum(path, downscale, max_frames, True, **kw)
        cons = {k: consistency(frames, p) for k, p in pairs.items()}
        out[name] = {"loader": kw, "camera": camera_of(path, **kw), "ate": ate, "consistency": cons}
        a = cons["adjacent"]
        print(f"  {name}: ATE {_cm(ate['mean_m'])} ± {_cm(ate['std_m'])} cm, colour L1 {_num(a['colour_l1'][0])}, "
              f"depth error {_num(a['depth_rel_pct'][0])} % (adjacent), {_num(cons['wide']['depth_rel_pct'][0])} % (wide)")
    return out


def _paired(r: dict, base: dict, pair_set: str, key: str) -> dict:
    """:func:`gausslite.stats.paired_gain` of ``key`` over the pairs of ``pair_set``: variant ``r`` − ``base``."""
    cp, bp = r["consistency"][pair_set]["pairs"], base["consistency"][pair_set]["pairs"]
    return paired_gain({k: v[key] for k, v in cp.items()}, {k: v[key] for k, v in bp.items()})


def compare(variants: dict, default: str) -> dict:
    """Each variant against ``default``: the ATE difference (m, variant − default) with ``beyond_spread`` (it exceeds
    twice the larger of the two runs' standard deviations; None with a single run), and the paired per-pair
    differences of the colour and depth figures (:func:`gausslite.stats.paired_gain`; negative: the variant agrees
    better with the ground truth)."""
    base = variants[default]
    out = {}
    for name, r in variants.items():
        d = r["ate"]["mean_m"] - base["ate"]["mean_m"]
        runs = min(len(r["ate"]["runs"]), len(base["ate"]["runs"]))
        spread = max(r["ate"]["std_m"], base["ate"]["std_m"])
        out[name] = {"ate_minus_default_m": d, "beyond_spread": bool(abs(d) > 2 * spread) if runs > 1 else None,
                     "colour_l1_minus_default": _paired(r, base, "adjacent", "colour_l1"),
                     "depth_rel_minus_default": _paired(r, base, "adjacent", "depth_rel_pct"),
                     "wide_depth_rel_minus_default": _paired(r, base, "wide", "depth_rel_pct")}
    return out


def depth_sweep(frames_for, multipliers: Sequence[float], pairs: Dict[str, List[tuple]]) -> List[dict]:
    """The consistency (:func:`consistency`) of the frames ``frames_for(multiplier)`` reads at each depth multiplier
    (depth_m = value × multiplier / scale), over each set of ``pairs``: ``[{"multiplier", "adjacent": {...},
    "wide": {...}}]`` with ``colour_l1``, ``depth_rel_pct``, ``depth_bias_pct`` (``[mean, std]``) and ``n_pairs`` per
    set, and, when the multipliers hold 1, ``minus_1``: the paired differences from multiplier 1 of the wide pairs'
    ``depth_rel_pct`` and ``colour_l1`` (:func:`gausslite.stats.paired_gain`)."""
    rows, figures = [], []
    for m in tqdm(multipliers, desc="depth scale", unit="scale"):
        frames = frames_for(m)
        row: dict = {"multiplier": m}
        cons = {k: consistency(frames, p) for k, p in pairs.items()}
        for k, c in cons.items():
            row[k] = {f: c[f] for f in ("n_pairs", "colour_l1", "depth_rel_pct", "depth_bias_pct")}
        rows.append(row)
        figures.append(cons["wide"]["pairs"])
    if 1.0 in multipliers:
        base = figures[list(multipliers).index(1.0)]
        for row, fig in zip(rows, figures):
            row["minus_1"] = {key: paired_gain({k: v[key] for k, v in fig.items()},
                                               {k: v[key] for k, v in base.items()})
                              for key in ("depth_rel_pct", "colour_l1")}
    return rows


def replica_check(path: Path, downscale: float, max_frames: Optional[int], multipliers: Sequence[float],
                  gaps: Sequence[int], min_baseline_m: float) -> dict:
    """Replica's ``cam_params.json`` read directly against what ``load_dataset`` reads (full size, and at
    ``downscale`` against ``Intrinsics.scaled``), and the consistency over a depth-scale sweep.

    Raises:
        FileNotFoundError: no ``cam_params.json`` in the sequence folder or its parent.
    """
    ds = load_dataset(path, downscale=downscale, max_frames=max_frames, progress=False, pose_source="given")
    cp_path = next((d / "cam_params.json" for d in (ds.path, ds.path.parent) if (d / "cam_params.json").is_file()),
                   None)
    if cp_path is None:
        raise FileNotFoundError(f"cam_params.json not found beside {ds.path}")
    cam = json.loads(cp_path.read_text(encoding="utf-8"))["camera"]
    published = Intrinsics(float(cam["fx"]), float(cam["fy"]), float(cam["cx"]), float(cam["cy"]), int(cam["w"]),
                           int(cam["h"]))
    ni, si, want = ds.native_intrinsics, ds.intrinsics, published.scaled(downscale)

    def row(i: Intrinsics) -> list:
        return [i.fx, i.fy, i.cx, i.cy, i.width, i.height]

    checks = {"native_intrinsics": row(ni) == row(published), "scaled_intrinsics": row(si) == row(want),
              "depth_scale": ds.depth_scale == float(cam["scale"])}

    def frames_for(m: float) -> list:
        d = load_dataset(path, downscale=downscale, max_frames=max_frames, progress=False, pose_source="given",
                         depth_scale=float(cam["scale"]) / m)
        return [d[i] for i in range(len(d))]

    pairs = pair_sets(frames_for(1.0), gaps, min_baseline_m)
    return {"cam_params": {"file": str(cp_path), **cam}, "loader": {"native": row(ni), "scaled": row(si),
                                                                     "scaled_expected": row(want),
                                                                     "depth_scale": ds.depth_scale},
            "downscale": downscale, "checks": checks, "agree": all(checks.values()),
            "depth_sweep": depth_sweep(frames_for, multipliers, pairs)}


def _cm(v: Optional[float]) -> str:
    return "–" if v is None else f"{100 * v:.2f}"


def _num(v: Optional[float], scale: float = 1.0, sign: str = "", digits: int = 2) -> str:
    """``v × scale`` with ``digits`` decimals (``sign`` "+" shows it), "–" for None (no pair or run behind it)."""
    return "–" if v is None else f"{v * scale:{sign}.{digits}f}"


def tum_table(variants: dict, cmp: dict, default: str) -> str:
    """The Markdown table of the TUM variants (:func:`tum_variants`, :func:`compare`)."""
    rows = ["| variant | intrinsics read (fx, fy, cx, cy at 640×480) | depth ÷ | ATE cm (mean ± std, runs) | "
            "ATE − default cm | colour L1, adjacent (0–255) | − default [95 %] | depth error %, adjacent | "
            "− default [95 %] | depth error %, wide | − default [95 %] |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in variants.items():
        cam, a, d = r["camera"], r["ate"], cmp[name]
        adj, wide = r["consistency"]["adjacent"], r["consistency"]["wide"]
        intr = ", ".join(f"{x:.2f}" for x in cam["intrinsics"]) + (" (undistorted)" if cam["undistorted_with"] else "")
        tag = " (default)" if name == default else ""
        beyond = "" if name == default else {True: " (beyond spread)", False: " (within spread)",
                                             None: ""}[d["beyond_spread"]]
        rows.append(f"| {name}{tag} | {intr} | {cam['depth_scale']:.1f} | {_cm(a['mean_m'])} ± {_cm(a['std_m'])} "
                    f"({len(a['runs'])}) | {100 * d['ate_minus_default_m']:+.2f}{beyond} | {_num(adj['colour_l1'][0])} "
                    f"| {fmt_gain(d['colour_l1_minus_default'])} | {_num(adj['depth_rel_pct'][0], digits=3)} | "
                    f"{fmt_gain(d['depth_rel_minus_default'], 3)} | {_num(wide['depth_rel_pct'][0], digits=3)} | "
                    f"{fmt_gain(d['wide_depth_rel_minus_default'], 3)} |")
    diff = max(abs(r["ate"]["repeat_m"] - r["ate"]["runs"][0]) for r in variants.values())
    runs = len(next(iter(variants.values()))["ate"]["runs"])
    rows.append(f"\nATE runs start at frames 0 to {runs - 1}; the run from frame 0, repeated on the same input, changed "
                f"its ATE by {diff:.1e} m at most. Consistency pairs: "
                f"{next(iter(variants.values()))['consistency']['adjacent']['n_pairs']} adjacent, "
                f"{next(iter(variants.values()))['consistency']['wide']['n_pairs']} wide-baseline.")
    return "\n".join(rows)


def sweep_table(title: str, rows: List[dict], scale: float) -> str:
    """The Markdown table of a depth-scale sweep (:func:`depth_sweep`) of a sequence whose files hold ``scale``
    units per metre."""
    n = rows[0]
    out = [f"| {title}: depth multiplier | depth ÷ | colour L1, adjacent | depth error %, adjacent | colour L1, wide | "
           f"− ×1 [95 %] | depth error %, wide | − ×1 [95 %] | depth bias %, wide |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        a, w, g = r["adjacent"], r["wide"], r.get("minus_1", {})
        out.append(f"| {r['multiplier']:g} | {scale / r['multiplier']:.1f} | {_num(a['colour_l1'][0])} | "
                   f"{_num(a['depth_rel_pct'][0], digits=3)} | {_num(w['colour_l1'][0])} | "
                   f"{fmt_gain(g.get('colour_l1'))} | {_num(w['depth_rel_pct'][0], digits=3)} | "
                   f"{fmt_gain(g.get('depth_rel_pct'), 3)} | {_num(w['depth_bias_pct'][0], sign='+', digits=3)} |")
    out.append(f"\n{n['adjacent']['n_pairs']} adjacent pairs, {n['wide']['n_pairs']} wide-baseline pairs.")
    return "\n".join(out)


def replica_table(rep: dict) -> str:
    """The Markdown table of :func:`replica_check`."""
    cam, ld = rep["cam_params"], rep["loader"]
    pub = [cam["fx"], cam["fy"], cam["cx"], cam["cy"], cam["w"], cam["h"]]

    def fmt(v: list) -> str:
        return ", ".join(f"{x:g}" for x in v)

    return ("| Replica room0 | cam_params.json | loader reads | agree |\n|---|---|---|---|\n"
            f"| fx, fy, cx, cy, w, h | {fmt(pub)} | {fmt(ld['native'])} | {rep['checks']['native_intrinsics']} |\n"
            f"| the same at 1/{rep['downscale']:g} | {fmt(ld['scaled_expected'])} (`Intrinsics.scaled`) | "
            f"{fmt(ld['scaled'])} | {rep['checks']['scaled_intrinsics']} |\n"
            f"| depth units per metre | {cam['scale']:g} | {ld['depth_scale']:g} | {rep['checks']['depth_scale']} |")


def verdict(variants: dict, cmp: dict, default: str) -> dict:
    """Which variant measures best: ``better_than_default`` lists the variants whose ATE is below the default's by more
    than twice the runs' spread and none of whose consistency errors is significantly above the default's."""
    def worse(g: dict) -> bool:
        return significant(g) and g["gain"] > 0

    better = [n for n, d in cmp.items() if n != default and d["beyond_spread"] and d["ate_minus_default_m"] < 0
              and not any(worse(d[k]) for k in ("colour_l1_minus_default", "depth_rel_minus_default",
                                                "wide_depth_rel_minus_default"))]
    lowest = min(variants, key=lambda n: variants[n]["ate"]["mean_m"])
    return {"default": default, "lowest_ate": lowest, "better_than_default": better, "keep_default": not better}


def parse_args(argv: Optional[List[str]]) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tum", type=Path, default=DATASETS / "TUM_rgbd_dataset_freiburg1_rpy")
    ap.add_argument("--replica", type=Path, default=DATASETS / "Replica_room0")
    ap.add_argument("--downscale", type=float, default=2.0, help="TUM: 2 reads 320×240, as bench.odometry")
    ap.add_argument("--replica-downscale", type=float, default=4.0)
    ap.add_argument("--max-frames", type=int, default=None, help="the first N frames of each sequence")
    ap.add_argument("--runs", type=int, default=3, help="odometry runs per variant")
    ap.add_argument("--gaps", default="1,3", help="frame gaps of the consistency pairs")
    ap.add_argument("--min-baseline", type=float, default=0.05, help="wide pairs: optical centres this far apart (m)")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--depth-multipliers", default=",".join(f"{m:g}" for m in DEPTH_MULTIPLIERS))
    ap.add_argument("--replica-multipliers", default=",".join(f"{m:g}" for m in REPLICA_MULTIPLIERS))
    ap.add_argument("--out", type=Path, default=RESULTS / "calibration.json")
    args = ap.parse_args(argv)
    args.gaps = [int(g) for g in args.gaps.split(",")]
    args.variants = [v for v in args.variants.split(",") if v]
    unknown = [v for v in args.variants if v not in VARIANTS]
    if unknown or DEFAULT_VARIANT not in args.variants:
        ap.error(f"--variants must name {DEFAULT_VARIANT} and only variants of {sorted(VARIANTS)} (got {unknown})")
    if args.runs < 1 or min(args.gaps) < 1:
        ap.error("--runs and every gap must be at least 1")
    args.depth_multipliers = [float(m) for m in args.depth_multipliers.split(",")]
    args.replica_multipliers = [float(m) for m in args.replica_multipliers.split(",")]
    return args


def main(argv: Optional[List[str]] = None) -> int:
    """Measure TUM fr1/rpy's camera variants and Replica room0's camera, print the tables, write JSON and Markdown.
    Returns 2 when a dataset is absent."""
    args = parse_args(argv)
    for p in (args.tum, args.replica):
        if not p.exists():
            print(f"dataset not found: {p} (set GAUSSLITE_SHARED)", file=sys.stderr)
            return 2
    tum_frames = read_tum(args.tum, args.downscale, args.max_frames, True, **VARIANTS[DEFAULT_VARIANT])
    pairs = pair_sets(tum_frames, args.gaps, args.min_baseline)
    del tum_frames
    variants = tum_variants(args.tum, args.variants, args.downscale, args.max_frames, args.runs, pairs)
    cmp = compare(variants, DEFAULT_VARIANT)
    sweep = depth_sweep(lambda m: read_tum(args.tum, args.downscale, args.max_frames, True, undistort=True,
                                           depth_scale=TUM_DEPTH_SCALE / m), args.depth_multipliers, pairs)
    rep = replica_check(args.replica, args.replica_downscale, args.max_frames, args.replica_multipliers, args.gaps,
                        args.min_baseline)
    for r in variants.values():  # the per-pair figures stay in memory: their comparison is in "compare"
        for c in r["consistency"].values():
            c.pop("pairs")
    result = {"published": {"tum_fr1_intrinsics": TUM_INTRINSICS[1], "tum_fr1_distortion": TUM_DISTORTION[1],
                            "tum_ros_default_intrinsics": TUM_INTRINSICS[None], "tum_depth_scale": TUM_DEPTH_SCALE,
                            "tum_fr1_depth_correction": FR1_DEPTH_CORRECTION},
              "settings": {"tum": str(args.tum), "replica": str(args.replica), "downscale": args.downscale,
                           "replica_downscale": args.replica_downscale, "max_frames": args.max_frames,
                           "runs": args.runs, "gaps": args.gaps, "min_baseline_m": args.min_baseline,
                           "tum_read": TUM_READ, "tum_pairs": {k: len(v) for k, v in pairs.items()},
                           "odometry": OdometryConfig().model_dump()},
              "tum": {"variants": variants, "compare": cmp, "depth_sweep": sweep,
                      "verdict": verdict(variants, cmp, DEFAULT_VARIANT)},
              "replica": rep}
    md = "\n\n".join([tum_table(variants, cmp, DEFAULT_VARIANT),
                      sweep_table("TUM fr1/rpy", sweep, TUM_DEPTH_SCALE),
                      replica_table(rep),
                      sweep_table("Replica room0", rep["depth_sweep"], float(rep["cam_params"]["scale"]))])
    details = (f": TUM fr1/rpy at 1/{args.downscale:g}, {args.runs} odometry runs per variant, consistency over "
               f"{len(pairs['adjacent'])} adjacent frame pairs (gaps {args.gaps}) and {len(pairs['wide'])} pairs at "
               f"least {args.min_baseline:g} m apart; Replica room0 at 1/{args.replica_downscale:g}")
    write_results(args.out, "calibration", argv, details, md, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
