"""Durable store of the fusion server: sessions, subset chunks, keyframes and fused maps.

The fusion server persists what it accepted, so a restart loses nothing it acknowledged (paper
Sec. III-E; ``docs/fusion-and-deploy.md``).

Backends (one contract, one SQL implementation)
-----------------------------------------------
* :class:`SqliteFusionStore` — the embedded default: ``<data_dir>/fusion.sqlite3`` (stdlib
  :mod:`sqlite3`), WAL with ``synchronous=FULL``, one connection guarded by a lock. Right for one
  fusion process (a team of a few robots, the compose simulation).
* :class:`PostgresFusionStore` — PostgreSQL through psycopg 3 and a ``psycopg_pool`` connection
  pool, selected by a ``postgresql://`` DSN (:func:`open_store`). Several fusion replicas share one
  database: every write is one transaction serialised per agent by a transaction-level advisory
  lock, fused versions come from an identity column allocated under a database lock, and
  :meth:`SqlFusionStore.fuse_lock` is a session-level advisory lock, so concurrent ``Fuse`` calls on
  different replicas run one after the other.

The contract (``tests/services/test_fusion_store_contract.py`` runs the same tests against both):

* every write is committed (durable) before the method returns, so the server only acknowledges
  what is stored; a fresh store on the same database sees it;
* uploads are idempotent (an identical chunk re-delivery is a no-op, a different one a
  :class:`ChunkConflict`) and resumable (``upload().missing``);
* completing a newer map version of an agent supersedes (deletes) its older uploads;
* keyframes are bounded per agent (oldest by arrival evicted), idempotent by (agent, frame id);
* fused versions are allocated by the database and strictly increase.

Schema migrations are versioned (:data:`MIGRATIONS`, table ``schema_meta``); opening a database
whose schema is newer than :data:`SCHEMA_VERSION` raises :class:`SchemaTooNew` (a server never
writes into a schema it does not know). A SQLite database of the pre-migration layout is upgraded
in place (its tables are the version-1 tables).

Tables::

    sessions(agent_id PK, task_text, fx, fy, cx, cy, width, height, opened_unix)
    uploads(agent_id, map_version, n_chunks, full_map_gaussians, full_map_bytes, total_count,
            lossless, complete, completed_unix, received_bytes, PK(agent_id, map_version))
    chunks(agent_id, map_version, idx, data BLOB, digest BLOB, n_gaussians, wire_bytes,
           PK(agent_id, map_version, idx))
    agents(agent_id PK, latest_version)   -- latest complete subset
    keyframes(agent_id, frame_id, seq, color BLOB, depth BLOB, depth_scale, c2w BLOB (16 f64),
              fx, fy, cx, cy, width, height, timestamp, PK(agent_id, frame_id))
    fused(version PK (allocated by the database), info BLOB (serialized FuseResult), method, n_chunks)
    fused_chunks(version, idx, data BLOB, PK(version, idx))
    schema_meta(id = 1, version)

Modules: :mod:`~gausslite_services.fusion_server.store_records` (records and errors),
:mod:`~gausslite_services.fusion_server.store_sql` (the contract in SQL, schema and migrations; an abstract base whose
backends implement ``_tx``, ``_read``, ``fuse_lock`` and ``close``),
:mod:`~gausslite_services.fusion_server.store_sqlite` and :mod:`~gausslite_services.fusion_server.store_postgres`.
Import the names from this module.

Raw wire chunks are stored verbatim (bytes on the wire are reproducible and the assembled subset
after a restart is bit-identical to the one before). When a newer map version of an agent becomes
complete, the agent's older uploads and their chunks are deleted in the same transaction.
"""

from __future__ import annotations

from typing import Optional

from gausslite_services.fusion_server.store_postgres import PostgresFusionStore, redact_dsn
from gausslite_services.fusion_server.store_records import (ChunkConflict, SchemaTooNew, Session, StoredKeyframe,
                                                            StoreError, StoreUnavailable, Upload)
from gausslite_services.fusion_server.store_sql import MIGRATIONS, SCHEMA_VERSION, SqlFusionStore
from gausslite_services.fusion_server.store_sqlite import DB_NAME, SqliteFusionStore

#: DSN prefixes that select :class:`PostgresFusionStore`.
PG_PREFIXES = ("postgresql://", "postgres://")

#: Backwards-compatible name of the embedded store.
FusionStore = SqliteFusionStore


def is_postgres_dsn(spec: Optional[str]) -> bool:
    """True when ``spec`` selects the PostgreSQL backend."""
    return bool(spec) and str(spec).startswith(PG_PREFIXES)


def open_store(spec: str, **pg_options) -> SqlFusionStore:
    """Open the store named by ``spec``: a ``postgresql://`` DSN → :class:`PostgresFusionStore`,
    anything else is a directory → :class:`SqliteFusionStore`.

    Raises:
        StoreError, SchemaTooNew, OSError, sqlite3.DatabaseError: see the classes.
    """
    if is_postgres_dsn(spec):
        return PostgresFusionStore(spec, **pg_options)
    return SqliteFusionStore(spec)


__all__ = ["SqlFusionStore", "SqliteFusionStore", "PostgresFusionStore", "FusionStore", "open_store",
           "is_postgres_dsn", "redact_dsn", "Session", "Upload", "StoredKeyframe", "ChunkConflict", "StoreError",
           "StoreUnavailable", "SchemaTooNew", "SCHEMA_VERSION", "MIGRATIONS", "DB_NAME"]
