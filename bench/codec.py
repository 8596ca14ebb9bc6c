"""Wire codec benchmark: bytes per Gaussian, reconstruction error, encode/decode throughput.

Compares the quantised and lossless modes of :mod:`gausslite.wire` (and a few variants) on a
synthetic room-scale map against the 56-byte-per-Gaussian standard 3DGS PLY (14 float32: xyz,
f_dc×3, opacity, scale×3, rot×4): bytes on the wire per Gaussian and as % of the full map.

Usage::

    python -m bench.codec [--quick] [--n 100000] [--out bench/results/codec.json]
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from gausslite.wire import LOSSLESS, GaussianArrays, QuantConfig, assemble, encode_subset

from bench._results import write_json

PLY_BYTES_PER_GAUSSIAN = 56
RESULTS = Path(__file__).resolve().parent / "results"


def synthetic_room(n: int, seed: int = 0, *, roi_fraction: float = 0.07,
                   roi_center: tuple[float, float, float] = (5.0, 2.0, 0.9),
                   order: str = "tiles", offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
                   ) -> GaussianArrays:
    """A synthetic room-scale Gaussian map (8 m × 6 m × 3 m).

    Means lie on the floor, ceiling, walls and five furniture boxes (area-weighted, 4 mm normal
    noise); scales 3–30 mm, flattened along the surface normal; random rotations; opacity logits
    mostly high; colours per surface plus texture noise; κ = 0 except an ROI cluster (a 0.8 m ball
    around ``roi_center``, about ``roi_fraction`` of N) with κ ~ U{20..400} and active = True.

    Args:
        n: number of Gaussians.  seed: RNG seed.
        order: "tiles" mimics keyframe-wise seeding (0.5 m tiles in random order, random inside a
            tile); "random" is a uniformly random permutation (worst case for compression).
        offset: added to every mean (metres).

    Returns:
        GaussianArrays with N = n.
    """
    rng = np.random.default_rng(seed)
    L, W, H = 8.0, 6.0, 3.0
    # planes: (origin, u, v, normal) rectangles
    rects = [
        ((0, 0, 0), (L, 0, 0), (0, W, 0)), ((0, 0, H), (L, 0, 0), (0, W, 0)),
        ((0, 0, 0), (L, 0, 0), (0, 0, H)), ((0, W, 0), (L, 0, 0), (0, 0, H)),
        ((0, 0, 0), (0, W, 0), (0, 0, H)), ((L, 0, 0), (0, W, 0), (0, 0, H)),
    ]
    for cx, cy, sx, sy, sz in [(2, 1.5, 1.6, 0.9, 0.75), (5, 2, 1.2, 0.8, 0.5), (6.5, 5, 1.5, 0.4, 2),
                               (1, 5, 0.5, 0.5, 1.2), (3.5, 4, 2.0, 1.0, 0.45)]:
        x0, y0 = cx - sx / 2, cy - sy / 2
        rects += [((x0, y0, sz), (sx, 0, 0), (0, sy, 0)),
                  ((x0, y0, 0), (sx, 0, 0), (0, 0, sz)), ((x0, y0 + sy, 0), (sx, 0, 0), (0, 0, sz)),
                  ((x0, y0, 0), (0, sy, 0), (0, 0, sz)), ((x0 + sx, y0, 0), (0, sy, 0), (0, 0, sz))]
    o = np.array([r[0] for r in rects], float)
    u = np.array([r[1] for r in rects], float)
    v = np.array([r[2] for r in rects], float)
    nrm = np.cross(u, v)
    area = np.linalg.norm(nrm, axis=1)
    nrm /= area[:, None]
    face = rng.choice(len(rects), size=n, p=area / area.sum())
    a, b = rng.random(n), rng.random(n)
    means = o[face] + a[:, None] * u[face] + b[:, None] * v[face]
    means += nrm[face] * rng.normal(0, 0.004, n)[:, None]
    base = rng.uniform(0.15, 0.9, (len(rects), 3))
    colors = np.clip(base[face] + rng.normal(0, 0.05, (n, 3)), 0, 1)
    log_scales = np.log(rng.uniform(0.003, 0.03, (n, 3)))
    log_scales[:, 2] = np.log(rng.uniform(0.001, 0.004, n))
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    opacity = np.where(rng.random(n) < 0.85, rng.normal(3.0, 1.5, n), rng.normal(-2.0, 1.5, n))
    roi = np.zeros(n, bool)
    n_roi = int(round(roi_fraction * n))
    if n_roi:
        d = rng.normal(size=(n_roi, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        pts = np.asarray(roi_center) + d * 0.4 * rng.random(n_roi)[:, None] ** (1 / 3)
        idx = rng.choice(n, n_roi, replace=False)
        means[idx] = pts
        roi[idx] = True
        log_scales[idx] -= 0.7  # ROI Gaussians are finer
    kappa = np.where(roi, rng.integers(20, 401, n), 0).astype(np.int64)
    if order == "tiles":
        tile = np.floor(means / 0.5).astype(np.int64)
        tid = np.unique(tile, axis=0, return_inverse=True)[1].reshape(-1)
        rank = rng.permutation(tid.max() + 1)[tid]
        perm = np.lexsort((rng.random(n), rank))
    elif order == "random":
        perm = rng.permutation(n)
    else:
        raise ValueError("order must be 'tiles' or 'random'")
    g = GaussianArrays(means=(means + np.asarray(offset))[perm], quats=quats[perm],
                       log_scales=log_scales[perm], opacity_logits=opacity[perm],
                       colors=colors[perm], kappa=kappa[perm], active=roi[perm])
    return g


def field_errors(ref: GaussianArrays, out: GaussianArrays) -> dict:
    """Per-field reconstruction errors (max and mean).

    means in mm; quats as rotation angle in degrees (sign-invariant, after normalisation);
    log_scales in log units (and as relative scale error); opacity in sigmoid space; colours in RGB
    units; κ / active as exact-match flags.
    """
    def mm(x):
        return {"max": float(np.max(x)) if x.size else 0.0,
                "mean": float(np.mean(x)) if x.size else 0.0}
    qa = ref.quats.astype(np.float64)
    qa /= np.linalg.norm(qa, axis=1, keepdims=True)
    qb = out.quats.astype(np.float64)
    qb /= np.linalg.norm(qb, axis=1, keepdims=True)
    qb *= np.where((qa * qb).sum(1) < 0, -1.0, 1.0)[:, None]
    # rotation angle 4·atan2(|qa - qb|, |qa + qb|) (numerically stable for tiny angles)
    ang = 4 * np.arctan2(np.linalg.norm(qa - qb, axis=1), np.linalg.norm(qa + qb, axis=1))
    ds = np.abs(out.log_scales.astype(np.float64) - ref.log_scales)
    sig = lambda x: 1 / (1 + np.exp(-x.astype(np.float64)))  # noqa: E731
    return {
        "means_mm": mm(np.abs(out.means.astype(np.float64) - ref.means) * 1e3),
        "quat_deg": mm(np.degrees(ang)),
        "log_scale": mm(ds),
        "scale_rel": mm(np.expm1(ds)),
        "opacity": mm(np.abs(sig(out.opacity_logits) - sig(ref.opacity_logits))),
        "colors": mm(np.abs(out.colors.astype(np.float64) - ref.colors)),
        "kappa_exact": bool(np.array_equal(out.kappa, ref.kappa)),
        "active_exact": bool(np.array_equal(out.active, ref.active)),
    }


def run_case(name: str, g: GaussianArrays, quant: QuantConfig, repeats: int,
             chunk_gaussians: int = 65536) -> dict:
    """Encode/decode ``g`` ``repeats`` times; returns sizes, best timings and errors."""
    enc_t, dec_t = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        chunks = encode_subset(g, "bench", 1, quant=quant, chunk_gaussians=chunk_gaussians)
        t1 = time.perf_counter()
        out, meta = assemble(chunks)
        t2 = time.perf_counter()
        enc_t.append(t1 - t0)
        dec_t.append(t2 - t1)
    n = len(g)
    wire = sum(map(len, chunks))
    return {
        "case": name, "n": n, "chunks": len(chunks), "wire_bytes": wire,
        "bytes_per_gaussian": wire / n, "vs_ply": wire / (n * PLY_BYTES_PER_GAUSSIAN),
        "encode_s": min(enc_t), "decode_s": min(dec_t),
        "encode_mgauss_s": n / min(enc_t) / 1e6, "decode_mgauss_s": n / min(dec_t) / 1e6,
        "quant": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(quant).items()},
        "errors": field_errors(g, out),
    }


def main(argv: Optional[list[str]] = None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m bench.codec", description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="20k Gaussians, 1 repeat")
    ap.add_argument("--n", type=int, default=100_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=RESULTS / "codec.json")
    args = ap.parse_args(argv)
    n = 20_000 if args.quick else args.n
    reps = 1 if args.quick else args.repeats
    torch.set_num_threads(1)

    full = synthetic_room(n, seed=0)
    full_rand = synthetic_room(n, seed=0, order="random")
    roi = full.take(full.active)
    cases = [
        ("quantised (default)", full, QuantConfig()),
        ("quantised, random order", full_rand, QuantConfig()),
        ("quantised, no shuffle", full, QuantConfig(shuffle=False)),
        ("quantised, zstd 19", full, QuantConfig(zstd_level=19)),
        ("quantised, quat 10 bit", full, QuantConfig(quat_bits=10)),
        ("quantised, mean step 1 mm", full, QuantConfig(mean_step=1e-3)),
        ("lossless", full, LOSSLESS),
        ("lossless, no shuffle", full, QuantConfig(lossless=True, shuffle=False)),
        ("ROI subset, quantised", roi, QuantConfig()),
        ("ROI subset, mean step 1 mm", roi, QuantConfig(mean_step=1e-3)),
        ("ROI subset, lossless", roi, LOSSLESS),
    ]
    rows = [run_case(name, g, q, reps) for name, g, q in cases]
    full_ply = n * PLY_BYTES_PER_GAUSSIAN
    for r in rows:
        r["pct_of_full_map_ply"] = 100.0 * r["wire_bytes"] / full_ply

    print(f"synthetic room, N = {n} (ROI subset {len(roi)} = {100 * len(roi) / n:.1f} %), "
          f"PLY baseline {PLY_BYTES_PER_GAUSSIAN} B/G")
    hdr = (f"{'case':26s} {'B/G':>6s} {'%PLY':>6s} {'%map':>6s} {'enc MG/s':>8s} {'dec MG/s':>8s}"
           f" {'mean mm max':>11s} {'quat° max':>9s} {'opac max':>8s} {'rgb max':>7s}")
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        e = r["errors"]
        print(f"{r['case']:26s} {r['bytes_per_gaussian']:6.2f} {100 * r['vs_ply']:6.1f} "
              f"{r['pct_of_full_map_ply']:6.2f} {r['encode_mgauss_s']:8.2f} "
              f"{r['decode_mgauss_s']:8.2f} {e['means_mm']['max']:11.4f} "
              f"{e['quat_deg']['max']:9.4f} {e['opacity']['max']:8.5f} {e['colors']['max']:7.5f}")
    result = {
        "benchmark": "codec", "n": n, "quick": bool(args.quick), "repeats": reps,
        "ply_bytes_per_gaussian": PLY_BYTES_PER_GAUSSIAN, "roi_gaussians": len(roi),
        "machine": {"python": platform.python_version(), "numpy": np.__version__,
                    "processor": platform.processor() or platform.machine()},
        "cases": rows,
    }
    write_json(args.out, result, "codec", argv)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
