"""Poses for RGB-D input without them: frame-to-keyframe RGB-D odometry, relocalisation, and loop closing on a pose
graph.

- :mod:`gausslite.odometry.rgbd`: :class:`~gausslite.odometry.rgbd.RGBDOdometry` (coarse-to-fine colour and depth
  registration of each frame to the latest keyframe, Open3D), and :class:`~gausslite.odometry.rgbd.OdometryDataset`
  / :func:`~gausslite.odometry.rgbd.with_pose_source`, which give a sequence without poses its estimated ones;
- :mod:`gausslite.odometry.config`: its settings (:class:`~gausslite.odometry.config.OdometryConfig`) and where a
  mission's poses come from (``PoseSource``);
- :mod:`gausslite.odometry.pose_graph`: the keyframe graph, loop and relocalisation settings, ICP verification;
- :mod:`gausslite.odometry.loop_closing`: loops found and closed on their own thread;
- :mod:`gausslite.odometry.pyramid`: the image pyramid the registration runs on.

The odometry reads :class:`gausslite.core.frames.Frame`; the loaders of :mod:`gausslite.datasets` offer it for
sequences without poses (``load_dataset(pose_source=...)``).
"""
