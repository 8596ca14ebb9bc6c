"""Frame and dataset interfaces shared by every loader (Replica, TUM RGB-D, 7-Scenes, synthetic), named here for the
loaders; they are defined in :mod:`gausslite.core.frames`, which the odometry shares."""

from gausslite.core.frames import Frame, RGBDDataset

__all__ = ["Frame", "RGBDDataset"]
