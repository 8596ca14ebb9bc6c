"""Multi-agent fusion (paper Sec. III-E): κ-weighted voxel vote and the concat baseline."""

from gausslite.fusion.vote import IncrementalVote, VoteReport, VoxelRangeError, concat, voxel_keys, voxel_vote

__all__ = ["IncrementalVote", "VoxelRangeError", "VoteReport", "concat", "voxel_keys", "voxel_vote"]
