"""Tests of the SLAM-like pose error model (``gausslite.datasets.trajectory.perturb_trajectory``)."""

from __future__ import annotations

import numpy as np
import pytest

from gausslite.datasets.trajectory import (
    JITTER_SHARE, POSE_ERROR_LEVELS, ate_rmse, parse_pose_error_level, perturb_trajectory, pose_error_stats, rpe,
)
from gausslite.synthetic import make_trajectories


@pytest.fixture(scope="module")
def walk() -> np.ndarray:
    return make_trajectories(200, 0, "walk")["agent_a"]


def test_levels_parse() -> None:
    assert parse_pose_error_level("exact") == (0.0, 0.0)
    assert parse_pose_error_level("1cm_0.5deg") == (0.01, 0.5)
    assert parse_pose_error_level("2.5cm_1deg") == pytest.approx((0.025, 1.0))
    assert set(POSE_ERROR_LEVELS) == {"exact", "1cm_0.5deg", "3cm_1.5deg"}
    for bad in ("1cm", "1mm_0.5deg", "-1cm_1deg", ""):
        with pytest.raises(ValueError):
            parse_pose_error_level(bad)


@pytest.mark.parametrize("level", ["1cm_0.5deg", "3cm_1.5deg"])
def test_realised_error_is_the_level(walk: np.ndarray, level: str) -> None:
    ate, rot = POSE_ERROR_LEVELS[level]
    for seed in range(3):
        est = perturb_trajectory(walk, level, seed)
        st = pose_error_stats(est, walk)
        assert st["ate_m"] == pytest.approx(ate, rel=1e-6) and st["rot_rmse_deg"] == pytest.approx(rot, rel=1e-6)
        assert st["trans_rmse_m"] > st["ate_m"]  # unaligned: the map's misplacement exceeds the aligned ATE
        assert np.array_equal(est[0], walk[0])  # the first frame fixes the gauge
        R = est[:, :3, :3]
        assert np.allclose(R @ np.transpose(R, (0, 2, 1)), np.eye(3), atol=1e-9)
        assert np.allclose(est[:, 3], [0, 0, 0, 1])


def test_seeded_and_exact(walk: np.ndarray) -> None:
    a = perturb_trajectory(walk, "1cm_0.5deg", 7)
    assert np.array_equal(a, perturb_trajectory(walk, "1cm_0.5deg", 7))
    assert not np.allclose(a, perturb_trajectory(walk, "1cm_0.5deg", 8))
    ex = perturb_trajectory(walk, "exact", 7)
    assert np.array_equal(ex, walk) and ex is not walk
    assert ate_rmse(perturb_trajectory(walk, (0.02, 1.0), 1), walk) == pytest.approx(0.02, rel=1e-6)


def test_drift_grows_along_the_path_and_jitter_is_per_frame() -> None:
    line = np.repeat(np.eye(4)[None], 400, axis=0)
    line[:, 0, 3] = np.linspace(0.0, 8.0, 400)  # 8 m straight ahead (camera axes along the world's)
    early, late, rpe1 = [], [], []
    for seed in range(8):
        est = perturb_trajectory(line, "3cm_1.5deg", seed)
        d = np.linalg.norm(est[:, :3, 3] - line[:, :3, 3], axis=1)
        early.append(d[1:100].mean())
        late.append(d[300:].mean())
        rpe1.append(rpe(est, line, delta=1)["trans_rmse_m"])
    assert np.mean(late) > 3.0 * np.mean(early)  # a random walk in the path: error grows along it
    # consecutive frames differ by about two independent jitters (RMS norm JITTER_SHARE * ATE each) plus a step of drift
    jitter = JITTER_SHARE * 0.03
    assert 0.7 * np.sqrt(2) * jitter < np.mean(rpe1) < 2.0 * np.sqrt(2) * jitter


def test_rejects_bad_input() -> None:
    still = np.repeat(np.eye(4)[None], 10, axis=0)
    with pytest.raises(ValueError):
        perturb_trajectory(still, "1cm_0.5deg", 0)  # no path to drift along
    with pytest.raises(ValueError):
        perturb_trajectory(np.eye(4)[None], "1cm_0.5deg", 0)
    with pytest.raises(ValueError):
        perturb_trajectory(np.eye(4), "1cm_0.5deg", 0)
    with pytest.raises(ValueError):
        perturb_trajectory(np.repeat(np.eye(4)[None], 3, axis=0), "big", 0)
