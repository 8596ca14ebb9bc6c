"""Fusion server (paper Sec. III-E): receives ROI-Gaussian subsets and keyframes from
many agents, voxel-votes them into one map (optional joint refinement), persists and serves it.

* :mod:`gausslite_services.fusion_server.server` — starting the service (settings, ``serve``, ``run``, CLI).
* :mod:`gausslite_services.fusion_server.servicer` — the ``gausslite.v1.Fusion`` servicer over the store; fuse jobs
  run :class:`gausslite.fusion.engine.FuseEngine`.
* :mod:`gausslite_services.fusion_server.guards` — request checks and the status guards (a precise status and a log
  line for every rejected call).
* :mod:`gausslite_services.fusion_server.store` — durable store (everything acknowledged is committed): embedded
  SQLite by default, PostgreSQL (shared by replicas) selected by a ``postgresql://`` DSN; the contract in SQL,
  the backends and the record types live in its ``store_*`` modules.
* :mod:`gausslite_services.fusion_server.client` — the robot-side :class:`FusionClient`.
"""
