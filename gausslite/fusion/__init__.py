"""Multi-agent fusion (paper Sec. III-E): κ-weighted voxel vote and the concat baseline; the fusion side's upload
rules (version order, delta pushes) are :mod:`gausslite.fusion.uploads`."""

from gausslite.fusion.plausible import check_plausible
from gausslite.fusion.vote import IncrementalVote, VoteReport, VoxelRangeError, concat, voxel_keys, voxel_vote

__all__ = ["IncrementalVote", "VoxelRangeError", "VoteReport", "check_plausible", "concat", "voxel_keys",
           "voxel_vote"]
