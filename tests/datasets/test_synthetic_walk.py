"""Tests of the synthetic scene's hand-held walk (``make_trajectories(kind="walk")``) and its optional sensor error
model (``gausslite.synthetic.sensor``, ``make_scene(sensor_noise="realistic")``)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from gausslite.synthetic import (
    AGENTS, DEPTH_SCALE, WALK_FPS, WALK_PATH_M, SensorErrorModel, build_default_scene, camera_rays, default_intrinsics,
    make_scene, make_trajectories, pose_at, render, sensor_model,
)
from gausslite.synthetic.sensor import colour_with_errors, depth_with_errors, exposure_track, render_with_errors

SEED = 4
#: frames of a walk at 0.40 m/s at the walk's 30 fps
WALK_FRAMES = 525
DESK_TOP = np.array([-0.2, 0.55, 0.78])


def _path_length(P: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1).sum())


def test_walk_length_speed_and_free_space() -> None:
    trajs = make_trajectories(WALK_FRAMES, SEED, "walk")
    scene = build_default_scene(SEED)
    assert set(trajs) == set(AGENTS)
    for agent, P in trajs.items():
        length = _path_length(P)
        assert abs(length - WALK_PATH_M) < 0.3, f"{agent}: path {length:.2f} m"
        speed = length / ((WALK_FRAMES - 1) / WALK_FPS)
        assert 0.3 <= speed <= 0.5, f"{agent}: {speed:.2f} m/s is not walking speed"
        pos = P[:, :3, 3]
        assert np.linalg.norm(pos[-1] - pos[0]) < 0.01  # back at the start
        steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
        assert steps[:3].max() < 0.2 * steps.max()  # starts from rest
        assert np.all(pos > scene.room.lo + 0.3) and np.all(pos < scene.room.hi - 0.3)
        for o in scene.objects:
            local = (pos - o.center) @ o.rotation
            assert not np.any(np.all(np.abs(local) <= o.size / 2 + 0.2, axis=1)), f"{agent} inside {o.label}"
        assert np.allclose(np.einsum("nij,nik->njk", P[:, :3, :3], P[:, :3, :3]), np.eye(3), atol=1e-9)


def test_walk_revisits_with_other_headings_and_watches_the_desk() -> None:
    for agent, P in make_trajectories(WALK_FRAMES, SEED, "walk").items():
        pos, fwd = P[:, :3, 3], P[:, :3, 2]
        n = len(P)
        early, late = np.arange(0, int(0.45 * n)), np.arange(int(0.55 * n), n)
        dist = np.linalg.norm(pos[late][:, None] - pos[early][None], axis=-1)
        assert dist.min(axis=1).max() < 0.3, f"{agent}: a second-lap pose is far from every first-lap one"
        assert dist.min(axis=1).mean() < 0.15
        nearest = early[dist.argmin(axis=1)]
        turn = np.degrees(np.arccos(np.clip(np.sum(fwd[late] * fwd[nearest], axis=1), -1.0, 1.0)))
        assert np.median(turn) > 5.0, f"{agent}: the second lap looks the same way as the first"
        to_desk = DESK_TOP - pos
        along = np.sum(to_desk * fwd, axis=1)
        off_axis = np.linalg.norm(to_desk - along[:, None] * fwd, axis=1)
        assert np.mean(off_axis < 0.4) > 0.75, f"{agent}: the desk is off the optical axis too often"
        rate = np.degrees(np.arccos(np.clip(np.sum(fwd[1:] * fwd[:-1], axis=1), -1.0, 1.0))) * WALK_FPS
        assert 3.0 < rate.mean() < 60.0  # hand-held: turning, but not whipping


def _median_turn_rate(P: np.ndarray, fps: float) -> float:
    """Median rotation (degrees per second) between consecutive poses."""
    from scipy.spatial.transform import Rotation

    rel = np.einsum("nji,njk->nik", P[:-1, :3, :3], P[1:, :3, :3])
    return float(np.median(np.degrees(Rotation.from_matrix(rel).magnitude())) * fps)


def test_scan_walk_turns_at_tum_rate_on_the_same_path() -> None:
    walk = make_trajectories(WALK_FRAMES, SEED, "walk")
    scan = make_trajectories(WALK_FRAMES, SEED, "scan_walk")
    for agent in AGENTS:
        # the same positions: only where the camera looks changes
        assert np.allclose(scan[agent][:, :3, 3], walk[agent][:, :3, 3])
        assert np.allclose(np.einsum("nij,nkj->nik", scan[agent][:, :3, :3], scan[agent][:, :3, :3]),
                           np.eye(3), atol=1e-9)
        assert _median_turn_rate(walk[agent], WALK_FPS) < 25.0
        assert 35.0 < _median_turn_rate(scan[agent], WALK_FPS) < 70.0  # TUM fr1/rpy: 52 degrees/s
        # at rest at both ends, as the walk
        for i in (0, -1):
            assert np.allclose(scan[agent][i], walk[agent][i], atol=1e-9)
    again = make_trajectories(WALK_FRAMES, SEED, "scan_walk")
    assert all(np.array_equal(again[a], scan[a]) for a in AGENTS)


def test_walk_is_deterministic_per_seed() -> None:
    a = make_trajectories(60, SEED, "walk")
    b = make_trajectories(60, SEED, "walk")
    c = make_trajectories(60, SEED + 1, "walk")
    for agent in AGENTS:
        assert np.array_equal(a[agent], b[agent])
        assert not np.allclose(a[agent], c[agent])
    with pytest.raises(ValueError):
        make_trajectories(60, SEED, "walk", fps=0.0)
    with pytest.raises(ValueError):
        make_trajectories(60, SEED, "stroll")


def test_pose_at_interpolates_between_frames() -> None:
    P = make_trajectories(20, SEED, "walk")["agent_a"]
    assert np.allclose(pose_at(P, 7.0), P[7])
    mid = pose_at(P, 7.5)
    assert np.allclose(mid[:3, 3], 0.5 * (P[7, :3, 3] + P[8, :3, 3]))
    r = mid[:3, :3]
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-9)
    assert np.allclose(pose_at(P, -3.0), P[0]) and np.allclose(pose_at(P, 99.0), P[-1])


def _still(P: np.ndarray, i: int) -> np.ndarray:
    """A trajectory that stands still at ``P[i]`` (no blur, no shutter shear)."""
    return np.repeat(P[i][None], 5, axis=0)


def test_depth_noise_follows_the_documented_model() -> None:
    scene = build_default_scene(SEED)
    intr = default_intrinsics(160, 120)
    c2w = make_trajectories(40, SEED, "walk")["agent_a"][20]
    exact = render(scene, intr, c2w)
    model = SensorErrorModel()
    depth = depth_with_errors(exact, intr, c2w, model, np.random.default_rng(0))
    z = exact.depth
    valid = depth > 0
    holes = ~valid
    assert 0.01 < holes.mean() < 0.25
    assert np.all(holes[(z < model.depth_min_m) | (z > model.depth_max_m)])
    # the residual of the kept pixels, divided by the documented sigma (angle term left out: moderate angles)
    _, d = camera_rays(intr, c2w)
    cos = np.abs(np.sum(d / np.linalg.norm(d, axis=1, keepdims=True) * exact.normal.reshape(-1, 3), axis=1))
    moderate = (cos.reshape(z.shape) > np.cos(np.deg2rad(45.0))) & valid
    sigma = model.depth_sigma_a + model.depth_sigma_b * (z - model.depth_sigma_z0) ** 2
    zscore = ((depth - z) / sigma)[moderate]
    assert moderate.sum() > 1000
    assert abs(zscore.mean()) < 0.1 and 0.85 < zscore.std() < 1.15
    far, near = valid & (z > 3.0), valid & (z < 2.0)
    assert np.std((depth - z)[far]) > 2.0 * np.std((depth - z)[near])  # grows with z^2


def test_colour_gain_offset_and_noise_at_rest() -> None:
    scene = build_default_scene(SEED)
    intr = default_intrinsics(160, 120)
    P = _still(make_trajectories(40, SEED, "walk")["agent_a"], 20)
    exact = render(scene, intr, P[2])
    model = SensorErrorModel()
    gain, offset = np.array([1.2, 0.9, 1.05]), 0.02
    rgb = colour_with_errors(exact, intr, P, 2, WALK_FPS, model, np.random.default_rng(1), gain, offset)
    x = exact.rgb.reshape(-1, 3) / 255.0
    y = rgb.reshape(-1, 3) / 255.0
    for c in range(3):
        keep = (y[:, c] > 0.02) & (y[:, c] < 0.98)  # unclipped
        slope, icept = np.polyfit(x[keep, c], y[keep, c], 1)
        assert abs(slope - gain[c]) < 0.02 and abs(icept - offset) < 0.01
        resid = y[keep, c] - (gain[c] * x[keep, c] + offset)
        expect = np.sqrt(model.read_noise ** 2 + model.shot_noise * np.clip(y[keep, c], 0, 1)).mean()
        assert 0.8 < resid.std() / expect < 1.3
    g, o = exposure_track(np.random.default_rng(2), 300, WALK_FPS, model)
    assert g.shape == (300, 3) and o.shape == (300,)
    assert 0.05 < np.std(np.log(g[:, 0])) < 0.25 and np.abs(np.diff(np.log(g), axis=0)).max() < 0.02  # slow


def test_motion_blurs_and_shears_the_colour() -> None:
    scene = build_default_scene(SEED)
    intr = default_intrinsics(160, 120)
    P = make_trajectories(80, SEED, "walk")["agent_a"]  # 80 frames for 7 m: fast, so the blur is visible
    quiet = SensorErrorModel(gain_log_std=0.0, white_balance_std=0.0, offset_std=0.0, read_noise=0.0, shot_noise=0.0)
    i = 40
    exact = render(scene, intr, P[i])
    moving = colour_with_errors(exact, intr, P, i, WALK_FPS, quiet, np.random.default_rng(0), np.ones(3), 0.0)
    still = colour_with_errors(exact, intr, _still(P, i), 2, WALK_FPS, quiet, np.random.default_rng(0), np.ones(3), 0.0)
    assert np.abs(still.astype(int) - exact.rgb).max() <= 1  # at rest: the render itself

    def sharpness(img: np.ndarray) -> float:
        return float(cv2.Laplacian(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float64), cv2.CV_64F).var())

    assert sharpness(moving) < 0.8 * sharpness(exact.rgb)


def test_make_scene_walk_with_noise_is_deterministic_and_recorded(tmp_path: Path) -> None:
    kw = dict(seed=SEED, width=48, height=36, frames=8, progress=False, trajectory="walk", sensor_noise="realistic")
    make_scene(tmp_path / "a", **kw)
    make_scene(tmp_path / "b", **kw)
    files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    assert len(files) == 4 + 2 * (1 + 2 * 8)
    for f in files:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f"{f} differs"
    meta = json.loads((tmp_path / "a" / "scene.json").read_text())
    assert meta["sensor_noise"] == "realistic" and meta["fps"] == WALK_FPS and meta["trajectory"] == "walk"
    assert meta["sensor_model"]["depth_sigma_b"] == 0.0019
    traj = np.loadtxt(tmp_path / "a" / "agent_a" / "traj.txt").reshape(-1, 4, 4)
    assert meta["path_length_m"]["agent_a"] == pytest.approx(_path_length(traj), abs=1e-4)
    depth = [cv2.imread(str(tmp_path / "a" / "agent_a" / "results" / f"depth{i:06d}.png"), cv2.IMREAD_UNCHANGED)
             for i in range(8)]
    assert all(d.dtype == np.uint16 for d in depth) and np.mean([np.mean(d == 0) for d in depth]) > 0.005
    make_scene(tmp_path / "exact", **{**kw, "sensor_noise": "none"})
    exact = cv2.imread(str(tmp_path / "exact" / "agent_a" / "results" / "depth000004.png"), cv2.IMREAD_UNCHANGED)
    assert (exact > 0).all() and not np.array_equal(exact, depth[4])
    assert np.array_equal(np.loadtxt(tmp_path / "exact" / "agent_a" / "traj.txt"),
                          np.loadtxt(tmp_path / "a" / "agent_a" / "traj.txt"))  # poses stay exact
    with pytest.raises(ValueError):
        sensor_model("kinect")


def test_default_scene_json_has_no_sensor_fields(tmp_path: Path) -> None:
    make_scene(tmp_path / "arcs", seed=SEED, width=32, height=24, frames=2, progress=False)
    meta = json.loads((tmp_path / "arcs" / "scene.json").read_text())
    assert "sensor_noise" not in meta and "fps" not in meta


def test_render_with_errors_keeps_the_exact_ids(tmp_path: Path) -> None:
    scene = build_default_scene(SEED)
    intr = default_intrinsics(64, 48)
    P = make_trajectories(30, SEED, "walk")["agent_b"]
    exact = render(scene, intr, P[10])
    r = render_with_errors(scene, intr, P, 10, WALK_FPS, SensorErrorModel(), np.random.default_rng(0),
                           np.ones(3), 0.0)
    assert np.array_equal(r.ids, exact.ids) and r.rgb.shape == exact.rgb.shape
    assert r.depth.max() * DEPTH_SCALE < 65535


def test_cli_walk_with_sensor_noise(tmp_path: Path) -> None:
    from gausslite.cli import main

    out = tmp_path / "cli"
    assert main(["make-scene", "--out", str(out), "--width", "32", "--height", "24", "--frames", "3",
                 "--trajectory", "walk", "--sensor-noise", "realistic", "--fps", "15", "--quiet"]) == 0
    meta = json.loads((out / "scene.json").read_text())
    assert meta["fps"] == 15.0 and meta["sensor_noise"] == "realistic"
    with pytest.raises(SystemExit):
        main(["make-scene", "--out", str(out), "--sensor-noise", "kinect"])
