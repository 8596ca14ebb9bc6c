"""Contracts of relevance-driven seeding (paper III-C): SB counts, SIS grid, GFD weighting, s0."""

import math

import numpy as np
import pytest

from gausslite.camera import Intrinsics
from gausslite.mapping.seeding import (
    local_median_nn_distance,
    seed_points,
    select_seeds,
    sobel_magnitude,
    stratified_choice,
    weighted_choice,
)


def _masks(H=60, W=80):
    valid = np.ones((H, W), bool)
    valid[:, :3] = False  # a few invalid-depth columns
    roi = np.zeros((H, W), bool)
    roi[20:40, 30:60] = True  # 600 pixels
    return valid, roi


def test_uniform_draws_only_valid_pixels_without_replacement():
    valid, roi = _masks()
    rng = np.random.default_rng(0)
    sel = select_seeds(valid, 500, rng, relevance=roi)
    assert sel.pixels.size == 500
    assert np.unique(sel.pixels).size == 500
    assert valid.ravel()[sel.pixels].all()
    # without SB the ROI share follows the ROI's pixel share (binomial, generous bound)
    share = roi[valid].mean()
    assert abs(sel.is_roi.mean() - share) < 0.06


@pytest.mark.parametrize("rho", [0.2, 0.4, 0.75])
def test_sb_counts_per_pool(rho):
    valid, roi = _masks()
    sel = select_seeds(valid, 400, np.random.default_rng(1), relevance=roi, sb=True, rho=rho)
    n_roi = math.floor(rho * 400)
    assert sel.n_roi_requested == n_roi
    assert int(sel.is_roi.sum()) == n_roi
    assert roi.ravel()[sel.pixels[sel.is_roi]].all()
    assert not roi.ravel()[sel.pixels[~sel.is_roi]].any()
    assert sel.pixels.size == 400


def test_sb_roi_shortfall_goes_to_background():
    valid, _ = _masks()
    roi = np.zeros_like(valid)
    roi[10:15, 10:20] = True  # 50 ROI pixels only
    sel = select_seeds(valid, 400, np.random.default_rng(2), relevance=roi, sb=True, rho=0.5)
    assert int(sel.is_roi.sum()) == 50  # every ROI pixel taken
    assert sel.n_roi_shortfall == 150
    assert int((~sel.is_roi).sum()) == 350  # 200 + the 150 shortfall
    assert np.unique(sel.pixels).size == sel.pixels.size


def test_sb_invalid_roi_pixels_never_drawn():
    valid, roi = _masks()
    valid[20:40, 30:45] = False  # half the ROI has no depth
    sel = select_seeds(valid, 300, np.random.default_rng(3), relevance=roi, sb=True, rho=0.9)
    assert valid.ravel()[sel.pixels].all()


