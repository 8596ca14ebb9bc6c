"""Multi-agent fusion (paper Sec. III-E, SPEC §7): κ-weighted voxel vote and the concat baseline."""

from gausslite.fusion.vote import VoteReport, concat, voxel_keys, voxel_vote

__all__ = ["VoteReport", "concat", "voxel_keys", "voxel_vote"]
