"""ROS interoperability without a ROS install: TF trees, image message decoding, bag writing.

Pure logic (no I/O) lives in :mod:`gausslite.ros.transforms` (rigid transforms, quaternions, a TF buffer
with interpolation) and :mod:`gausslite.ros.images` (``sensor_msgs/Image`` / ``CompressedImage``
decoding and encoding). :mod:`gausslite.ros.bagio` reads and writes bags with the ``rosbags`` package
(rosbag2 MCAP / SQLite3 and ROS 1 ``.bag``); :mod:`gausslite.ros.export` writes any dataset as a bag.
The bag dataset loader is :class:`gausslite.datasets.bag.BagDataset`.

Conventions: REP 103 (right-handed; body frames x forward, y left, z up; camera *optical* frames
x right, y down, z forward, which are GaussLite's OpenCV camera axes) and REP 105 (``map`` → ``odom``
→ ``base_link``). A camera pose is the pose of the image's optical frame (``header.frame_id`` of the
image) in the world frame.
"""
