"""Dataset loaders on the real research data in ../shared/datasets (skipped when absent, fail under CI)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gausslite.camera import check_rigid
from gausslite.datasets import ReplicaDataset, TUMDataset, load_dataset
from gausslite.datasets.tum import quat_to_rot

pytestmark = pytest.mark.shared


def _check_frame(f, w, h):
    assert f.rgb.shape == (h, w, 3) and f.rgb.dtype == np.uint8
    assert f.depth.shape == (h, w) and f.depth.dtype == np.float32
    assert f.c2w.shape == (4, 4) and f.c2w.dtype == np.float64
    check_rigid(f.c2w)
    assert (f.intrinsics.width, f.intrinsics.height) == (w, h)
    assert np.all(f.depth >= 0) and np.all(np.isfinite(f.depth))


def test_room0_full_resolution(room0_dir):
    ds = load_dataset(room0_dir)
    assert isinstance(ds, ReplicaDataset)
    assert len(ds) == 20 and ds.name == "room0"
    i = ds.intrinsics
    assert (i.width, i.height, i.fx, i.fy, i.cx, i.cy) == (1200, 680, 600.0, 600.0, 599.5, 339.5)
    assert ds.depth_scale == 6553.5
    for k in (0, 19):
        f = ds[k]
        _check_frame(f, 1200, 680)
        assert f.frame_id == k and f.name == f"frame{k:06d}"
    for T in ds.poses:
        check_rigid(T)
    # depth = raw / 6553.5, rendered depth is dense
    raw = cv2.imread(str(room0_dir / "results" / "depth000000.png"), cv2.IMREAD_UNCHANGED)
    f0 = ds[0]
    np.testing.assert_allclose(f0.depth, raw / 6553.5, rtol=1e-6)
    assert (f0.depth > 0).mean() > 0.99
    # colour is RGB order
    bgr = cv2.imread(str(room0_dir / "results" / "frame000000.jpg"))
    np.testing.assert_array_equal(f0.rgb, bgr[..., ::-1])
    # first pose = first line of traj.txt
    first = np.array(open(room0_dir / "traj.txt").readline().split(), dtype=float).reshape(4, 4)
    np.testing.assert_array_equal(f0.c2w, first)
    assert ds.annotations is not None


def test_room0_downscale_4(room0_dir):
    ds = load_dataset(room0_dir.parent, downscale=4)  # parent folder with cam_params.json resolves
    assert ds.path == room0_dir
    i = ds.intrinsics
    assert (i.width, i.height) == (300, 170) and i.fx == 150.0 and i.fy == 150.0
    assert i.cx == pytest.approx((599.5 + 0.5) / 4 - 0.5) and i.cy == pytest.approx((339.5 + 0.5) / 4 - 0.5)
    f = ds[3]
    _check_frame(f, 300, 170)
    full = ReplicaDataset(room0_dir)[3]
    # every downscaled depth value comes from its 4x4 source block
    blocks = full.depth.reshape(170, 4, 300, 4).transpose(0, 2, 1, 3).reshape(170, 300, 16)
    assert np.all(np.any(blocks == f.depth[..., None], axis=-1))


def test_room0_stride_and_max_frames(room0_dir):
    ds = load_dataset(room0_dir, stride=3, max_frames=4)
    assert [ds[k].frame_id for k in range(len(ds))] == [0, 3, 6, 9]
    full = load_dataset(room0_dir)
    np.testing.assert_array_equal(ds.poses[2], full.poses[6])
    assert ds[1].timestamp == pytest.approx(3 / 30.0)


def test_office0_more_poses_than_frames(office0_dir):
    lines = [ln for ln in open(office0_dir / "traj.txt") if ln.strip()]
    assert len(lines) == 2000
    ds = load_dataset(office0_dir)
    assert len(ds) == 4 and ds.annotations is None
    for k in range(4):
        _check_frame(ds[k], 1200, 680)
        np.testing.assert_array_equal(ds[k].c2w, np.array(lines[k].split(), dtype=float).reshape(4, 4))


def test_tum_fr1_rpy(tum_rpy_dir):
    ds = load_dataset(tum_rpy_dir)
    assert isinstance(ds, TUMDataset)
    assert len(ds) == 150 and ds.n_dropped == 0 and ds.freiburg == 1
    i = ds.intrinsics
    assert (i.fx, i.fy, i.cx, i.cy, i.width, i.height) == (517.3, 516.5, 318.6, 255.3, 640, 480)
    assert np.all(np.diff(ds.timestamps) > 0)
    assert ds.frame_ids[:3] == [0, 1, 2]  # indices into the (already subsampled) rgb.txt
    for T in ds.poses:
        check_rigid(T)
    f = ds[0]
    _check_frame(f, 640, 480)
    assert f.timestamp == pytest.approx(1305031229.528748)
    raw = cv2.imread(str(ds.depth_paths[0]), cv2.IMREAD_UNCHANGED)
    np.testing.assert_allclose(f.depth, raw / 5000.0, rtol=1e-6)
    assert ds.depth_paths[0].name == "1305031229.528784.png"
    # pose = nearest groundtruth line (1305031229.5284 or ...5334 etc.), quaternion scalar-last
    gt = np.loadtxt(tum_rpy_dir / "groundtruth.txt", comments="#")
    g = gt[np.argmin(np.abs(gt[:, 0] - f.timestamp))]
    assert abs(g[0] - f.timestamp) <= 0.005  # README: largest rgb-groundtruth gap 5 ms
    np.testing.assert_allclose(f.c2w[:3, 3], g[1:4])
    np.testing.assert_allclose(f.c2w[:3, :3], quat_to_rot(g[4:8]), atol=1e-12)
    # camera +y (down) points roughly to world -z (up axis +z)
    assert np.mean([T[2, 1] for T in ds.poses]) < 0


def test_tum_downscale_options(tum_rpy_dir):
    ds = TUMDataset(tum_rpy_dir, downscale=2.5, max_frames=3, stride=50, interpolate_poses=True)
    assert len(ds) == 3 and ds.frame_ids == [0, 50, 100]
    f = ds[1]
    _check_frame(f, 256, 192)
    near = TUMDataset(tum_rpy_dir, max_frames=3, stride=50)
    # interpolated poses differ from nearest-sample poses by less than one 10 ms step of motion
    assert np.max(np.abs(ds.poses[:, :3, 3] - near.poses[:, :3, 3])) < 0.01
    und = TUMDataset(tum_rpy_dir, max_frames=1, undistort=True)[0]
    dist = near[0]
    assert und.rgb.shape == dist.rgb.shape
    # nearest-neighbour undistortion keeps measured values only
    assert np.isin(und.depth[und.depth > 0], dist.depth[dist.depth > 0]).all()


# ------------------------------------------------------------------------------------------------
# published ROI pixel fractions (shared/datasets/*/README.md, "mean over all frames (min-max)")
# Computed over ALL frames at full resolution. The README values are rounded to 0.01 percentage
# points, so they are within 0.005 pp of the exact figure; 0.01 pp tolerance adds 0.005 pp of slack
# for float32/float64 rounding of points that lie exactly on a box face.
# ------------------------------------------------------------------------------------------------
ROOM0_ROI = {
    "room0-pick-plant": (2.62, 2.49, 2.79),
    "room0-find-books": (0.18, 0.18, 0.19),
    "room0-find-ottoman": (5.56, 5.47, 5.91),
    "room0-nav-door": (21.29, 20.09, 21.68),
    "room0-map-ottomans": (6.46, 5.67, 6.76),
}
TUM_ROI = {
    "tum-pick-cup": (40.27, 0.66, 68.54),
    "tum-find-mouse": (5.37, 0.00, 11.20),
    "tum-reach-keyboard": (8.07, 0.00, 16.69),
    "tum-map-monitors": (8.72, 0.00, 21.88),
    "tum-pick-gamepad": (0.50, 0.00, 2.37),
}


def _roi_fractions(ds):
    ann = ds.annotations
    out = {t.id: [] for t in ann.tasks}
    for f in ds:
        for t in ann.tasks:
            out[t.id].append(100.0 * ann.roi_mask(t.id, f.depth, f.c2w, f.intrinsics).mean())
    return {k: np.asarray(v) for k, v in out.items()}


@pytest.mark.parametrize("which", ["room0", "tum"])
def test_published_roi_fractions(which, room0_dir, tum_rpy_dir):
    ds = load_dataset(room0_dir if which == "room0" else tum_rpy_dir)
    expected = ROOM0_ROI if which == "room0" else TUM_ROI
    got = _roi_fractions(ds)
    assert set(got) == set(expected)
    for tid, (mean, lo, hi) in expected.items():
        v = got[tid]
        assert abs(v.mean() - mean) <= 0.01, (tid, v.mean(), mean)
        assert abs(v.min() - lo) <= 0.01, (tid, v.min(), lo)
        assert abs(v.max() - hi) <= 0.01, (tid, v.max(), hi)

