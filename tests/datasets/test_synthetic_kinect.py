"""Tests of the structured-light depth effects (``gausslite.synthetic.kinect``) and of the ``"tum"`` sensor level that
uses them (``make_scene(sensor_noise="tum")``): small images, fixed seeds."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from gausslite.synthetic import (
    SensorErrorModel, build_default_scene, default_intrinsics, make_scene, make_trajectories, pose_at, render,
    sensor_model,
)
from gausslite.synthetic import kinect
from gausslite.synthetic.sensor import TUM_FR1, depth_render, depth_with_errors, sensor_intrinsics

SEED = 4


def _step_scene(H: int = 40, W: int = 60, near: float = 1.0, far: float = 3.0) -> np.ndarray:
    """A near square (rows 10..29, columns 20..39) in front of a far wall."""
    z = np.full((H, W), far)
    z[10:30, 20:40] = near
    return z


def test_quantisation_steps_grow_with_z_squared() -> None:
    c = 0.0028
    for z0 in (0.8, 1.6, 3.2):
        z = np.linspace(z0 - 0.05, z0 + 0.05, 4001)
        levels = np.unique(kinect.quantise_disparity(z, c))
        steps = np.diff(levels)
        assert np.allclose(steps, c * levels[:-1] * levels[1:], rtol=1e-9)  # 1/z equally spaced by c
        assert abs(np.median(steps) / (c * z0 ** 2) - 1.0) < 0.05
        assert np.abs(kinect.quantise_disparity(z, c) - z).max() <= 0.5 * c * (z0 + 0.06) ** 2 + 1e-9
    z = np.array([[0.0, 1.0], [2.0, -1.0]])
    assert np.array_equal(kinect.quantise_disparity(z, 0.0), [[0.0, 1.0], [2.0, 0.0]])
    assert kinect.quantise_disparity(z, c)[0, 0] == 0.0
    with pytest.raises(ValueError):
        kinect.quantise_disparity(z, -1.0)


def test_correlated_noise_has_unit_spread_and_correlates_neighbours() -> None:
    white = kinect.correlated_field(np.random.default_rng(0), (120, 160), 0.0)
    smooth = kinect.correlated_field(np.random.default_rng(0), (120, 160), 1.5)

    def lag1(x: np.ndarray) -> float:
        return float(np.corrcoef(x[:, :-1].ravel(), x[:, 1:].ravel())[0, 1])

    assert abs(white.std() - 1.0) < 0.02 and abs(smooth.std() - 1.0) < 1e-6
    assert abs(lag1(white)) < 0.03 and lag1(smooth) > 0.7
    assert np.array_equal(smooth, kinect.correlated_field(np.random.default_rng(0), (120, 160), 1.5))


def test_border_bands_and_dark_surface_dropout() -> None:
    m = kinect.border_holes((240, 320), 0.0667, 0.0, 0.0063, 0.0625)
    assert m[:16].all() and not m[16:, 2:300].any() and m[:, 300:].all() and m[:, :2].all()
    knots = ((10.0, 0.25), (100.0, 0.0))
    grey = np.full((96, 128), 10.0)
    dark = kinect.dark_dropout(grey, np.random.default_rng(1), knots)
    assert abs(dark.mean() - 0.25) < 0.01  # the probability at its grey level
    assert not kinect.dark_dropout(grey + 150.0, np.random.default_rng(1), knots).any()
    same = np.mean(dark[:, 1:] == dark[:, :-1])
    assert same > 0.9  # in patches: neighbours agree far more often than independent drops would (62 %)
    assert not kinect.dark_dropout(grey, np.random.default_rng(1), ()).any()


def test_shadows_lie_on_the_far_side_next_to_edges() -> None:
    z = _step_scene()
    holes = kinect.edge_shadows(z, np.random.default_rng(2), 1.0, 3.0, 0.05, 0.04)
    assert holes.any() and not holes[10:30, 20:40].any()  # never on the near surface
    dist = cv2.distanceTransform((z != 3.0).astype(np.uint8) ^ 1, cv2.DIST_L1, 3)  # far pixels: distance to near
    far_dist = cv2.distanceTransform((z == 3.0).astype(np.uint8), cv2.DIST_L1, 3)
    assert far_dist[holes].min() >= 1 and np.all(dist[holes] > 0)
    runs = [np.argmin(holes[r, 19::-1]) for r in range(10, 30)]  # run lengths left of the square
    assert 2.0 < np.mean(runs) < 4.5  # mean 3 (1 + geometric)
    assert not kinect.edge_shadows(np.full((20, 20), 2.0), np.random.default_rng(2), 1.0, 3.0, 0.05, 0.04).any()
    assert not kinect.edge_shadows(z, np.random.default_rng(2), 0.0, 3.0, 0.05, 0.04).any()
    with pytest.raises(ValueError):
        kinect.edge_shadows(z, np.random.default_rng(2), 0.5, 0.5, 0.05, 0.04)


def test_flying_pixels_appear_only_at_edges_between_the_two_depths() -> None:
    z = _step_scene()
    out = kinect.flying_pixels(z, np.random.default_rng(3), 0.5, 0.05, 0.04)
    changed = out != z
    assert changed.sum() > 10
    edge = np.zeros_like(changed)
    for _, far in kinect.jump_masks(z, 0.05, 0.04):
        edge |= far
    assert np.all(edge[changed])  # only far-side pixels next to the near square
    assert np.all((out[changed] > 1.0) & (out[changed] < 3.0))  # mixed: between the two surfaces
    assert np.array_equal(kinect.flying_pixels(z, np.random.default_rng(3), 0.0, 0.05, 0.04), z)
    flat = np.full((20, 20), 2.0)
    assert np.array_equal(kinect.flying_pixels(flat, np.random.default_rng(3), 1.0, 0.05, 0.04), flat)


def test_misregistration_shifts_the_depth_by_the_configured_offset() -> None:
    scene = build_default_scene(SEED)
    intr = default_intrinsics(96, 72)
    P = make_trajectories(40, SEED, "walk")["agent_a"]
    exact = render(scene, intr, P[20]).depth
    dx, dy = 3, -2  # pixels: right and up
    model = dataclasses.replace(SensorErrorModel(), misregistration_x_mrad=1e3 * dx / intr.fx,
                                misregistration_y_mrad=1e3 * dy / intr.fy)
    r, c2w = depth_render(scene, intr, P, 20, 30.0, model, np.random.default_rng(0))
    assert not np.allclose(c2w, P[20])
    H, W = exact.shape
    err = {}
    for sx in range(-4, 5):
        for sy in range(-4, 5):
            a = r.depth[max(sy, 0):H + min(sy, 0), max(sx, 0):W + min(sx, 0)]
            b = exact[max(-sy, 0):H + min(-sy, 0), max(-sx, 0):W + min(-sx, 0)]
            err[(sx, sy)] = float(np.median(np.abs(a - b)))
    assert min(err, key=err.get) == (dx, dy)  # the depth's content moved by (dx, dy) against the colour's


def test_depth_is_rendered_at_the_delayed_pose_and_rows_at_their_readout() -> None:
    scene = build_default_scene(SEED)
    intr = default_intrinsics(48, 36)
    P = make_trajectories(40, SEED, "walk")["agent_a"]
    model = dataclasses.replace(SensorErrorModel(), depth_time_offset_s=0.01)
    r, c2w = depth_render(scene, intr, P, 20, 30.0, model, np.random.default_rng(0))
    assert np.allclose(c2w, pose_at(P, 20.3))
    assert np.array_equal(r.depth, render(scene, intr, pose_at(P, 20.3)).depth)
    still = np.repeat(P[20][None], intr.height, axis=0)
    assert np.allclose(kinect.warp_depth_rows(r.depth, intr, c2w, np.repeat(c2w[None], intr.height, axis=0)),
                       r.depth)
    fwd = still.copy()
    fwd[:, :3, 3] += 0.05 * P[20][:3, 2]  # every row 5 cm further along the optical axis
    ex = render(scene, intr, P[20]).depth
    moved = kinect.warp_depth_rows(ex, intr, P[20], fwd)
    inside = moved > 0
    assert inside.mean() > 0.8 and abs(np.median((ex - moved)[inside]) - 0.05) < 1e-6


def test_the_tum_level_quantises_and_opens_holes_as_measured() -> None:
    scene = build_default_scene(SEED)
    intr = sensor_intrinsics(TUM_FR1, 160, 120)
    assert intr.fx == pytest.approx(160 * 546.75 / 640) and intr.fy == pytest.approx(120 * 543.09 / 480)
    P = make_trajectories(40, SEED, "walk")["agent_a"]
    r, c2w = depth_render(scene, intr, P, 20, 30.0, TUM_FR1, np.random.default_rng(0))
    d = depth_with_errors(r, intr, c2w, TUM_FR1, np.random.default_rng(1))
    valid = d > 0
    k = 1.0 / d[valid] / TUM_FR1.depth_quant_per_m
    assert np.allclose(k, np.rint(k), atol=1e-6)  # on the disparity lattice
    assert 0.1 < (~valid).mean() < 0.4 and (~valid)[:8].all()  # the top band
    assert sensor_model("tum") is TUM_FR1 and sensor_model("realistic") == SensorErrorModel()


def test_make_scene_with_the_tum_sensor(tmp_path: Path) -> None:
    kw = dict(seed=SEED, width=48, height=36, frames=4, progress=False, trajectory="walk", sensor_noise="tum",
              agents=("agent_a",))
    make_scene(tmp_path / "a", **kw)
    make_scene(tmp_path / "b", **kw)
    for f in sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file()):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f"{f} differs"
    cam = json.loads((tmp_path / "a" / "cam_params.json").read_text())["camera"]
    assert cam["fx"] == pytest.approx(48 * 546.75 / 640) and cam["fy"] == pytest.approx(36 * 543.09 / 480)
    meta = json.loads((tmp_path / "a" / "scene.json").read_text())
    assert meta["sensor_noise"] == "tum" and meta["sensor_model"]["depth_quant_per_m"] == 0.0028
    make_scene(tmp_path / "r", **{**kw, "sensor_noise": "realistic"})
    assert json.loads((tmp_path / "r" / "cam_params.json").read_text())["camera"]["fx"] == 24.0  # 90 degrees


def test_cli_selects_the_tum_sensor(tmp_path: Path) -> None:
    from gausslite.cli import main

    out = tmp_path / "cli"
    assert main(["make-scene", "--out", str(out), "--width", "32", "--height", "24", "--frames", "2",
                 "--trajectory", "walk", "--sensor-noise", "tum", "--agents", "agent_a", "--quiet"]) == 0
    assert json.loads((out / "scene.json").read_text())["sensor_noise"] == "tum"


def test_each_tum_fault_alone_on_the_clean_tum_camera(tmp_path: Path) -> None:
    from gausslite.cli.cmd_make_scene import SENSOR_NOISE_NAMES
    from gausslite.synthetic import SENSOR_NOISE
    from gausslite.synthetic.sensor import TUM_CLEAN, TUM_FAULTS, tum_fault

    assert SENSOR_NOISE_NAMES == SENSOR_NOISE  # the command line offers every level
    groups = [f for fields in TUM_FAULTS.values() for f in fields]
    assert len(groups) == len(set(groups))  # each field in one fault
    for name, fields in TUM_FAULTS.items():
        m = sensor_model(f"tum-{name}")
        assert m == tum_fault(name)
        for f in dataclasses.fields(SensorErrorModel):
            want = getattr(TUM_FR1 if f.name in fields else TUM_CLEAN, f.name)
            assert getattr(m, f.name) == want, (name, f.name)
    # the clean camera renders exact depth and colour through TUM's lens
    scene = build_default_scene(SEED)
    intr = sensor_intrinsics(TUM_CLEAN, 64, 48)
    assert intr.fx == pytest.approx(64 * 546.75 / 640)
    P = make_trajectories(40, SEED, "walk")["agent_a"]
    exact = render(scene, intr, P[20])
    r, c2w = depth_render(scene, intr, P, 20, 30.0, TUM_CLEAN, np.random.default_rng(0))
    d = depth_with_errors(r, intr, c2w, TUM_CLEAN, np.random.default_rng(1))
    inside = (exact.depth >= TUM_CLEAN.depth_min_m) & (exact.depth <= TUM_CLEAN.depth_max_m)
    np.testing.assert_array_equal(d[inside], exact.depth[inside])
    assert np.all(d[~inside] == 0)
    with pytest.raises(ValueError, match="unknown fault"):
        tum_fault("lens-flare")
    from gausslite.cli import main

    out = tmp_path / "fault"
    assert main(["make-scene", "--out", str(out), "--width", "32", "--height", "24", "--frames", "2",
                 "--trajectory", "walk", "--sensor-noise", "tum-exposure", "--agents", "agent_a", "--quiet"]) == 0
    meta = json.loads((out / "scene.json").read_text())
    assert meta["sensor_noise"] == "tum-exposure" and meta["sensor_model"]["gain_log_std"] == TUM_FR1.gain_log_std
    assert meta["sensor_model"]["exposure_s"] == 0.0