def test_sis_one_sample_per_grid_cell():
    H, W = 60, 80
    cand = np.ones((H, W), bool)
    n = 48  # g = 7 → 49 cells, 48 kept
    pix = stratified_choice(cand, n, np.random.default_rng(4))
    assert pix.size == n
    g = math.ceil(math.sqrt(n))
    v, u = np.divmod(pix, W)
    cells = (v * g // H) * g + (u * g // W)
    assert np.unique(cells).size == pix.size  # never two samples in one cell


def test_sis_cells_without_candidates_give_nothing():
    H, W = 60, 80
    cand = np.zeros((H, W), bool)
    cand[:, :40] = True  # left half only
    pix = stratified_choice(cand, 100, np.random.default_rng(5))
    assert pix.size == 50  # 10x10 grid, 5 columns of cells have candidates
    assert cand.ravel()[pix].all()


def test_sis_is_more_even_than_uniform():
    """Stratification removes clumping: the largest empty region is smaller on average."""
    H, W = 120, 160
    cand = np.ones((H, W), bool)
    rng = np.random.default_rng(6)
    def coverage_gap(pix):
        v, u = np.divmod(pix, W)
        pts = np.stack([v, u], 1).astype(float)
        grid = np.stack(np.meshgrid(np.arange(0, H, 4), np.arange(0, W, 4), indexing="ij"), -1).reshape(-1, 2)
        d = np.sqrt(((grid[:, None] - pts[None]) ** 2).sum(-1)).min(1)
        return d.max()
    strat = np.mean([coverage_gap(stratified_choice(cand, 100, rng)) for _ in range(5)])
    unif = np.mean([coverage_gap(weighted_choice(np.arange(H * W), 100, rng)) for _ in range(5)])
    assert strat < 0.8 * unif


def test_gfd_prefers_edges_statistically():
    """Draws ∝ E + ε: within a cell, an edge pixel is chosen far more often than a flat one."""
    H, W = 40, 40
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:, 20:] = 255  # one vertical edge at u = 19/20
    E = sobel_magnitude(rgb)
    assert E[:, 19:21].min() > 1.0 and E[:, :15].max() == 0.0
    valid = np.ones((H, W), bool)
    rng = np.random.default_rng(7)
    hits = 0
    trials = 200
    for _ in range(trials):
        sel = select_seeds(valid, 4, rng, rgb=rgb, sb=True, sis=True, gfd=True, rho=0.0, gfd_eps=0.05)
        u = sel.pixels % W
        hits += int(np.isin(u, [18, 19, 20, 21]).sum())
    # 4 cells (2x2): the two cells touching the edge draw an edge column with prob
    # ≈ (4*40*E_edge) / (4*40*E_edge + 16*40*eps) ≈ 0.99 each → ~2 of 4 seeds per draw
    assert hits / trials > 1.8
    # and without GFD, edge columns are hit only ~4/20 of the time in those cells
    hits_u = 0
    for _ in range(trials):
        sel = select_seeds(valid, 4, rng, rgb=rgb, sb=True, sis=True, gfd=False, rho=0.0)
        hits_u += int(np.isin(sel.pixels % W, [18, 19, 20, 21]).sum())
    assert hits_u / trials < 0.7


def test_gfd_weighted_choice_matches_probabilities():
    pool = np.arange(4)
    w = np.array([1.0, 1.0, 1.0, 7.0])
    rng = np.random.default_rng(8)
    counts = np.bincount([weighted_choice(pool, 1, rng, w)[0] for _ in range(4000)], minlength=4)
    assert abs(counts[3] / 4000 - 0.7) < 0.03


def test_gfd_requires_rgb():
    valid, roi = _masks()
    with pytest.raises(ValueError, match="rgb"):
        select_seeds(valid, 10, np.random.default_rng(0), gfd=True)


def test_relevance_shape_checked():
    valid, _ = _masks()
    with pytest.raises(ValueError, match="relevance"):
        select_seeds(valid, 10, np.random.default_rng(0), relevance=np.zeros((3, 3), bool))


def test_local_median_nn_distance_on_a_grid():
    g = np.stack(np.meshgrid(np.arange(10), np.arange(10), [0.0], indexing="ij"), -1).reshape(-1, 3) * 0.05
    s0 = local_median_nn_distance(g, k=3)
    # interior points: 4 neighbours at 5 cm → median of 3 nearest = 5 cm
    assert np.allclose(np.median(s0), 0.05)
    assert local_median_nn_distance(g[:1]).tolist() == [1e-2]


def test_seed_points_backprojects_with_pose():
    intr = Intrinsics(100.0, 100.0, 9.5, 7.5, 20, 16)
    depth = np.full((16, 20), 2.0, np.float32)
    rgb = np.zeros((16, 20, 3), np.uint8)
    rgb[7, 9] = (255, 0, 0)
    c2w = np.eye(4)
    c2w[:3, 3] = [1.0, 2.0, 3.0]
    pts, cols = seed_points(np.array([7 * 20 + 9]), depth, rgb, intr, c2w)
    np.testing.assert_allclose(pts[0], [1.0 + (9 - 9.5) / 100 * 2, 2.0 + (7 - 7.5) / 100 * 2, 5.0])
    np.testing.assert_allclose(cols[0], [1.0, 0.0, 0.0])
