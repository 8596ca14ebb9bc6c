"""Dataset loaders on small synthetic fixtures written to tmp_path: layouts, values and every error path."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from gausslite.camera import Intrinsics
from gausslite.datasets import (
    ReplicaDataset,
    SevenScenesDataset,
    TUMDataset,
    detect_layout,
    load_dataset,
)

W, H = 40, 30


def _pose(k: int) -> np.ndarray:
    a = 0.1 * k
    T = np.eye(4)
    T[:3, :3] = [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = [0.1 * k, -0.2, 1.0]
    return T


def _rgb(k: int, w: int = W, h: int = H) -> np.ndarray:
    img = np.zeros((h, w, 3), np.uint8)
    img[..., 0] = 10 + k  # R
    img[..., 1] = 100  # G
    img[..., 2] = 200  # B
    return img


def _write_rgb(path: Path, rgb: np.ndarray) -> None:
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def _depth_raw(k: int, w: int = W, h: int = H) -> np.ndarray:
    d = np.full((h, w), 6553 + 100 * k, np.uint16)
    d[0, 0] = 0
    return d


def make_replica(root: Path, n: int = 3, n_poses=None, ext: str = "png", cam_in_parent: bool = True) -> Path:
    """<root>/cam_params.json + <root>/seq/{traj.txt, results/frame*.png, depth*.png}."""
    seq = root / "seq"
    (seq / "results").mkdir(parents=True)
    cam = {"camera": {"w": W, "h": H, "fx": 30.0, "fy": 31.0, "cx": 19.5, "cy": 14.5, "scale": 6553.5}}
    (root if cam_in_parent else seq).joinpath("cam_params.json").write_text(json.dumps(cam))
    for k in range(n):
        _write_rgb(seq / "results" / f"frame{k:06d}.{ext}", _rgb(k))
        assert cv2.imwrite(str(seq / "results" / f"depth{k:06d}.png"), _depth_raw(k))
    m = n if n_poses is None else n_poses
    with open(seq / "traj.txt", "w") as fh:
        for k in range(m):
            fh.write(" ".join(f"{v:.17g}" for v in _pose(k).ravel()) + "\n")
    return seq


def _quat_z(a: float):
    return (0.0, 0.0, math.sin(a / 2), math.cos(a / 2))  # xyzw


def make_tum(root: Path, name: str = "rgbd_dataset_freiburg1_test", n: int = 4, w: int = W, h: int = H,
             drop_depth=(), gt_offset: float = 0.003) -> Path:
    seq = root / name
    (seq / "rgb").mkdir(parents=True)
    (seq / "depth").mkdir()
    t0 = 1000.0
    rgb_lines, depth_lines, gt_lines = ["# color images", "# file: 'x.bag'", "# timestamp filename"], ["# depth"], ["# gt"]
    for k in range(n):
        t = t0 + k / 30.0
        _write_rgb(seq / "rgb" / f"{t:.6f}.png", _rgb(k, w, h))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        if k not in drop_depth:
            td = t + 0.004
            assert cv2.imwrite(str(seq / "depth" / f"{td:.6f}.png"), np.full((h, w), 5000 * (k + 1), np.uint16))
            depth_lines.append(f"{td:.6f} depth/{td:.6f}.png")
    for j in range(int(n / 30.0 * 100) + 10):
        t = t0 - 0.05 + j * 0.01 + gt_offset
        q = _quat_z(0.1 * j)
        gt_lines.append(f"{t:.4f} {0.01 * j:.4f} 0.5 1.5 {q[0]:.6f} {q[1]:.6f} {q[2]:.6f} {q[3]:.6f}")
    (seq / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (seq / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (seq / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    return seq


def make_seven(root: Path, n: int = 3, w: int = W, h: int = H, with_k: bool = True) -> Path:
    seq = root / "seq-01"
    seq.mkdir(parents=True)
    if with_k:
        (root / "camera-intrinsics.txt").write_text("30 0 20\n0 30 15\n0 0 1\n")
    for k in range(n):
        _write_rgb(seq / f"frame-{k:06d}.color.png", _rgb(k, w, h))
        d = np.full((h, w), 1500 + k, np.uint16)
        d[0, 0] = 0
        d[0, 1] = 65535
        assert cv2.imwrite(str(seq / f"frame-{k:06d}.depth.png"), d)
        np.savetxt(seq / f"frame-{k:06d}.pose.txt", _pose(k), fmt="%.10e")
    return seq


# ------------------------------------------------------------------------------------------------
# Replica
# ------------------------------------------------------------------------------------------------
def test_replica_fixture_values(tmp_path):
    seq = make_replica(tmp_path, n=3, n_poses=7)
    ds = load_dataset(seq)
    assert isinstance(ds, ReplicaDataset) and len(ds) == 3 and ds.annotations is None
    f = ds[2]
    assert f.rgb.dtype == np.uint8 and f.rgb.shape == (H, W, 3)
    np.testing.assert_array_equal(f.rgb[5, 5], [12, 100, 200])  # RGB order
    assert f.depth.dtype == np.float32 and f.depth[0, 0] == 0
    assert f.depth[1, 1] == pytest.approx((6553 + 200) / 6553.5)
    np.testing.assert_allclose(f.c2w, _pose(2), atol=1e-12)
    assert f.c2w.dtype == np.float64 and f.frame_id == 2 and f.name == "frame000002"
    assert ds[-1].frame_id == 2 and [x.frame_id for x in ds[0:2]] == [0, 1]
    with pytest.raises(IndexError):
        ds[3]


def test_replica_cam_params_in_sequence_folder_and_jpg(tmp_path):
    seq = make_replica(tmp_path, ext="jpg", cam_in_parent=False)
    ds = ReplicaDataset(seq, downscale=2)
    assert ds.cam_params_path == seq / "cam_params.json"
    f = ds[0]
    assert f.rgb.shape == (15, 20, 3) and f.intrinsics.fx == 15.0


def test_replica_lazy_loading(tmp_path):
    seq = make_replica(tmp_path)
    ds = ReplicaDataset(seq)
    (seq / "results" / "frame000001.png").write_bytes(b"garbage")  # broken after construction
    ds[0]
    with pytest.raises(ValueError, match="frame000001.png"):
        ds[1]


def test_replica_missing_folders_and_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope"):
        ReplicaDataset(tmp_path / "nope")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match="results"):
        ReplicaDataset(empty)
    seq = make_replica(tmp_path / "a")
    (seq / "traj.txt").unlink()  # no poses: odometry estimates them, pose_source "given" names the file
    assert not ReplicaDataset(seq).has_poses
    with pytest.raises(ValueError, match="traj.txt"):
        load_dataset(seq, pose_source="given")
    seq = make_replica(tmp_path / "b")
    (seq.parent / "cam_params.json").unlink()
    with pytest.raises(FileNotFoundError, match="cam_params.json"):
        ReplicaDataset(seq)
    seq = make_replica(tmp_path / "c")
    (seq / "results" / "depth000001.png").unlink()
    with pytest.raises(FileNotFoundError, match="depth000001.png"):
        ReplicaDataset(seq)
    seq = make_replica(tmp_path / "d", n=1)
    (seq / "results" / "frame000000.png").unlink()
    with pytest.raises(FileNotFoundError, match="no colour frames"):
        ReplicaDataset(seq)


def test_replica_bad_cam_params(tmp_path):
    seq = make_replica(tmp_path)
    cp = tmp_path / "cam_params.json"
    cp.write_text(json.dumps({"camera": {"w": W, "h": H, "fx": 1, "fy": 1, "cx": 1, "cy": 1}}))
    with pytest.raises(ValueError, match=r"cam_params.json.*scale"):
        ReplicaDataset(seq)
    cp.write_text("{not json")
    with pytest.raises(ValueError, match="cam_params.json"):
        ReplicaDataset(seq)
    cp.write_text(json.dumps({"camera": {"w": W, "h": H, "fx": -1, "fy": 1, "cx": 1, "cy": 1, "scale": 1}}))
    with pytest.raises(ValueError, match="cam_params.json"):
        ReplicaDataset(seq)


def test_replica_fewer_poses_than_frames(tmp_path):
    seq = make_replica(tmp_path, n=3, n_poses=2)
    with pytest.raises(ValueError, match=r"traj.txt.*2 poses.*3 frames"):
        ReplicaDataset(seq)


@pytest.mark.parametrize(
    "line, match",
    [
        ("1 2 3", r"traj.txt:2: expected 16 numbers"),
        (" ".join(["x"] * 16), r"traj.txt:2: non-numeric"),
        (" ".join(["nan"] + ["0"] * 15), r"traj.txt:2: .*NaN"),
        (" ".join(str(v) for v in np.diag([2, 2, 2, 1.0]).ravel()), r"traj.txt:2: .*non-rigid"),
        (" ".join(str(v) for v in (2 * np.eye(4)).ravel()), r"traj.txt:2: last row"),
        (" ".join(str(v) for v in np.diag([1, 1, -1, 1.0]).ravel()), r"traj.txt:2: .*non-rigid"),
    ],
)
def test_replica_bad_pose_lines(tmp_path, line, match):
    seq = make_replica(tmp_path, n=3)
    lines = (seq / "traj.txt").read_text().splitlines()
    lines[1] = line
    (seq / "traj.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=match):
        ReplicaDataset(seq)


def test_replica_bad_images(tmp_path):
    seq = make_replica(tmp_path)
    r = seq / "results"
    assert cv2.imwrite(str(r / "frame000000.png"), np.zeros((H + 2, W, 3), np.uint8))
    assert cv2.imwrite(str(r / "depth000000.png"), np.zeros((H + 2, W), np.uint16))
    assert cv2.imwrite(str(r / "depth000001.png"), np.zeros((H, W + 1), np.uint16))
    assert cv2.imwrite(str(r / "depth000002.png"), np.zeros((H, W), np.uint8))  # 8-bit depth
    ds = ReplicaDataset(seq)
    with pytest.raises(ValueError, match=r"frame000000.png: image is 40x32 but the intrinsics are for 40x30"):
        ds[0]
    with pytest.raises(ValueError, match=r"size mismatch.*frame000001.png.*depth000001.png"):
        ds[1]
    with pytest.raises(ValueError, match=r"depth000002.png: depth must be a single-channel 16-bit"):
        ds[2]
    (r / "depth000002.png").write_bytes(b"\x89PNG broken")
    with pytest.raises(ValueError, match=r"depth000002.png: unreadable depth"):
        ds[2]
    (r / "frame000002.png").unlink()
    with pytest.raises(FileNotFoundError, match="frame000002.png"):
        ds[2]


# ------------------------------------------------------------------------------------------------
# TUM
# ------------------------------------------------------------------------------------------------
def test_tum_fixture_association_and_poses(tmp_path, caplog):
    seq = make_tum(tmp_path, n=5, drop_depth=(2,))
    small = Intrinsics(30, 30, 19.5, 14.5, W, H)
    with caplog.at_level(logging.WARNING, logger="gausslite.datasets.tum"):
        ds = TUMDataset(seq, intrinsics=small)
    assert "dropped 1 of 5" in caplog.text
    assert len(ds) == 4 and ds.n_dropped == 1 and ds.frame_ids == [0, 1, 3, 4]
    f = ds[2]
    assert f.frame_id == 3 and f.timestamp == pytest.approx(1000.1)
    assert f.depth[0, 0] == pytest.approx(4.0)  # value 5000 * 4 / 5000
    np.testing.assert_array_equal(f.rgb[0, 0], [13, 100, 200])
    # nearest groundtruth sample j: t = 999.95 + 0.01 j + 0.003, rotation about z by 0.1 j
    j = int(round((f.timestamp - 999.953) / 0.01))
    a = 0.1 * j
    np.testing.assert_allclose(f.c2w[:3, :3], [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]], atol=1e-5)
    np.testing.assert_allclose(f.c2w[:3, 3], [0.01 * j, 0.5, 1.5])
    # interpolation: translation x is linear in time
    di = TUMDataset(seq, intrinsics=small, interpolate_poses=True)
    assert di.poses[2][0, 3] == pytest.approx(0.01 * (f.timestamp - 999.953) / 0.01, abs=1e-9)
    # stride/max_frames act on associated frames
    assert TUMDataset(seq, intrinsics=small, stride=2, max_frames=1).frame_ids == [0]


def test_tum_pose_gap(tmp_path):
    seq = make_tum(tmp_path, n=3, gt_offset=0.005)  # nearest gt 0.002 s .. 0.005 s away
    small = (30.0, 30.0, 19.5, 14.5)
    assert len(TUMDataset(seq, intrinsics=Intrinsics(*small, W, H))) == 3
    with pytest.raises(ValueError, match="no colour frame has depth"):
        TUMDataset(seq, intrinsics=Intrinsics(*small, W, H), max_depth_dt=0.001)


@pytest.mark.parametrize(
    "name, fx",
    [
        ("rgbd_dataset_freiburg1_rpy", 517.3),
        ("rgbd_dataset_freiburg2_xyz", 520.9),
        ("fr3_office", 535.4),
        ("my_kitchen", 517.3),  # falls back to the rgb.txt header ... 'freiburg1' below
        ("frame1_data", 525.0),
    ],
)
def test_tum_intrinsics_by_name(tmp_path, name, fx):
    seq = make_tum(tmp_path, name=name, n=1)
    if name == "my_kitchen":
        txt = (seq / "rgb.txt").read_text().replace("'x.bag'", "'rgbd_dataset_freiburg1_desk.bag'")
        (seq / "rgb.txt").write_text(txt)
    ds = TUMDataset(seq)
    assert ds.intrinsics.fx == fx and (ds.intrinsics.width, ds.intrinsics.height) == (640, 480)
    with pytest.raises(ValueError, match=r"image is 40x30 but the intrinsics are for 640x480"):
        ds[0]
    ov = TUMDataset(seq, intrinsics=(500.0, 501.0, 300.0, 200.0))
    assert (ov.intrinsics.fx, ov.intrinsics.fy, ov.intrinsics.width) == (500.0, 501.0, 640)


def test_tum_full_size_frame_and_undistort(tmp_path):
    seq = make_tum(tmp_path, n=1, w=640, h=480)
    ds = TUMDataset(seq, undistort=True, downscale=4)
    f = ds[0]
    # undistorted onto the alpha=0 optimal camera: zoomed in (fx 546.75 at 640x480), no black border
    assert f.rgb.shape == (120, 160, 3) and f.intrinsics.fx == pytest.approx(546.75 / 4, abs=0.01)
    assert ds.raw_intrinsics.fx == 517.3 and ds.native_intrinsics.fx == pytest.approx(546.75, abs=0.01)
    raw = TUMDataset(seq, downscale=4)[0]
    assert (raw.depth > 0).all() and (f.depth > 0).all()
    assert set(np.unique(f.depth)) <= {0.0, 1.0}


@pytest.mark.parametrize(
    "fname, content, match",
    [
        ("rgb.txt", "# h\n1000.0 rgb/a.png extra\n", r"rgb.txt:2: expected 'timestamp filename'"),
        ("depth.txt", "abc depth/a.png\n", r"depth.txt:1: bad timestamp"),
        ("groundtruth.txt", "# h\n1000.0 1 2 3 0 0 0\n", r"groundtruth.txt:2: expected"),
        ("groundtruth.txt", "1000.0 1 2 3 0 0 0 0\n", r"groundtruth.txt:1: zero quaternion"),
        ("groundtruth.txt", "1000.0 nan 2 3 0 0 0 1\n", r"groundtruth.txt:1: NaN"),
        ("groundtruth.txt", "1000.0 1 2 3 0 0 x 1\n", r"groundtruth.txt:1: non-numeric"),
        ("groundtruth.txt", "# only comments\n", r"groundtruth.txt: no poses"),
        ("rgb.txt", "# only comments\n", r"rgb.txt: no frames"),
    ],
)
def test_tum_malformed_files(tmp_path, fname, content, match):
    seq = make_tum(tmp_path, n=2)
    (seq / fname).write_text(content)
    with pytest.raises(ValueError, match=match):
        TUMDataset(seq)


def test_tum_missing_files(tmp_path):
    seq = make_tum(tmp_path, n=2)
    (seq / "groundtruth.txt").unlink()  # no poses: odometry estimates them, pose_source "given" names the file
    assert not TUMDataset(seq).has_poses
    with pytest.raises(ValueError, match="groundtruth.txt"):
        load_dataset(seq, pose_source="given")
    seq = make_tum(tmp_path / "b", n=2)
    victim = sorted((seq / "rgb").iterdir())[1]
    victim.unlink()
    with pytest.raises(FileNotFoundError, match=rf"rgb.txt not found: .*{victim.name}"):
        TUMDataset(seq)
    with pytest.raises(FileNotFoundError):
        TUMDataset(tmp_path / "missing")


def test_tum_bad_arguments(tmp_path):
    seq = make_tum(tmp_path, n=2)
    with pytest.raises(ValueError, match="intrinsics override"):
        TUMDataset(seq, intrinsics=(1.0, 2.0))
    with pytest.raises(ValueError, match="distortion"):
        TUMDataset(seq, distortion=(1.0,))
    with pytest.raises(ValueError, match="max_pose_dt"):
        TUMDataset(seq, max_pose_dt=-1)


# ------------------------------------------------------------------------------------------------
# 7-Scenes
# ------------------------------------------------------------------------------------------------
def test_sevenscenes_fixture(tmp_path):
    seq = make_seven(tmp_path, n=3)
    ds = load_dataset(seq)
    assert isinstance(ds, SevenScenesDataset) and len(ds) == 3 and ds.annotations is None
    assert ds.intrinsics_path == tmp_path / "camera-intrinsics.txt"
    i = ds.intrinsics
    assert (i.fx, i.fy, i.cx, i.cy) == (30.0, 30.0, 20.0, 15.0)
    ds = SevenScenesDataset(seq, image_size=(W, H))
    f = ds[1]
    assert f.depth[0, 0] == 0 and f.depth[0, 1] == 0  # 0 and 65535 invalid
    assert f.depth[5, 5] == pytest.approx(1.501)
    np.testing.assert_array_equal(f.rgb[3, 3], [11, 100, 200])
    np.testing.assert_allclose(f.c2w, _pose(1), atol=1e-9)
    assert f.frame_id == 1 and f.name == "frame-000001" and f.timestamp == pytest.approx(1 / 30)
    d2 = SevenScenesDataset(seq, image_size=(W, H), downscale=3)[2]
    assert d2.depth.shape == (10, 13) and d2.intrinsics.fx == 10.0
    assert set(np.unique(d2.depth)) <= {0.0, np.float32(1.502)}


def test_sevenscenes_published_default_intrinsics(tmp_path):
    seq = make_seven(tmp_path, n=1, w=640, h=480, with_k=False)
    ds = SevenScenesDataset(seq, stride=1)
    i = ds.intrinsics
    assert (i.fx, i.fy, i.cx, i.cy, i.width, i.height) == (585.0, 585.0, 320.0, 240.0, 640, 480)
    assert ds[0].depth.shape == (480, 640)


def test_sevenscenes_errors(tmp_path):
    seq = make_seven(tmp_path / "a", n=2)
    (seq / "frame-000001.pose.txt").unlink()
    with pytest.raises(FileNotFoundError, match="frame-000001.pose.txt"):
        SevenScenesDataset(seq)
    seq = make_seven(tmp_path / "b", n=2)
    (seq / "frame-000000.depth.png").unlink()
    with pytest.raises(FileNotFoundError, match="frame-000000.depth.png"):
        SevenScenesDataset(seq)
    seq = make_seven(tmp_path / "c", n=2)
    (seq / "frame-000001.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1\n0 0 0 1\n")
    with pytest.raises(ValueError, match=r"frame-000001.pose.txt:3: expected 4 numbers"):
        SevenScenesDataset(seq)
    (seq / "frame-000001.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    with pytest.raises(ValueError, match=r"frame-000001.pose.txt: expected 4 rows"):
        SevenScenesDataset(seq)
    (seq / "frame-000001.pose.txt").write_text("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(ValueError, match=r"frame-000001.pose.txt: .*non-rigid"):
        SevenScenesDataset(seq)
    seq = make_seven(tmp_path / "d", n=1)
    (seq.parent / "camera-intrinsics.txt").write_text("30 0 20\n0 30 15\n")
    with pytest.raises(ValueError, match=r"camera-intrinsics.txt: expected 3 rows"):
        SevenScenesDataset(seq)
    (seq.parent / "camera-intrinsics.txt").write_text("30 0 20\n0 30 15\n1 0 1\n")
    with pytest.raises(ValueError, match=r"camera-intrinsics.txt: not a pinhole K"):
        SevenScenesDataset(seq)
    empty = tmp_path / "e"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match="no colour frames"):
        SevenScenesDataset(empty)


# ------------------------------------------------------------------------------------------------
# factory
# ------------------------------------------------------------------------------------------------
def test_factory_detection_and_kinds(tmp_path):
    rep = make_replica(tmp_path / "r")
    tum = make_tum(tmp_path / "t", n=2)
    sev = make_seven(tmp_path / "s", n=1)
    assert detect_layout(rep) == ("replica", rep)
    assert detect_layout(rep.parent) == ("replica", rep)
    assert detect_layout(tum) == ("tum", tum)
    assert detect_layout(sev) == ("7scenes", sev)
    assert isinstance(load_dataset(sev, kind="sevenscenes"), SevenScenesDataset)
    assert isinstance(load_dataset(tum, kind="tum", intrinsics=(30, 30, 19.5, 14.5)), TUMDataset)
    assert len(load_dataset(rep, kind="replica", max_frames=2)) == 2
    with pytest.raises(ValueError, match="unknown dataset kind"):
        load_dataset(rep, kind="kitti")
    other = tmp_path / "other"
    other.mkdir()
    with pytest.raises(ValueError, match="unknown dataset layout"):
        load_dataset(other)
    with pytest.raises(FileNotFoundError):
        load_dataset(tmp_path / "missing")


@pytest.mark.parametrize("kw", [{"stride": 0}, {"stride": 1.5}, {"max_frames": 0}, {"downscale": 0.5},
                                {"downscale": float("nan")}, {"downscale": "2"}, {"downscale": True}])
def test_factory_bad_arguments(tmp_path, kw):
    rep = make_replica(tmp_path)
    with pytest.raises(ValueError):
        load_dataset(rep, **kw)
