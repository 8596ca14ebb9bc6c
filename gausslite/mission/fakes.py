"""In-memory fusion sides for a mission: :class:`gausslite.mission.ports.FusionPort` implementations without a
network or a server, for running a mission that shares in one process (tests, benchmarks, an integration's own
checks).

* :class:`SinkFusion` accepts every upload and counts what it received: the agent selects, fine-tunes, plans and
  encodes its pushes as it would for a server, so the push work competes with mapping as on a robot.
* :class:`RecordingFusion` also keeps what a fusion server's store would hold of one agent: every map version
  decoded (a delta rebuilt on its base) and the uploaded keyframes, under the server's bound.

Both acknowledge every upload as complete and never fail a call.
"""

from __future__ import annotations

import time
from types import SimpleNamespace
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from gausslite.core.arrays import GaussianArrays
from gausslite.fusion.uploads import rebuild_subset
from gausslite.mapping.views import Keyframe, keyframe_from_frame
from gausslite.wire.decode import SubsetAssembler
from gausslite.wire.format import WireLimits

__all__ = ["SinkFusion", "RecordingFusion"]


def _chunk_bytes(chunk: Any) -> bytes:
    """A chunk as bytes: ``bytes`` as they are, a protobuf message serialised."""
    return chunk.SerializeToString() if hasattr(chunk, "SerializeToString") else chunk


class SinkFusion:
    """A :class:`gausslite.mission.ports.FusionPort` that accepts every upload and keeps nothing but counts.

    Attributes:
        bytes: bytes of every chunk received so far (serialised size for protobuf messages).
        uploads: calls of :meth:`upload_chunks` so far.
    """

    def __init__(self) -> None:
        self.bytes = 0
        self.uploads = 0

    def open_session(self, agent_id, task_text, intrinsics):
        """A new session on an empty store: ``latest_map_version`` 0, whatever the agent uploaded before."""
        return SimpleNamespace(latest_map_version=0)

    def upload_chunks(self, agent_id, version, chunks, n_gaussians=0, full_map_gaussians=0):
        """Count the chunks (``bytes`` or protobuf messages) of one map version; returns an acknowledgement with
        ``complete`` True, ``bytes_sent`` (their total size, bytes) and ``n_chunks``."""
        chunks = list(chunks)
        n = sum(len(_chunk_bytes(c)) for c in chunks)
        self.bytes += n
        self.uploads += 1
        return SimpleNamespace(complete=True, bytes_sent=n, n_chunks=len(chunks))

    def upload_keyframes(self, agent_id, frames, **kw):
        """Acknowledge every keyframe (:class:`gausslite.datasets.base.Frame`); returns ``len(frames)``."""
        return len(frames)


class RecordingFusion(SinkFusion):
    """A :class:`SinkFusion` that holds what a fusion server's store holds of one agent.

    Every upload is decoded and, for a delta, rebuilt on the subset it names as base
    (:func:`gausslite.fusion.uploads.rebuild_subset`), exactly as the server stores it. Keyframes are kept as the
    server keeps them: at most ``max_keyframes``, the oldest dropped first.

    Attributes:
        subsets: ``{map version: GaussianArrays}``, every version received, full.
        history: ``[(seconds since start(), map version, GaussianArrays)]``, one entry per upload, in order.
        keyframes: ``{frame id: gausslite.mapping.views.Keyframe}`` (CPU tensors, with the uploaded ROI mask).
        t0: ``time.perf_counter()`` at construction or at the last :meth:`start`.

    Args:
        max_keyframes: how many keyframes to keep (the server's per-agent bound).
    """

    def __init__(self, max_keyframes: int = 64) -> None:
        super().__init__()
        self.max_keyframes = int(max_keyframes)
        self.t0 = time.perf_counter()
        self.history: List[Tuple[float, int, GaussianArrays]] = []
        self.subsets: Dict[int, GaussianArrays] = {}
        self.keyframes: Dict[int, Keyframe] = {}

    def start(self) -> None:
        """Restart the clock of :attr:`history` (seconds from now)."""
        self.t0 = time.perf_counter()

    def upload_chunks(self, agent_id, version, chunks, n_gaussians=0, full_map_gaussians=0):
        """Decode the chunks of one map version (every chunk of it, ``gausslite.wire``), rebuild a delta on its base
        and record the full subset; returns :meth:`SinkFusion.upload_chunks`' acknowledgement.

        Raises:
            gausslite.wire.format.WireError: a chunk that does not decode, or chunks that do not make a whole
                version of ``agent_id``.
            KeyError: a delta whose base version this store never received.
            gausslite.wire.format.DeltaMismatch: a delta that does not fit its base.
            gausslite.fusion.uploads.RebuiltTooLarge: a rebuilt subset beyond the wire's subset limit.
        """
        chunks = list(chunks)
        asm = SubsetAssembler(agent_id=agent_id, map_version=version)
        for c in chunks:
            asm.add(_chunk_bytes(c))
        records, meta = asm.result()
        if meta.delta:
            targets, removed = asm.delta_parts()
            records = rebuild_subset(self.subsets[meta.base_version], records, targets, removed, meta,
                                     WireLimits().max_total_gaussians)
        self.subsets[int(version)] = records
        self.history.append((time.perf_counter() - self.t0, int(version), records))
        return super().upload_chunks(agent_id, version, chunks, n_gaussians, full_map_gaussians)

    def upload_keyframes(self, agent_id, frames: Sequence, *, rois: Optional[Sequence] = None, **kw) -> int:
        """Keep each keyframe (:class:`gausslite.datasets.base.Frame`) not held yet, with its (H, W) bool ROI mask
        (``rois[i]``, None = none), then drop the oldest beyond ``max_keyframes``; returns ``len(frames)``.

        Raises:
            ValueError: a frame's images or ROI of another size than its intrinsics
                (:func:`gausslite.mapping.views.keyframe_from_frame`).
        """
        for i, fr in enumerate(frames):
            roi = None if rois is None or rois[i] is None else np.asarray(rois[i], bool)
            self.keyframes.setdefault(int(fr.frame_id), keyframe_from_frame(fr, "cpu", roi))
        while len(self.keyframes) > self.max_keyframes:
            self.keyframes.pop(next(iter(self.keyframes)))
        return len(frames)
