"""Frame and dataset interfaces shared by every loader (Replica, TUM RGB-D, 7-Scenes, synthetic). (defined in :mod:`gausslite.core.frames`,
which the odometry shares)."""

from gausslite.core.frames import Frame, RGBDDataset

__all__ = ["Frame", "RGBDDataset"]
