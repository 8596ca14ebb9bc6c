"""The fusion side's rules for subset uploads: version order and delta pushes (paper Sec. III-E).

An agent uploads numbered versions of its shared subset; completing a version makes it the agent's latest and
supersedes the older ones, so an upload below the latest complete version is refused (``docs/robot-integration.md``,
"Superseded versions"). A *delta* version names a base version and carries only replaced, new and removed rows
(``docs/wire-format.md`` §6). The base must be held complete; once every delta chunk is stored, the full subset is
rebuilt from the base (:func:`gausslite.wire.decode.apply_delta`) and stored as lossless chunks in place of the
delta, so the values never drift across deltas. The rebuild is idempotent and crash-safe: the delta chunks stay
until the rebuilt subset is committed, and a resumed upload redoes it.

The state lives in any object with the methods of :class:`UploadStore` (the fusion server's SQL store conforms).
No gRPC here: refusals are typed exceptions, which the fusion server answers with the status
``gausslite_services.common.errors.status_for`` gives their type:

=========================  ===========================================  ====================
exception                  when                                         status
=========================  ===========================================  ====================
:class:`SupersededVersion`  the version is below the latest complete one  FAILED_PRECONDITION
:class:`MissingDeltaBase`   the delta's base is not held complete         FAILED_PRECONDITION
``DeltaMismatch``           the delta does not fit its base               INVALID_ARGUMENT
:class:`RebuiltTooLarge`    the rebuilt subset exceeds the subset limit   RESOURCE_EXHAUSTED
=========================  ===========================================  ====================

A refused delta is discarded (the agent then uploads the full subset).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, List, Optional, Protocol, Sequence, Tuple

import numpy as np

from gausslite.core.arrays import GaussianArrays
from gausslite.errors import CapacityExceeded, PreconditionFailed
from gausslite.wire.decode import SubsetAssembler, apply_delta, decode_chunk, peek_header
from gausslite.wire.encode import encode_subset
from gausslite.wire.format import LOSSLESS, DeltaMismatch, SubsetMeta, WireLimits

__all__ = ["UploadState", "UploadStore", "SupersededVersion", "MissingDeltaBase", "RebuiltTooLarge", "RebuiltDelta",
           "check_not_superseded", "check_delta_base", "rebuild_subset", "complete_delta_upload"]


class SupersededVersion(PreconditionFailed):
    """An upload of a map version below the agent's latest complete version (FAILED_PRECONDITION)."""


class MissingDeltaBase(PreconditionFailed):
    """A delta whose base version is not held complete (FAILED_PRECONDITION; the delta is discarded)."""


class RebuiltTooLarge(CapacityExceeded):
    """A delta that rebuilds a subset above the subset limit (RESOURCE_EXHAUSTED; the delta is discarded)."""


class UploadState(Protocol):
    """What the rules read of one (agent, map version) upload."""

    @property
    def complete(self) -> bool:
        """Every chunk stored (a delta: rebuilt and stored)."""

    @property
    def missing(self) -> List[int]:
        """Sorted indices of the chunks not stored yet."""


class UploadStore(Protocol):
    """The upload state the rules read and change (``gausslite_services.fusion_server.store.SqlFusionStore``
    conforms)."""

    def upload(self, agent_id: str, map_version: int) -> Optional[UploadState]:
        """State of (agent, version), None when never announced."""

    def latest_version(self, agent_id: str) -> Optional[int]:
        """The agent's latest complete map version, None before the first."""

    def chunk_data(self, agent_id: str, map_version: int) -> Sequence[bytes]:
        """The stored chunks of (agent, version), in index order."""

    def discard_upload(self, agent_id: str, map_version: int) -> None:
        """Delete an incomplete upload and its chunks (no-op when absent or complete)."""

    def complete_rebuilt(self, agent_id: str, map_version: int, chunks: List[Tuple[bytes, bytes, int]],
                         total_count: int, lossless: bool) -> Any:
        """Replace a received delta by its rebuilt subset's chunks ((data, digest, rows) in index order) and
        complete the version, in one transaction."""


@dataclass(frozen=True)
class RebuiltDelta:
    """A delta version rebuilt into a full subset (:func:`complete_delta_upload`).

    Attributes:
        subset: the rebuilt subset (world frame, metres), as stored.
        meta: the delta's metadata (base version, base row count, κ shift).
        records: rows the delta carried (replaced and new); removed: base rows it removed.
    """

    subset: GaussianArrays
    meta: SubsetMeta
    records: int
    removed: int


