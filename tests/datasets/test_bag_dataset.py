"""ROS bags as datasets: small bags written in tmp dirs with rosbags (MCAP, SQLite3, ROS 1), every
encoding / format, pose sources, registration and every error path of gausslite.datasets.bag."""

from __future__ import annotations

import logging
import math

import cv2
import numpy as np
import pytest

from gausslite.camera import Intrinsics
from gausslite.cli import main
from gausslite.datasets import detect_layout, load_dataset
from gausslite.datasets.bag import BagDataset, BagError, BagOptions
from gausslite.datasets.registration import DepthCamera, register_depth
from gausslite.ros.bagio import BagWriter, is_bag_path
from gausslite.ros.images import encode_compressed, encode_compressed_depth
from gausslite.ros.transforms import R_BODY_OPTICAL, make_transform

W, H = 32, 24
INTR = Intrinsics(30.0, 31.0, 15.5, 11.5, W, H)
T0 = 100.0
N = 4
OPT = "camera_color_optical_frame"
T_MAP_ODOM = make_transform([1.0, 2.0, 0.0], [0.0, 0.0, math.sin(0.1), math.cos(0.1)])
T_BASE_OPT = np.eye(4)
T_BASE_OPT[:3, :3] = R_BODY_OPTICAL
T_BASE_OPT[:3, 3] = [0.1, 0.0, 0.4]


def stamp(k: int) -> float:
    return T0 + k / 30.0


def odom_base(t: float) -> np.ndarray:
    """Constant-rate motion: linear interpolation + slerp of any two samples is exact."""
    s = t - T0
    a = 0.6 * s
    return make_transform([0.9 * s, 0.3 * s, 0.0], [0.0, 0.0, math.sin(a / 2), math.cos(a / 2)])


def expected_c2w(k: int, world: str = "map") -> np.ndarray:
    T = odom_base(stamp(k)) @ T_BASE_OPT
    return T_MAP_ODOM @ T if world == "map" else T


def rgb_img(k: int) -> np.ndarray:
    return np.random.default_rng(k).integers(0, 256, size=(H, W, 3), dtype=np.uint8)


def depth_img(k: int) -> np.ndarray:
    v, u = np.mgrid[0:H, 0:W]
    d = (1.0 + 0.1 * k + 0.01 * u + 0.005 * v).astype(np.float32)
    d = np.round(d * 1000) / 1000  # whole millimetres: 16UC1 is exact too
    d[0, 0] = 0.0
    return d.astype(np.float32)


def make_bag(path, storage="mcap", *, rgb="rgb8", depth="32FC1", poses="tf", rgb_topic="/camera/color/image_raw",
             depth_topic="/camera/aligned_depth_to_color/image_raw", info_topic="/camera/color/camera_info",
             distortion=(0.0,) * 5, tf_times=None, n=N, extra=None, map_frame=True, depth_frame=OPT):
    """A small bag: N colour/depth pairs with CameraInfo and poses from TF ("tf"), a PoseStamped ("pose"),
    an Odometry ("odom") or nothing ("none")."""
    with BagWriter(path, storage) as w:
        if poses == "tf":
            static = [("base_link", "camera_link", make_transform(T_BASE_OPT[:3, 3], [0, 0, 0, 1])),
                      ("camera_link", OPT, make_transform([0, 0, 0], [-0.5, 0.5, -0.5, 0.5]))]
            if map_frame:
                static.append(("map", "odom", T_MAP_ODOM))
            w.write_tf(T0 - 0.05, static, static=True)
            for t in (tf_times if tf_times is not None else T0 - 0.03 + 0.01 * np.arange(20)):
                w.write_tf(float(t), [("odom", "base_link", odom_base(float(t)))])
        for k in range(n):
            t = stamp(k)
            if poses == "pose":
                w.write_pose("/camera/pose", t, "map", expected_c2w(k))
            elif poses == "odom":
                w.write_odometry("/odom", t, "odom", "base_link", odom_base(t))
            if info_topic:
                w.write_camera_info(info_topic, t, OPT, INTR, distortion)
            if rgb in ("jpeg", "png"):
                fmt, data = encode_compressed(rgb_img(k), rgb)
                w.write_compressed(rgb_topic, t, OPT, fmt, data)
            else:
                w.write_image(rgb_topic, t, OPT, rgb_img(k), rgb)
            if depth.startswith("compressedDepth"):
                fmt, data = encode_compressed_depth(depth_img(k), depth.split()[-1])
                w.write_compressed(depth_topic, t + 0.005, depth_frame, fmt, data)
            else:
                w.write_image(depth_topic, t + 0.005, depth_frame, depth_img(k), depth)
            if extra is not None:
                extra(w, k, t)
    return path


