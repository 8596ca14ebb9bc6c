"""Fusion server (paper Sec. III-E): receives ROI-Gaussian subsets and keyframes from
many agents, voxel-votes them into one map (optional joint refinement), persists and serves it.

* :mod:`services.fusion_server.server` — the ``gausslite.v1.Fusion`` gRPC service and CLI.
* :mod:`services.fusion_server.store` — durable store (everything acknowledged is committed): embedded
  SQLite by default, PostgreSQL (shared by replicas) selected by a ``postgresql://`` DSN.
* :mod:`services.fusion_server.client` — the robot-side :class:`FusionClient`.
"""
