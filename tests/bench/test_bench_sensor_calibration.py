"""bench.sensor_calibration's statistics on frames whose answer is known (no dataset needed): the depth lattice's
step, the plane-fit residual, holes and flying pixels at depth edges, the colour-depth edge offset and the exposure
track's spread."""

from __future__ import annotations

import numpy as np

from gausslite.camera import Intrinsics
from gausslite.datasets.base import Frame
from gausslite.synthetic import kinect

INTR = Intrinsics(fx=80.0, fy=80.0, cx=39.5, cy=29.5, width=80, height=60)


def _frame(depth: np.ndarray, rgb: np.ndarray = None, t: float = 0.0) -> Frame:
    rgb = np.full(depth.shape + (3,), 128, np.uint8) if rgb is None else rgb
    return Frame(0, t, rgb, depth.astype(np.float32), np.eye(4), INTR)


def test_the_lattice_step_and_the_plane_residual_are_recovered() -> None:
    import bench.sensor_calibration as sc

    v, u = np.mgrid[0:60, 0:80]
    frames = [_frame(kinect.quantise_disparity(z0 + 0.004 * u + 0.003 * v, 0.0028)) for z0 in np.arange(0.5, 3.6, 0.1)]
    q = sc.quantisation(frames)
    assert abs(q["c_per_m"] / 0.0028 - 1.0) < 0.1
    plane = 2.0 + 0.01 * u + 0.005 * v
    assert np.nanmax(sc.plane_residual(plane, 3)) < 1e-6  # a micrometre: rounding only
    noisy = plane + 0.002 * np.random.default_rng(0).standard_normal(plane.shape)
    assert abs(np.nanmedian(sc.plane_residual(noisy, 5)) / 0.002 - 1.0) < 0.15


def test_holes_and_flying_pixels_at_depth_edges_are_counted() -> None:
    import bench.sensor_calibration as sc

    z = np.full((60, 80), 3.0)
    z[:, 40:] = 1.0
    clean = sc.edges([_frame(z)])
    assert clean["with_holes"] == 0.0 and clean["pixel_between"]["flying"] == 0.0
    holed, mixed = z.copy(), z.copy()
    holed[:, 37:40] = 0.0  # a 3-pixel shadow on the far side
    mixed[:, 39] = 2.0  # a flying column
    h = sc.edges([_frame(holed)])
    assert h["with_holes"] > 0.9 and h["run_mean_px"] == 3.0
    assert sc.edges([_frame(mixed)])["pixel_between"]["flying"] > 0.3
    holes = sc.holes([_frame(holed)] * 3)
    assert abs(holes["all"] - 3 / 80) < 1e-9 and holes["border"] == holes["all"]


def test_the_colour_edge_offset_from_depth_edges_is_found() -> None:
    import bench.sensor_calibration as sc

    z = np.full((60, 80), 3.0)
    z[:, 40:] = 1.0  # depth edge between columns 39 and 40
    rgb = np.full((60, 80, 3), 40, np.uint8)
    rgb[:, 42:] = 200  # colour edge between columns 41 and 42: 2 px right of the depth's
    shifts = np.arange(-5.0, 5.001, 0.125)
    assert abs(sc.peak(shifts, sc.edge_score(_frame(z, rgb), 1, shifts)) - 2.0) < 0.2
    assert sc.edge_score(_frame(np.full((60, 80), 2.0), rgb), 1, shifts) is None  # no depth edge


def test_the_exposure_spread_follows_its_model() -> None:
    import bench.sensor_calibration as sc

    tau = np.array([0.0, 0.1, 10.0])
    s = sc.structure(tau, 0.2, 0.5)
    assert s[0] == 0.0 and abs(s[2] - np.sqrt(2) * 0.2) < 1e-6 and 0 < s[1] < s[2]
    assert abs(sc.robust_std(np.random.default_rng(0).standard_normal(20000)) - 1.0) < 0.03