def _bag(tmp_path, name="b", storage="mcap", **kw):
    p = tmp_path / (name + (".bag" if storage == "ros1" else ""))
    return make_bag(p, storage, **kw)


# ---------------------------------------------------------------------------------------------- formats
@pytest.mark.parametrize("storage", ["mcap", "sqlite3", "ros1"])
def test_storage_formats_images_intrinsics_and_tf_poses(tmp_path, storage):
    p = _bag(tmp_path, storage=storage)
    assert is_bag_path(p) and detect_layout(p) == ("bag", p)
    ds = load_dataset(p)
    assert isinstance(ds, BagDataset) and len(ds) == N
    assert ds.intrinsics == INTR and ds.pose_topic == "tf" and ds.world_frame == "map" and ds.camera_frame == OPT
    with pytest.warns(DeprecationWarning, match="renamed pose_topic"):
        assert ds.pose_source == "tf"  # the old name still reads, with a warning
    for k, fr in enumerate(ds):
        assert np.array_equal(fr.rgb, rgb_img(k))
        assert fr.depth.dtype == np.float32 and np.array_equal(fr.depth, depth_img(k))
        assert np.allclose(fr.c2w, expected_c2w(k), atol=1e-9)  # TF at 100 Hz interpolated at the image stamps
        assert fr.timestamp == pytest.approx(stamp(k), abs=1e-6) and fr.frame_id == k
    ds.close()
    assert np.array_equal(ds[1].rgb, rgb_img(1))  # the reader reopens after close()


def test_single_storage_files_are_bags(tmp_path):
    p = _bag(tmp_path, name="dir")
    mcap = next(p.glob("*.mcap"))
    ds = load_dataset(mcap)
    assert len(ds) == N and np.array_equal(ds[2].depth, depth_img(2))


@pytest.mark.parametrize("enc", ["bgr8", "rgba8", "bgra8", "mono8"])
def test_colour_encodings(tmp_path, enc):
    ds = load_dataset(_bag(tmp_path, rgb=enc, depth="16UC1"))
    fr = ds[1]
    if enc == "mono8":
        grey = np.round(rgb_img(1).astype(np.float32).mean(axis=2)).astype(np.uint8)
        assert all(np.array_equal(fr.rgb[..., c], grey) for c in range(3))
    else:
        assert np.array_equal(fr.rgb, rgb_img(1))
    assert np.allclose(fr.depth, depth_img(1), atol=1e-6)  # 16UC1 millimetres


@pytest.mark.parametrize("rgb,depth,tol", [("png", "compressedDepth 16UC1", 0.0), ("jpeg", "compressedDepth 32FC1", 3e-4)])
def test_compressed_topics(tmp_path, rgb, depth, tol):
    p = _bag(tmp_path, rgb=rgb, depth=depth, rgb_topic="/camera/color/image_raw/compressed",
             depth_topic="/camera/aligned_depth_to_color/image_raw/compressedDepth")
    ds = load_dataset(p)
    assert ds.camera_info_topic == "/camera/color/camera_info"
    fr = ds[2]
    if rgb == "png":
        assert np.array_equal(fr.rgb, rgb_img(2))
    else:  # jpeg of random noise is lossy: check it is the same picture
        assert np.corrcoef(fr.rgb.ravel().astype(float), rgb_img(2).ravel().astype(float))[0, 1] > 0.5
    assert np.abs(fr.depth - depth_img(2)).max() <= tol + 1e-7


