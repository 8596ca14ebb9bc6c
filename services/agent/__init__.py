"""Agent service (one per robot): task → parser service → graph; posed RGB-D stream (client stream or
dataset replay) → attention front-end → task-conditioned mapper → periodic ROI-subset + keyframe pushes to
the fusion server (paper Sec. III-E).

Modules: the mission loop is the library's :mod:`gausslite.mission` (no gRPC); :mod:`~gausslite_services.agent.frames`
(FrameMsg codec and validation), :mod:`~gausslite_services.agent.server` (gRPC service),
:mod:`~gausslite_services.agent.client`.
Run with ``gausslite serve agent`` or ``python -m gausslite_services.agent``.
"""