def check_not_superseded(agent_id: str, map_version: int, latest: Optional[int]) -> None:
    """Refuse an upload below the agent's latest complete version (versions only move forward; re-sending the
    latest version itself is a resume and allowed).

    Args:
        agent_id: the uploading agent; map_version: the version it uploads; latest: its latest complete version
            (None before the first).

    Raises:
        SupersededVersion: ``map_version < latest``.
    """
    if latest is not None and map_version < latest:
        raise SupersededVersion(f"map_version {map_version} of {agent_id!r} is superseded by complete version {latest}")


def check_delta_base(store: UploadStore, agent_id: str, map_version: int, base_version: int) -> None:
    """Refuse a delta whose base version ``store`` does not hold complete, discarding the delta's upload.

    Args:
        store: the upload state; agent_id, map_version: the delta upload; base_version: the version it applies to.

    Raises:
        MissingDeltaBase: the base is unknown or incomplete (the delta's upload is discarded first).
    """
    base = store.upload(agent_id, base_version)
    if base is None or not base.complete:
        store.discard_upload(agent_id, map_version)
        latest = store.latest_version(agent_id)
        raise MissingDeltaBase(
            f"delta v{map_version} of {agent_id!r} needs base version {base_version}, which this server "
            f"does not hold (latest complete: {latest if latest is not None else 'none'}); upload the full subset")


def rebuild_subset(base: GaussianArrays, records: GaussianArrays, targets: np.ndarray, removed: np.ndarray,
                   meta: SubsetMeta, max_total_gaussians: int) -> GaussianArrays:
    """The full subset a delta describes, within the subset limit (pure; see :func:`complete_delta_upload`).

    Args:
        base: the base version's subset (``meta.base_count`` rows).
        records: (R,) rows of the delta; targets: (R,) int64 ascending; removed: (D,) int64 sorted
            (:meth:`gausslite.wire.decode.SubsetAssembler.delta_parts`).
        meta: the delta's metadata (agent, versions, base count, κ shift).
        max_total_gaussians: largest subset allowed (rows).

    Returns:
        the rebuilt subset (:func:`gausslite.wire.decode.apply_delta`).

    Raises:
        DeltaMismatch: the delta does not fit its base (the message names agent and version).
        RebuiltTooLarge: the rebuilt subset has more than ``max_total_gaussians`` rows.
    """
    what = f"delta v{meta.map_version} of {meta.agent_id!r}"
    try:
        full = apply_delta(base, records, targets, removed, meta.base_count, meta.kappa_shift)
    except DeltaMismatch as e:
        raise DeltaMismatch(f"{what}: {e}") from None
    if len(full) > max_total_gaussians:
        raise RebuiltTooLarge(f"{what} rebuilds a subset of {len(full)} Gaussians, above the server's limit of "
                              f"{max_total_gaussians}")
    return full


def complete_delta_upload(store: UploadStore, agent_id: str, map_version: int, limits: WireLimits,
                          load_subset: Callable[[str, int], GaussianArrays]) -> Optional[RebuiltDelta]:
    """When every chunk of a delta upload is stored: rebuild the full subset from its base and store it (lossless
    chunks) as the complete version.

    Idempotent and crash-safe: nothing happens for an unknown, complete or partly received upload, or a full
    (non-delta) one; the delta chunks stay until ``store.complete_rebuilt`` commits the rebuilt subset.

    Args:
        store: the upload state; agent_id, map_version: the upload.
        limits: the server's wire limits (decoding the stored chunks; the rebuilt subset's size and chunks).
        load_subset: ``(agent_id, version) -> GaussianArrays``, the decoded subset of a complete version (the base).

    Returns:
        the rebuilt delta, or None when there was nothing to rebuild.

    Raises:
        MissingDeltaBase, DeltaMismatch, RebuiltTooLarge: the delta is refused (and its upload discarded).
        WireError subclasses: the stored chunks do not assemble (they were validated when stored).
    """
    up = store.upload(agent_id, map_version)
    if up is None or up.complete or up.missing:
        return None
    asm = SubsetAssembler(limits, agent_id=agent_id, map_version=map_version)
    for c in store.chunk_data(agent_id, map_version):
        asm.add(c)
    records, meta = asm.result()
    if not meta.delta:
        return None
    check_delta_base(store, agent_id, map_version, meta.base_version)
    targets, removed = asm.delta_parts()
    try:
        full = rebuild_subset(load_subset(agent_id, meta.base_version), records, targets, removed, meta,
                              limits.max_total_gaussians)
    except (DeltaMismatch, RebuiltTooLarge):
        store.discard_upload(agent_id, map_version)
        raise
    chunks = encode_subset(full, agent_id, map_version, quant=LOSSLESS, max_chunk_bytes=limits.max_chunk_bytes,
                           limits=limits)
    stored = [(c, decode_chunk(c, limits).digest, peek_header(c, limits).count) for c in chunks]
    store.complete_rebuilt(agent_id, map_version, stored, len(full), True)
    return RebuiltDelta(full, meta, len(records), len(removed))
