"""Any camera's files (gausslite.datasets.camera_folder, camera_file): a folder of colour and depth images with a
camera file, with and without a trajectory, with distortion; a camera file beside a TUM sequence; every bad input
gives one line naming the file and the field."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from gausslite.camera import Intrinsics
from gausslite.datasets import detect_layout, load_dataset
from gausslite.datasets.camera_file import read_camera_file
from gausslite.datasets.camera_folder import CameraFolderDataset
from gausslite.odometry.rgbd import OdometryDataset
from gausslite.datasets.trajectory import write_tum_trajectory

W, H = 48, 36
INTR = Intrinsics(40.0, 41.0, 23.5, 17.5, W, H)


def _pose(k: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [0.01 * k, 0.0, 0.0]
    return T


def make_folder(root, n=4, names=None, camera="camera.yaml", traj=False, scale=1000.0, size=(W, H), extra=""):
    """A camera folder of ``n`` frames: colour gradients and a depth ramp (metres = 1 + 0.01 * column)."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "rgb").mkdir()
    (root / "depth").mkdir()
    names = names or [f"{k:06d}" for k in range(n)]
    w, h = size
    for k, name in enumerate(names):
        rgb = np.zeros((h, w, 3), np.uint8)
        rgb[..., 0] = np.arange(w, dtype=np.uint8)[None] * 4
        rgb[..., 1] = 10 * k
        cv2.imwrite(str(root / "rgb" / f"{name}.png"), rgb[..., ::-1])
        depth_m = 1.0 + 0.01 * np.arange(w)[None].repeat(h, 0)
        cv2.imwrite(str(root / "depth" / f"{name}.png"), np.round(depth_m * scale).astype(np.uint16))
    cam = {"width": W, "height": H, "fx": INTR.fx, "fy": INTR.fy, "cx": INTR.cx, "cy": INTR.cy,
           "depth_scale": scale}
    text = json.dumps(cam) if camera.endswith(".json") else "".join(f"{k}: {v}\n" for k, v in cam.items()) + extra
    (root / camera).write_text(text)
    if traj:
        write_tum_trajectory(root / "trajectory.txt", np.arange(n) / 30.0, np.stack([_pose(k) for k in range(n)]))
    return root


def test_a_folder_without_poses_is_a_dataset_with_odometry(tmp_path):
    root = make_folder(tmp_path / "mine")
    assert detect_layout(root) == ("camera", root)
    raw = CameraFolderDataset(root)
    assert not raw.has_poses and len(raw) == 4 and raw.intrinsics == INTR
    f = raw[1]
    assert f.rgb.shape == (H, W, 3) and f.depth.dtype == np.float32
    assert np.allclose(f.depth[0, :3], [1.0, 1.01, 1.02], atol=1e-3) and f.rgb[0, 1, 0] == 4 and f.rgb[0, 0, 1] == 10
    assert np.isclose(f.timestamp, 1 / 30.0)
    ds = load_dataset(root, progress=False)
    assert isinstance(ds, OdometryDataset) and ds.reference_poses is None
    with pytest.raises(ValueError, match="trajectory.txt not found"):
        load_dataset(root, pose_source="given")


def test_a_trajectory_gives_the_poses_and_a_half_size_downscale(tmp_path):
    root = make_folder(tmp_path / "mine", camera="camera.json", traj=True)
    ds = load_dataset(root, downscale=2)
    assert ds.has_poses and not isinstance(ds, OdometryDataset)
    assert np.allclose(ds[3].c2w, _pose(3)) and ds[3].rgb.shape == (H // 2, W // 2, 3)
    assert ds.intrinsics == INTR.scaled(2)


def test_time_stems_pair_by_name_and_give_the_timestamps(tmp_path):
    names = ["1305031102.175304", "1305031102.211214", "1305031102.243211"]
    root = make_folder(tmp_path / "mine", names=names)
    (root / "depth" / f"{names[1]}.png").rename(root / "depth" / "1305031102.211999.png")  # 3 and 3: by order
    ds = CameraFolderDataset(root)
    assert np.allclose(ds.timestamps, [float(n) for n in names])


def test_distortion_undistorts_onto_the_optimal_pinhole_camera(tmp_path):
    root = make_folder(tmp_path / "mine", extra="distortion: [0.1, -0.05, 0.0, 0.0, 0.0]\n")
    ds = CameraFolderDataset(root)
    assert ds.undistort and ds.raw_intrinsics == INTR and ds.intrinsics != INTR
    f = ds[0]
    assert f.rgb.shape == (H, W, 3) and (f.depth > 0).mean() > 0.9


@pytest.mark.parametrize("edit, field", [
    (lambda c: c.pop("fx"), "field 'fx' is missing"),
    (lambda c: c.update(fy="abc"), "field 'fy' must be a positive number"),
    (lambda c: c.update(width=40.5), "field 'width' must be an integer"),
    (lambda c: c.update(depth_scale=0), "field 'depth_scale' must be a positive number"),
    (lambda c: c.update(distortion=[1, 2]), "field 'distortion' must be"),
    (lambda c: c.update(focal=3), "unknown field 'focal'"),
])
def test_a_bad_camera_file_names_the_file_and_the_field(tmp_path, edit, field):
    root = make_folder(tmp_path / "mine", camera="camera.json")
    cam = json.loads((root / "camera.json").read_text())
    edit(cam)
    (root / "camera.json").write_text(json.dumps(cam))
    with pytest.raises(ValueError, match=field) as e:
        load_dataset(root)
    assert str(root / "camera.json") in str(e.value) and "\n" not in str(e.value)


def test_unreadable_yaml_and_images_of_another_size(tmp_path):
    root = make_folder(tmp_path / "a")
    (root / "camera.yaml").write_text("width: [1\n")
    with pytest.raises(ValueError, match=r"camera.yaml: not valid YAML"):
        read_camera_file(root / "camera.yaml")
    root = make_folder(tmp_path / "b", size=(W + 2, H))
    with pytest.raises(ValueError, match=r"camera.yaml says width 48, height 36"):
        CameraFolderDataset(root)[0]


def test_unpaired_images_name_the_folder(tmp_path):
    root = make_folder(tmp_path / "mine")
    (root / "depth" / "000002.png").unlink()
    with pytest.raises(ValueError, match="cannot be paired"):
        CameraFolderDataset(root)


def test_a_camera_file_beside_a_tum_sequence_overrides_its_camera(tmp_path):
    seq = tmp_path / "rgbd_dataset_freiburg1_mine"
    make_folder(seq, n=3, names=["1.000000", "1.033333", "1.066667"], scale=5000.0 / 2)
    for kind in ("rgb", "depth"):
        lines = [f"{n[:-4]} {kind}/{n}" for n in sorted(p.name for p in (seq / kind).iterdir())]
        (seq / f"{kind}.txt").write_text("# header\n" + "\n".join(lines) + "\n")
    assert detect_layout(seq)[0] == "tum"  # rgb.txt and depth.txt win over the camera folder
    ds = load_dataset(seq, progress=False)
    assert isinstance(ds, OdometryDataset) and ds.intrinsics == INTR and ds.depth_scale == 2500.0
    assert np.allclose(ds.base[0].depth[0, :2], [1.0, 1.01], atol=1e-3)
