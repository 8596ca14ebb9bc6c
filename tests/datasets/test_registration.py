"""Depth registration to the colour camera (gausslite.datasets.registration) and its use by folder loaders."""

from __future__ import annotations

import numpy as np
import pytest

from gausslite.camera import Intrinsics
from gausslite.datasets import TUMDataset, load_dataset
from gausslite.datasets.registration import DepthCamera, parse_depth_camera, project_plumb_bob, register_depth
from gausslite.ros.transforms import make_transform
from gausslite.synthetic.raycast import render
from gausslite.synthetic.scene import build_default_scene
from gausslite.synthetic.trajectories import make_trajectories

# 7-Scenes/Kinect-like: depth camera fx = fy = 585, colour 525 (640x480 values at 1/4 size), 2.5 cm baseline
S = 4
COLOR = Intrinsics(525 / S, 525 / S, 319.5 / S, 239.5 / S, 640 // S, 480 // S)
DEPTH = Intrinsics(585 / S, 585 / S, 319.5 / S, 239.5 / S, 640 // S, 480 // S)
T_CD = make_transform([-0.025, 0.004, 0.002], [0.0, 0.0087, 0.0, 1.0])  # ~1 degree about y


def test_registration_matches_direct_depth_of_the_colour_camera():
    scene = build_default_scene(0)
    c2w = make_trajectories(4, 0)["agent_a"][1]
    direct = render(scene, COLOR, c2w).depth  # what the colour camera would measure
    raw = render(scene, DEPTH, c2w @ T_CD).depth.astype(np.float32)  # what the depth camera measured
    reg = register_depth(raw, DepthCamera(DEPTH, T_CD), COLOR)
    assert reg.shape == (COLOR.height, COLOR.width) and reg.dtype == np.float32
    valid = reg > 0
    err = np.abs(reg - direct)[valid]
    naive = np.abs(raw - direct)  # using the unregistered depth as if it were registered
    # the narrower depth field of view (585 vs 525) leaves a border of the colour image uncovered
    assert 0.75 < valid.mean() < 0.86
    assert np.median(err) < 0.01 and np.percentile(err, 95) < 0.03 and (err > 0.05).mean() < 0.02
    assert np.median(naive) > 0.05  # without registration the depth is badly off: the test can fail


def test_identity_registration_is_exact_and_invalid_stays_invalid():
    rng = np.random.default_rng(0)
    d = rng.uniform(0.5, 3.0, size=(COLOR.height, COLOR.width)).astype(np.float32)
    d[5, 7] = 0.0
    d[6, 8] = np.nan
    out = register_depth(d, DepthCamera(COLOR), COLOR)
    expect = np.nan_to_num(d)
    assert np.array_equal(out, expect)
    assert DepthCamera(COLOR).is_identity_for(COLOR) and not DepthCamera(DEPTH).is_identity_for(COLOR)


@pytest.mark.parametrize("order", [(3.0, 2.0), (2.0, 3.0)])
def test_z_buffer_keeps_the_nearest_surface(order):
    # both depth pixels project onto colour pixel (0, 0): the nearer one must win whatever the order
    di = Intrinsics(1000.0, 1000.0, 0.5, 0.0, 2, 1)
    ci = Intrinsics(1.0, 1.0, 0.0, 0.0, 1, 1)
    out = register_depth(np.array([order], np.float32), DepthCamera(di), ci)
    assert out[0, 0] == pytest.approx(2.0)


def test_splat_fills_holes_of_a_coarse_depth_camera():
    coarse = Intrinsics(COLOR.fx / 2, COLOR.fy / 2, (COLOR.cx + 0.5) / 2 - 0.5, (COLOR.cy + 0.5) / 2 - 0.5,
                        COLOR.width // 2, COLOR.height // 2)
    d = np.full((coarse.height, coarse.width), 2.0, np.float32)
    one = register_depth(d, DepthCamera(coarse), COLOR)
    two = register_depth(d, DepthCamera(coarse, splat=2), COLOR)
    assert (one > 0).mean() == pytest.approx(0.25, abs=0.02) and (two > 0).mean() > 0.98
    assert np.all(two[two > 0] == 2.0)


def test_distortion_projection_and_unprojection_agree():
    dist = (0.1, -0.05, 0.001, -0.002, 0.01)
    P = np.array([[0.1, -0.2, 2.0], [0.0, 0.0, 1.0], [-0.3, 0.25, 3.0]])
    uv = project_plumb_bob(P, COLOR.K, dist)
    import cv2

    ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), COLOR.K, np.asarray(dist))
    assert np.allclose(uv, ref.reshape(-1, 2), atol=1e-9)
    # a distorted depth camera registered into itself (same model) returns the same depth
    di = Intrinsics(COLOR.fx, COLOR.fy, COLOR.cx, COLOR.cy, COLOR.width, COLOR.height)
    d = np.full((di.height, di.width), 1.5, np.float32)
    out = register_depth(d, DepthCamera(di, distortion=dist), di, dist)
    inner = out[10:-10, 10:-10]
    assert (inner > 0).mean() > 0.97 and np.allclose(inner[inner > 0], 1.5, atol=1e-5)


def test_depth_camera_validation_and_parsing():
    with pytest.raises(ValueError, match="not a rigid transform"):
        DepthCamera(DEPTH, np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="4x4"):
        DepthCamera(DEPTH, np.eye(3))
    with pytest.raises(ValueError, match="splat"):
        DepthCamera(DEPTH, splat=0)
    dc = parse_depth_camera([585, 585, 320, 240], [0.025, 0, 0, 0, 0, 0, 1], size=(640, 480))
    assert dc.intrinsics == Intrinsics(585, 585, 320, 240, 640, 480) and dc.T_color_depth[0, 3] == 0.025
    assert parse_depth_camera([585, 585, 320, 240, 320, 240]).intrinsics.width == 320
    with pytest.raises(ValueError, match="image size"):
        parse_depth_camera([585, 585, 320, 240])
    with pytest.raises(ValueError, match="tx,ty,tz,qx,qy,qz,qw or 16"):
        parse_depth_camera([585, 585, 320, 240, 64, 48], [1, 2, 3])
    with pytest.raises(ValueError, match="depth image is"):
        register_depth(np.zeros((3, 3), np.float32), DepthCamera(DEPTH), COLOR)


def test_folder_loader_registers_unregistered_depth(tmp_path):
    from tests.datasets.test_datasets_fixtures import make_tum

    seq = make_tum(tmp_path, w=40, h=30)
    intr = Intrinsics(40.0, 40.0, 19.5, 14.5, 40, 30)
    plain = load_dataset(seq, intrinsics=intr)
    dcam = parse_depth_camera([44.0, 44.0, 19.5, 14.5, 40, 30], [0.05, 0, 0, 0, 0, 0, 1])
    ds = load_dataset(seq, intrinsics=intr, depth_camera=dcam)
    assert isinstance(ds, TUMDataset) and ds.depth_camera is dcam
    f0, g0 = plain[0], ds[0]
    ci, cd = ds._color_camera()
    assert ci == intr and cd is not None  # freiburg1: registered into the distorted colour camera
    assert np.array_equal(g0.depth, register_depth(f0.depth, dcam, ci, cd))
    assert not np.array_equal(g0.depth, f0.depth) and (g0.depth > 0).mean() > 0.5
    with pytest.raises(ValueError, match="must be a DepthCamera"):
        load_dataset(seq, intrinsics=intr, depth_camera="585")


def test_cli_depth_camera_flags(tmp_path):
    import argparse

    from gausslite.cli.cmd_map import add_mapping_args, dataset_kwargs
    from tests.datasets.test_datasets_fixtures import make_seven

    p = argparse.ArgumentParser()
    add_mapping_args(p)
    seq = make_seven(tmp_path)  # 40x30 frames
    kw = dataset_kwargs(p.parse_args(["--color-intrinsics", "35,35,19.5,14.5", "--depth-intrinsics", "39,39,19.5,14.5",
                                      "--depth-extrinsic", "0.025,0,0,0,0,0,1"]), seq)
    assert kw["intrinsics"] == [35.0, 35.0, 19.5, 14.5]
    dc = kw["depth_camera"]
    assert dc.intrinsics == Intrinsics(39, 39, 19.5, 14.5, 640, 480)  # size of the loader's (default) colour camera
    assert np.allclose(dc.T_color_depth[:3, 3], [0.025, 0, 0])
    with pytest.raises(ValueError, match="--depth-extrinsic needs --depth-intrinsics"):
        dataset_kwargs(p.parse_args(["--depth-extrinsic", "0,0,0,0,0,0,1"]), seq)
    with pytest.raises(ValueError, match="--color-intrinsics needs fx,fy,cx,cy"):
        dataset_kwargs(p.parse_args(["--color-intrinsics", "1,2"]), seq)
    with pytest.raises(ValueError, match="comma-separated numbers"):
        dataset_kwargs(p.parse_args(["--depth-intrinsics", "a,b,c,d"]), seq)
    with pytest.raises(ValueError, match="--undistort/--interpolate-poses/--align-depth-time apply to TUM"):
        dataset_kwargs(p.parse_args(["--undistort"]), seq)


def test_tum_depth_time_alignment_reprojects_depth_to_the_colour_instant(tmp_path):
    """Each depth image is re-projected from the pose at its own timestamp (colour + 4 ms in the fixture)
    to the colour frame's; the fixture's camera turns about its optical axis at 10 rad/s and moves at
    1 m/s along world x, so T_color_depth = [Rz(0.04), Rz(-a)·(0.004, 0, 0)] exactly (linear motion)."""
    import math

    import cv2

    from tests.datasets.test_datasets_fixtures import make_tum

    seq = make_tum(tmp_path, n=4, w=40, h=30)
    intr = Intrinsics(30, 30, 19.5, 14.5, 40, 30)
    plain = TUMDataset(seq, intrinsics=intr, interpolate_poses=True)
    # a depth step (1 m left, 2 m right) so the re-projection moves visible structure
    dname = plain.depth_paths[2]
    step = np.full((30, 40), 5000, np.uint16)
    step[:, 20:] = 10000
    assert cv2.imwrite(str(dname), step)
    plain = TUMDataset(seq, intrinsics=intr, interpolate_poses=True)
    aligned = TUMDataset(seq, intrinsics=intr, interpolate_poses=True, align_depth_time=True)
    np.testing.assert_array_equal(plain[2].depth, step / 5000.0)  # off: the file as stored
    a = 10.0 * (plain.timestamps[2] - 999.953)  # colour-frame yaw
    T = np.eye(4)
    c, s = math.cos(0.04), math.sin(0.04)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [math.cos(a) * 0.004, -math.sin(a) * 0.004, 0.0]
    np.testing.assert_allclose(aligned._time_extrinsics[2], T, atol=1e-6)
    # the files are in the raw fr1 camera (plumb_bob distortion): re-projected within it
    expected = register_depth(step / 5000.0, DepthCamera(intr, T, aligned.distortion), intr, aligned.distortion)
    got = aligned[2].depth
    np.testing.assert_allclose(got, expected, atol=1e-6)
    assert np.count_nonzero(got != plain[2].depth) > 20  # the step edge moved
    assert aligned.poses[2] == pytest.approx(plain.poses[2])  # colour poses are untouched


def test_cli_align_depth_time_flag(tmp_path):
    import argparse

    from gausslite.cli.cmd_map import add_mapping_args, dataset_kwargs
    from tests.datasets.test_datasets_fixtures import make_seven, make_tum

    p = argparse.ArgumentParser()
    add_mapping_args(p)
    tum = make_tum(tmp_path / "t")
    assert dataset_kwargs(p.parse_args([]), tum)["align_depth_time"] is True  # hand-held profile default
    assert dataset_kwargs(p.parse_args(["--no-align-depth-time"]), tum)["align_depth_time"] is False
    with pytest.raises(ValueError, match="--align-depth-time apply to TUM"):
        dataset_kwargs(p.parse_args(["--align-depth-time"]), make_seven(tmp_path / "s"))
