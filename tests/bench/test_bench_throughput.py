"""bench.throughput: the pairs the compositing kernels evaluate, counted from a render's saved state, agree with a
per-pair emulation of the kernels' footprint bounds; and a quick run (the tiny scene, against HEAD in a git worktree
when git is there) writes the JSON with positive, finite figures for both trees and the roofline. No timing is
asserted: speed is a benchmark figure."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from bench.rasterizer import make_scene
from bench.throughput import CENSUS_KEYS, FWD_FLOPS, BWD_FLOPS, count_pairs, main
from gausslite.render import rasterize
from tests._git import has_git

pytestmark = pytest.mark.integration


def _row_bounds(lo, hi, a, b):
    """The kernels' clamp of the footprint bounds ``[lo, hi]`` to the tile's ``[a, b]`` (tile_rows / row_span)."""
    first = a if not lo > a else (int(lo) if lo <= b else b + 1)
    last = b if not hi < b else (int(hi) if hi >= a else a - 1)
    return first, last


def _lanes_by_pair(gdata, gids, start, end, ts, tiles_x, width, height):
    """The SIMD kernels' lanes over every entry of every tile, one entry and row at a time in float32."""
    f32, n = np.float32, 0
    for t in range(len(start)):
        x0, y0 = (t % tiles_x) * ts, (t // tiles_x) * ts
        x1, y1 = min(x0 + ts, width) - 1, min(y0 + ts, height) - 1
        for j in range(start[t], end[t]):
            r = gdata[gids[j]]
            uu, vv, ks, k1, k0 = f32(r[0] + r[10]), f32(r[1] + r[11]), r[13], r[14], r[15]
            with np.errstate(all="ignore"):
                e = f32(np.sqrt(f32(k0 / k1))) + f32(0.5)
            ya, yb = _row_bounds(np.ceil(vv - e), np.floor(vv + e), y0, y1)
            for py in range(ya, yb + 1):
                dyr = f32(vv - f32(py))
                cx, half2 = f32(uu + f32(ks * dyr)), f32(k0 - f32(f32(k1 * dyr) * dyr))
                if half2 < 0:
                    continue
                hw = f32(np.sqrt(half2)) + f32(0.5)
                xa, xb = _row_bounds(np.ceil(f32(cx - hw)), np.floor(f32(cx + hw)), x0, x1)
                if xa <= xb:
                    n += 8 * (((xb - x0) >> 3) - ((xa - x0) >> 3) + 1)
    return n


def test_pairs_counted_from_the_saved_state_match_the_kernels_bounds():
    params, K = make_scene(150, 40, 30, seed=3)
    out = rasterize(*params, K=K, width=40, height=30, viewmat=np.eye(4), num_threads=1)
    c = count_pairs(out)
    assert c is not None and set(c) == {"tile_pairs", "entries", "lane_pairs_fwd", "lane_pairs_bwd"}
    node = out.alpha.grad_fn
    gdata, gids, tile_start = (t.detach().numpy() for t in node.saved_tensors[:3])
    width, height, ts, tiles_x, _, _ = node.dims
    start = tile_start.astype(np.int64)
    end = np.append(start[1:], len(gids))
    # sparse random Gaussians: no tile saturates, so the forward visits every entry of every list
    assert c["lane_pairs_fwd"] == _lanes_by_pair(gdata, gids, start, end, ts, tiles_x, width, height) > 0
    assert 0 < c["lane_pairs_bwd"] <= c["lane_pairs_fwd"] <= c["tile_pairs"]
    out.alpha.sum().backward()  # the saved state is freed: nothing to count
    assert count_pairs(out) is None


def test_the_census_counts_each_listed_pair_once_and_the_pairs_a_stopped_pixel_skips():
    """Sparse Gaussians: every listed pair is counted, the passing ones are those whose float64 alpha is >= 1/255 (to
    boundary rounding), no pixel stops. Opaque ones: pixels stop, and the pairs after their stop are the listed pairs
    neither before it nor at it."""
    params, K = make_scene(150, 40, 30, seed=3)
    out = rasterize(*params, K=K, width=40, height=30, viewmat=np.eye(4), num_threads=1)
    c = count_pairs(out, census=True)
    assert set(CENSUS_KEYS) <= set(c)
    node = out.alpha.grad_fn
    gdata, gids, tile_start = (t.detach().numpy().astype(np.float64) if i == 0 else t.detach().numpy()
                               for i, t in enumerate(node.saved_tensors[:3]))
    width, height, ts, tiles_x, _, _ = node.dims
    end = np.append(tile_start[1:], len(gids))
    listed = passing = 0
    for t in range(len(tile_start)):
        x0, y0 = (t % tiles_x) * ts, (t // tiles_x) * ts
        py, px = np.mgrid[y0:min(y0 + ts, height), x0:min(x0 + ts, width)]
        for j in range(tile_start[t], end[t]):
            r = gdata[gids[j]]
            dx, dy = r[0] + r[10] - px, r[1] + r[11] - py
            power = -0.5 * (r[2] * dx * dx + r[4] * dy * dy) - r[3] * dx * dy
            alpha = np.minimum(0.99, r[5] * np.exp(power))
            listed += px.size
            passing += int(((power <= 0) & (alpha >= 1 / 255)).sum())
    assert c["listed"] == listed == c["tile_pairs"] and abs(c["passing"] - passing) <= 0.01 * passing
    assert c["after_stop"] == 0 and c["contributing"] == c["passing"] > 0
    dense, K = make_scene(1500, 40, 30, seed=4)
    with torch.no_grad():
        dense[3].add_(6.0)
        dense[2].add_(1.5)
    d = count_pairs(rasterize(*dense, K=K, width=40, height=30, viewmat=np.eye(4), num_threads=1), census=True)
    assert d["after_stop"] > 0 and 0 < d["contributing"] < d["passing"] <= d["listed"]
    assert d["contributing"] + d["after_stop"] <= d["listed"]


def _positive(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and x > 0


def test_quick_run_writes_both_trees_and_the_roofline(tmp_path):
    out = tmp_path / "throughput.json"
    against = ["--against", "HEAD", "--cases", "1k_64x48,keyframe_agent"] if has_git() else []
    main(["--quick", "--work", str(tmp_path / "work"), "--out", str(out), *against])
    res = json.loads(out.read_text())
    assert res["provenance"]["command"].startswith("python -m bench.throughput --quick")
    assert out.with_suffix(".md").read_text().count("| 1k_64x48 |") >= 1
    rf = res["roofline"]
    assert all(_positive(rf[k]) for k in ("fma_gflops_1", "fma_gflops_all", "pairs_per_s_1", "pairs_per_s_all"))
    assert rf["flops_per_pair"] == {"forward": FWD_FLOPS, "backward": BWD_FLOPS, "total": FWD_FLOPS + BWD_FLOPS}
    trees = ["this", "that"] if against else ["this"]
    assert res["trees"]["this"]["gausslite_file"] == "gausslite/__init__.py"
    if against:  # the other tree's workers imported the worktree's gausslite
        assert res["trees"]["that"]["gausslite_file"].startswith("TMP/") and len(res["trees"]["that"]["commit"]) == 40
    size, kf = res["cases"]["1k_64x48"], res["cases"]["keyframe_agent"]
    for t in trees:
        b = size[t]
        assert (b["width"], b["height"]) == (64, 48) and b["n_gaussians"] > 0
        assert all(_positive(b[k]) for k in ("it_per_s", "full_it_per_s", "roi_it_per_s"))
        assert b["config"]["exposure_comp"] and b["config"]["pose_refine"]  # the hand-held profile
        ras = b["raster"]
        assert all(_positive(ras[k]) for k in ("fwd_bwd_s", "tile_pairs", "lane_pairs_fwd", "pairs_per_s",
                                                "gflops", "roofline_fraction"))
        assert _positive(kf[t]["it_per_s"]) and kf[t]["iters"] and kf[t]["n_gaussians"] > 0
    if against:
        assert all(_positive(v) for v in size["ratio"].values()) and "it_per_s" in size["ratio"]
        assert _positive(kf["ratio"]["it_per_s"])
    else:
        assert "2k_128x96" in res["cases"]
