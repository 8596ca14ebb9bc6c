"""RealSense recordings (gausslite.datasets.realsense): a tiny bag in the RealSense Viewer / rs-record layout written
with rosbags' ROS 1 writer; depth units from the sensor option; depth registered to the colour camera with the
bag's extrinsics; the layout detected; missing topics named."""

from __future__ import annotations

import numpy as np
import pytest

from gausslite.camera import Intrinsics
from gausslite.datasets import detect_layout, load_dataset
from gausslite.odometry.rgbd import OdometryDataset
from gausslite.datasets.realsense import RealSenseBagDataset, is_realsense_bag
from gausslite.datasets.registration import DepthCamera, register_depth
from gausslite.ros.bagio import BagWriter
from gausslite.ros.transforms import make_transform

W, H = 40, 30
C_INTR = Intrinsics(38.0, 38.5, 19.5, 14.5, W, H)
D_INTR = Intrinsics(33.0, 33.0, 20.0, 15.0, W, H)
UNITS = 0.0001  # metres per depth unit (RealSense's "Depth Units" option; 1 mm is the default)
COLOR, DEPTH = "/device_0/sensor_1/Color_0", "/device_0/sensor_0/Depth_0"
N = 3


def raw_depth(k: int) -> np.ndarray:
    """A slanted plane, 1.2-1.6 m, in depth units."""
    m = 1.2 + 0.01 * np.arange(W)[None].repeat(H, 0) + 0.01 * k
    return np.round(m / UNITS).astype(np.uint16)


def colour(k: int) -> np.ndarray:
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0] = (np.arange(W) * 6)[None]
    img[..., 2] = 20 * k
    return img


def _image(w: BagWriter, topic: str, t: float, arr: np.ndarray, encoding: str, step: int):
    msg = w._t("sensor_msgs/msg/Image")(header=w.header(t, "", topic), height=H, width=W, encoding=encoding,
                                         is_bigendian=0, step=step, data=np.frombuffer(arr.tobytes(), np.uint8))
    w.write(topic, "sensor_msgs/msg/Image", msg, t)


def write_realsense_bag(path, T_ref_color=np.eye(4), depth_intr=D_INTR, units=True, color_tf=True):
    """The RealSense layout: per stream image/data, info/camera_info and tf/0 (the stream's extrinsics to the
    reference stream, depth); the depth sensor's "Depth Units" option."""
    with BagWriter(path, storage="ros1") as w:
        w.write_camera_info(f"{COLOR}/info/camera_info", 0.0, "", C_INTR)
        w.write_camera_info(f"{DEPTH}/info/camera_info", 0.0, "", depth_intr)
        for topic, T in ((f"{DEPTH}/tf/0", np.eye(4)), (f"{COLOR}/tf/0", T_ref_color))[: 2 if color_tf else 1]:
            v, q = w._tq(T)
            msg = w._t("geometry_msgs/msg/Transform")(translation=v, rotation=q)
            w.write(topic, "geometry_msgs/msg/Transform", msg, 0.0)
        if units:
            w.write("/device_0/sensor_0/option/Depth Units/value", "std_msgs/msg/Float32",
                    w._t("std_msgs/msg/Float32")(data=UNITS), 0.0)
        for k in range(N):
            t = 1.0 + k / 30.0
            _image(w, f"{COLOR}/image/data", t, colour(k), "rgb8", W * 3)
            _image(w, f"{DEPTH}/image/data", t + 0.004, raw_depth(k), "mono16", W * 2)
    return path


def test_an_aligned_recording_reads_as_it_is(tmp_path):
    bag = write_realsense_bag(tmp_path / "rec.bag", depth_intr=C_INTR)
    assert is_realsense_bag(bag) and detect_layout(bag) == ("realsense", bag)
    ds = RealSenseBagDataset(bag)
    assert len(ds) == N and not ds.has_poses and ds.depth_camera is None and ds.depth_units == pytest.approx(UNITS)
    f = ds[2]
    assert np.array_equal(f.rgb, colour(2)) and np.isclose(f.timestamp, 1.0 + 2 / 30.0)
    assert np.allclose(f.depth, raw_depth(2) * UNITS, atol=1e-6)
    assert isinstance(load_dataset(bag, progress=False), OdometryDataset)


def test_depth_is_registered_to_colour_with_the_bags_extrinsics(tmp_path):
    T_ref_color = make_transform([0.015, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])  # colour 1.5 cm right of depth
    bag = write_realsense_bag(tmp_path / "rec.bag", T_ref_color=T_ref_color)
    ds = RealSenseBagDataset(bag, downscale=2)
    assert ds.depth_camera is not None and np.allclose(ds.depth_camera.T_color_depth, np.linalg.inv(T_ref_color))
    assert ds.depth_camera.intrinsics == D_INTR
    metres = raw_depth(1).astype(np.float32) / np.float32(1000) * np.float32(ds.depth_units / 0.001)  # as decoded
    want = register_depth(metres, DepthCamera(D_INTR, ds.depth_camera.T_color_depth), C_INTR)
    unregistered = register_depth(metres, DepthCamera(C_INTR), C_INTR)
    assert not np.allclose(unregistered, want)  # the extrinsics and the depth camera move the depth
    got = RealSenseBagDataset(bag)[1].depth
    assert np.allclose(got, want, atol=1e-6) and (got > 0).mean() > 0.5
    assert ds[1].depth.shape == (H // 2, W // 2) and ds.intrinsics == C_INTR.scaled(2)


def test_missing_depth_units_default_to_a_millimetre_and_missing_extrinsics_are_named(tmp_path, caplog):
    bag = write_realsense_bag(tmp_path / "a.bag", units=False)
    assert RealSenseBagDataset(bag).depth_units == 0.001 and "Depth Units" in caplog.text
    bag = write_realsense_bag(tmp_path / "b.bag", color_tf=False)
    with pytest.raises(ValueError, match=f"{bag}: topic {COLOR}/tf/0 is missing"):
        RealSenseBagDataset(bag)


def test_other_bags_and_files_are_not_realsense(tmp_path):
    other = tmp_path / "other.bag"
    with BagWriter(other, storage="ros1") as w:
        w.write_camera_info("/camera/color/camera_info", 0.0, "cam", C_INTR)
    assert not is_realsense_bag(other) and detect_layout(other)[0] == "bag"
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"not a bag")
    assert not is_realsense_bag(junk)
