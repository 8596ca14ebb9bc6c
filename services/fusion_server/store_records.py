"""Record and error types of the fusion server's store (:mod:`gausslite_services.fusion_server.store`): an agent's
session, the state of an upload, a stored keyframe, and the errors every backend raises."""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional

import numpy as np


class StoreError(RuntimeError):
    """The store is closed, its database is unreachable or unusable."""


class StoreUnavailable(StoreError):
    """The database cannot be reached now: connection refused or lost (a PostgreSQL restart or outage), or
    no pooled connection within the acquire timeout. Transient: the same call may succeed later (the server
    answers UNAVAILABLE, which clients retry with backoff); nothing was acknowledged by the failed call."""


class SchemaTooNew(StoreError):
    """The database was written by a newer GaussLite (schema version above :data:`SCHEMA_VERSION`)."""


@dataclass(frozen=True)
class Session:
    """An agent's session: task text and default intrinsics (pixels)."""

    agent_id: str
    task_text: str
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


@dataclass(frozen=True)
class Upload:
    """State of one (agent, map version) upload.

    Attributes:
        n_chunks (int): declared chunk count. full_map_gaussians / full_map_bytes (int): from the
        latest header. total_count (int | None), lossless (bool | None): fixed by the first stored
        chunk. complete (bool). stored (list[int]): sorted stored chunk indices. n_gaussians (int): sum over the
        stored chunks. wire_bytes (int): bytes received on the wire for this version (its distinct chunks as sent;
        for a completed delta upload, the delta's chunks). stored_bytes (int): bytes of the chunks held now (equal
        to ``wire_bytes`` except for a completed delta, whose chunks are the lossless rebuilt subset).
    """

    agent_id: str
    map_version: int
    n_chunks: int
    full_map_gaussians: int
    full_map_bytes: int
    total_count: Optional[int]
    lossless: Optional[bool]
    complete: bool
    stored: List[int]
    n_gaussians: int
    wire_bytes: int
    stored_bytes: int

    @property
    def missing(self) -> List[int]:
        s = set(self.stored)
        return [i for i in range(self.n_chunks) if i not in s]


@dataclass(frozen=True)
class StoredKeyframe:
    """A keyframe as stored (encoded images, metadata). ``c2w``: (4, 4) float64. ``roi``: the agent's
    task ROI as an 8-bit PNG (empty bytes: none sent)."""

    agent_id: str
    frame_id: int
    color: bytes
    depth: bytes
    depth_scale: float
    c2w: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    timestamp: float
    roi: bytes = b""


class ChunkConflict(ValueError):
    """A chunk index is already stored with different content."""