def test_downscale_stride_max_frames(tmp_path):
    ds = load_dataset(_bag(tmp_path), downscale=2, stride=2, max_frames=1)
    assert len(ds) == 1 and ds.intrinsics == INTR.scaled(2)
    fr = ds[0]
    assert fr.rgb.shape == (H // 2, W // 2, 3) and fr.depth.shape == (H // 2, W // 2)
    ds2 = load_dataset(_bag(tmp_path, name="c"), stride=2)
    assert ds2.frame_ids == [0, 2] and np.allclose(ds2[1].c2w, expected_c2w(2), atol=1e-9)


# ---------------------------------------------------------------------------------------------- poses
def test_pose_stamped_topic_without_tf(tmp_path):
    ds = load_dataset(_bag(tmp_path, poses="pose"))
    assert ds.pose_topic == "/camera/pose" and ds.world_frame == "map"
    for k in range(N):
        assert np.allclose(ds[k].c2w, expected_c2w(k), atol=1e-9)


def test_odometry_topic_composed_with_static_tf(tmp_path):
    def static(w, k, t):
        if k == 0:
            w.write_tf(t, [("base_link", OPT, T_BASE_OPT)], static=True)

    ds = load_dataset(_bag(tmp_path, poses="odom", extra=static))
    assert ds.pose_topic == "/odom" and ds.world_frame == "odom"
    for k in range(N):
        assert np.allclose(ds[k].c2w, expected_c2w(k, "odom"), atol=1e-9)


def test_world_frame_defaults_and_override(tmp_path):
    assert load_dataset(_bag(tmp_path, name="m")).world_frame == "map"
    ds = load_dataset(_bag(tmp_path, name="o", map_frame=False))
    assert ds.world_frame == "odom" and np.allclose(ds[1].c2w, expected_c2w(1, "odom"), atol=1e-9)
    ds = load_dataset(_bag(tmp_path, name="w"), bag={"world_frame": "odom"})
    assert np.allclose(ds[1].c2w, expected_c2w(1, "odom"), atol=1e-9)
    # a PoseStamped topic re-expressed in another world frame through TF
    ds = load_dataset(_bag(tmp_path, name="p", poses="pose", extra=lambda w, k, t: k == 0 and w.write_tf(
        t, [("odom", "map", np.linalg.inv(T_MAP_ODOM))], static=True)), bag={"world_frame": "odom"})
    assert np.allclose(ds[1].c2w, expected_c2w(1, "odom"), atol=1e-9)


def test_frames_without_pose_are_dropped_with_a_warning(tmp_path, caplog):
    tf_times = T0 + 1.0 / 30.0 + 0.01 * np.arange(15)  # TF starts at the second image
    with caplog.at_level(logging.WARNING):
        ds = load_dataset(_bag(tmp_path, tf_times=tf_times), bag={"max_pose_dt": 0.02})
    assert len(ds) == N - 1 and ds.n_dropped == 1 and ds.frame_ids == [1, 2, 3]
    assert "dropped 1 of 4 colour frames" in caplog.text


def test_distortion_is_undistorted_like_the_tum_loader(tmp_path):
    dist = (0.05, -0.02, 0.001, 0.0005, 0.0)
    p = _bag(tmp_path, distortion=dist)
    ds = load_dataset(p)
    new_k, _ = cv2.getOptimalNewCameraMatrix(INTR.K, np.asarray(dist), (W, H), 0.0)
    assert np.allclose(ds.intrinsics.K, new_k) and ds.raw_intrinsics == INTR
    mx, my = cv2.initUndistortRectifyMap(INTR.K, np.asarray(dist), None, new_k, (W, H), cv2.CV_32FC1)
    fr = ds[0]
    assert np.array_equal(fr.rgb, cv2.remap(rgb_img(0), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT))
    assert np.array_equal(fr.depth, cv2.remap(depth_img(0), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT))
    raw = load_dataset(p, bag={"undistort": False})
    assert raw.intrinsics == INTR and np.array_equal(raw[0].rgb, rgb_img(0))


def test_unregistered_depth_is_registered_with_tf_extrinsic(tmp_path):
    from gausslite.synthetic.raycast import render
    from gausslite.synthetic.scene import build_default_scene
    from gausslite.synthetic.trajectories import make_trajectories

    ci = Intrinsics(525 / 8, 525 / 8, 319.5 / 8, 239.5 / 8, 80, 60)
    di = Intrinsics(585 / 8, 585 / 8, 319.5 / 8, 239.5 / 8, 80, 60)
    T_cd = make_transform([-0.025, 0.0, 0.0], [0, 0, 0, 1])
    scene = build_default_scene(0)
    c2w = make_trajectories(3, 0)["agent_a"]
    p = tmp_path / "unreg"
    with BagWriter(p, "mcap") as w:
        w.write_tf(T0, [("camera_link", "cam_rgb_optical", make_transform([0, 0, 0], [-0.5, 0.5, -0.5, 0.5])),
                        ("cam_rgb_optical", "cam_depth_optical", T_cd)], static=True)
        for k in range(3):
            t = stamp(k)
            w.write_tf(t, [("map", "camera_link", c2w[k] @ np.linalg.inv(make_transform([0, 0, 0], [-0.5, 0.5, -0.5, 0.5])))])
            col = render(scene, ci, c2w[k])
            dep = render(scene, di, c2w[k] @ T_cd).depth.astype(np.float32)
            w.write_camera_info("/cam/color/camera_info", t, "cam_rgb_optical", ci)
            w.write_camera_info("/cam/depth/camera_info", t, "cam_depth_optical", di)
            w.write_image("/cam/color/image_raw", t, "cam_rgb_optical", col.rgb, "rgb8")
            w.write_image("/cam/depth/image_raw", t, "cam_depth_optical", dep, "32FC1")
    ds = load_dataset(p)
    assert not ds.registered and ds.depth_camera_info_topic == "/cam/depth/camera_info" and ds.depth_intrinsics == di
    assert np.allclose(ds.depth_camera_at(stamp(0)).T_color_depth, T_cd)
    fr = ds[1]
    dep = render(scene, di, c2w[1] @ T_cd).depth.astype(np.float32)
    assert np.array_equal(fr.depth, register_depth(dep, DepthCamera(di, T_cd), ci))
    direct = render(scene, ci, c2w[1]).depth
    ok = fr.depth > 0
    assert ok.mean() > 0.7 and np.median(np.abs(fr.depth - direct)[ok]) < 0.02
    assert np.allclose(fr.c2w, c2w[1], atol=1e-9)


# ---------------------------------------------------------------------------------------------- errors
def _err(path, **opts) -> str:
    with pytest.raises(BagError) as ei:
        load_dataset(path, bag=opts)
    msg = str(ei.value)
    assert "topics found:" in msg and "TF frames found:" in msg  # one error that lists what the bag holds
    return msg


def test_error_missing_and_wrong_type_topics(tmp_path):
    p = _bag(tmp_path)
    msg = _err(p, rgb_topic="/nope")
    assert "rgb topic '/nope' is not in the bag" in msg and "/camera/color/image_raw  [sensor_msgs/msg/Image, 4" in msg
    assert "camera_color_optical_frame" in msg
    assert "has type sensor_msgs/msg/CameraInfo" in _err(p, rgb_topic="/camera/color/camera_info")
    assert "holds depth images, not color" in _err(p, rgb_topic="/camera/aligned_depth_to_color/image_raw")
    assert "pose topic '/x' is not in the bag" in _err(p, pose_topic="/x")


def test_error_ambiguous_topics(tmp_path):
    def second(w, k, t):
        w.write_image("/camera2/color/image_raw", t, "cam2", rgb_img(k), "rgb8")

    msg = _err(_bag(tmp_path, extra=second))
    assert "several rgb topics (/camera/color/image_raw, /camera2/color/image_raw); choose one with --rgb-topic" in msg
    ds = load_dataset(tmp_path / "b", bag={"rgb_topic": "/camera/color/image_raw"})
    assert len(ds) == N


def test_error_unknown_encoding(tmp_path):
    p = _bag(tmp_path, extra=None)
    bad = tmp_path / "yuv"
    with BagWriter(bad, "mcap") as w:
        from gausslite.ros.images import encode_image

        for k in range(2):
            h, ww, step, data = encode_image(rgb_img(k), "rgb8")
            msg = w._t("sensor_msgs/msg/Image")(header=w.header(stamp(k), OPT), height=h, width=ww, encoding="yuv422",
                                                is_bigendian=0, step=step, data=np.frombuffer(data, np.uint8))
            w.write("/camera/color/image_raw", "sensor_msgs/msg/Image", msg, stamp(k))
            w.write_image("/depth", stamp(k), OPT, depth_img(k), "32FC1")
    msg = _err(bad)
    assert "no rgb topic found" in msg and "unsupported image encoding 'yuv422'" in msg
    assert "unsupported image encoding 'yuv422'" in _err(bad, rgb_topic="/camera/color/image_raw")
    assert len(load_dataset(p)) == N


def test_error_disconnected_tf_chain(tmp_path):
    def other_tree(w, k, t):
        if k == 0:
            w.write_tf(t, [("rig", "other_optical", np.eye(4))], static=True)

    msg = _err(_bag(tmp_path, extra=other_tree), camera_frame="other_optical")
    assert "TF chain 'map' <- 'other_optical' does not connect" in msg and "rooted at 'rig'" in msg
    msg = _err(tmp_path / "b", world_frame="rig")
    assert "TF chain 'rig' <- 'camera_color_optical_frame' does not connect" in msg


def test_error_no_pose_within_tolerance(tmp_path):
    msg = _err(_bag(tmp_path, tf_times=[T0 + 5.0, T0 + 5.01]))
    assert "no colour frame of '/camera/color/image_raw' has depth and a pose within tolerance" in msg
    assert "no transform 'odom' -> 'base_link' within 0.05 s" in msg


def test_error_no_depth_within_tolerance(tmp_path):
    msg = _err(_bag(tmp_path), max_depth_dt=0.001)
    assert "no depth within 0.001 s" in msg


def test_error_no_poses_at_all_and_no_camera_info(tmp_path):
    msg = _err(_bag(tmp_path, name="np", poses="none"))
    assert "no poses: the camera frame 'camera_color_optical_frame' is not in the TF tree" in msg
    msg = _err(_bag(tmp_path, name="ni", info_topic=None))
    assert "no camera info topic found" in msg and "--camera-info-topic" in msg


def test_error_unregistered_depth_without_info_or_tf(tmp_path):
    def dinfo(w, k, t):
        w.write_camera_info("/camera/depth/camera_info", t, "depth_optical", INTR)

    msg = _err(_bag(tmp_path, name="a", depth_frame="depth_optical", extra=dinfo))
    assert "no TF chain between the depth frame 'depth_optical' and the colour frame" in msg
    msg = _err(_bag(tmp_path, name="b2", depth_frame="depth_optical"))
    assert "no CameraInfo of the depth camera was found" in msg


def test_error_not_a_bag_and_corrupt_bag(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x00" * 64)
    with pytest.raises(BagError, match="cannot read bag"):
        load_dataset(junk)
    with pytest.raises(FileNotFoundError):
        BagDataset(tmp_path / "missing.bag")
    with pytest.raises(ValueError, match="not a bag"):
        BagDataset(tmp_path)
    with pytest.raises(ValueError, match="Extra inputs are not permitted"):
        BagOptions(rgb_topics="/x")


def test_bag_options_rejected_for_folder_datasets(tmp_path):
    from tests.datasets.test_datasets_fixtures import make_seven

    seq = make_seven(tmp_path)
    with pytest.raises(ValueError, match=r"bag options \(rgb_topic\) apply to ROS bags only"):
        load_dataset(seq, bag={"rgb_topic": "/x"})
    assert len(load_dataset(seq, bag=BagOptions())) == 3  # defaults are fine (the agent passes them)


def test_cli_map_reports_one_clear_error(tmp_path, caplog):
    p = _bag(tmp_path)
    with caplog.at_level(logging.ERROR):
        rc = main(["map", "--dataset", str(p), "--rgb-topic", "/nope", "--out", str(tmp_path / "out")])
    assert rc == 2
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "rgb topic '/nope' is not in the bag" in errors[0].getMessage()
    from tests.datasets.test_datasets_fixtures import make_seven

    seq = make_seven(tmp_path / "seven")
    with caplog.at_level(logging.ERROR):
        rc = main(["map", "--dataset", str(seq), "--rgb-topic", "/x", "--out", str(tmp_path / "o2")])
    assert rc == 2 and "apply to ROS bags only" in caplog.text
