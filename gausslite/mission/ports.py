"""The port through which a mission pushes to the fusion side (paper Sec. III-E; ``docs/sharing.md``).

:class:`FusionPort` lists what :class:`gausslite.mission.pusher.Pusher` calls. The gRPC client
(``gausslite_services.fusion_server.client.FusionClient``) implements it over the wire; the in-process sink and
recording store (:class:`gausslite.mission.fakes.SinkFusion`, :class:`gausslite.mission.fakes.RecordingFusion`)
implement it in memory. A rejected delta base is signalled by raising
:class:`gausslite.mission.errors.PreconditionFailed`.
"""

from __future__ import annotations

from typing import Any, Optional, Protocol, Sequence, runtime_checkable

__all__ = ["FusionPort", "SessionInfo", "UploadAck"]


class SessionInfo(Protocol):
    """What :meth:`FusionPort.open_session` returns: ``latest_map_version``, the newest complete subset the fusion
    side holds of this agent (0 = none)."""

    latest_map_version: int


class UploadAck(Protocol):
    """What :meth:`FusionPort.upload_chunks` returns: ``complete`` (the fusion side holds every chunk of the
    version), ``n_chunks`` (chunks of the version) and ``bytes_sent`` (bytes actually transmitted)."""

    complete: bool
    n_chunks: int
    bytes_sent: int


@runtime_checkable
class FusionPort(Protocol):
    """The fusion side of a mission, as the pusher uses it (module docstring). Calls may raise any exception on
    a failed link (the pusher retries with backoff); :class:`~gausslite.mission.errors.PreconditionFailed` from
    :meth:`upload_chunks` means the fusion side lacks a delta's base (the pusher uploads the full subset)."""

    def open_session(self, agent_id: str, task_text: str, intrinsics: Any, /) -> SessionInfo:
        """Open (or re-open, keeping earlier uploads) the session of ``agent_id`` for ``task_text``, with the camera
        ``intrinsics`` (:class:`gausslite.camera.Intrinsics`, pixels) of its keyframes."""
        ...

    def upload_chunks(self, agent_id: str, map_version: int, chunks: Sequence[bytes], /, *, n_gaussians: int,
                      full_map_gaussians: int) -> UploadAck:
        """Upload the encoded chunks (``gausslite.wire``) of one map version (a full subset of ``n_gaussians``
        records or a delta), resuming what the fusion side holds; ``full_map_gaussians`` is the agent's map size."""
        ...

    def upload_keyframes(self, agent_id: str, keyframes: Sequence[Any], /, *, jpeg_quality: int = 95,
                         color_format: str = "jpeg", rois: Optional[Sequence[Any]] = None) -> int:
        """Upload keyframes (:class:`gausslite.datasets.base.Frame`, with their optional (H, W) bool ROI masks);
        returns how many the fusion side acknowledged."""
        ...
