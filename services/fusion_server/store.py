"""Durable store of the fusion server: sessions, subset chunks, keyframes and fused maps.

Source: SPEC §8 ("The fusion server persists what it accepted, so a restart loses nothing it
acknowledged"), paper Sec. III-E.

Design
------
One SQLite database ``<data_dir>/fusion.sqlite3`` (stdlib :mod:`sqlite3`), journal mode WAL with
``synchronous=FULL``: every write is its own committed transaction, made durable (fsync of the WAL)
before the method returns, so the server only acknowledges what is on disk; a SIGKILL or power cut
after the commit loses nothing, one before it loses only the un-acknowledged write (SQLite's atomic
commit: no torn rows). One connection guarded by a lock serialises access (writes are small: one
chunk, one keyframe; the heavy work — decoding, fusing — happens outside the lock).

Tables::

    sessions(agent_id PK, task_text, fx, fy, cx, cy, width, height, opened_unix)
    uploads(agent_id, map_version, n_chunks, full_map_gaussians, full_map_bytes, total_count,
            lossless, complete, completed_unix, PK(agent_id, map_version))
    chunks(agent_id, map_version, idx, data BLOB, digest BLOB, n_gaussians, wire_bytes,
           PK(agent_id, map_version, idx))
    agents(agent_id PK, latest_version, superseded_below)   -- latest complete subset
    keyframes(agent_id, frame_id, seq, color BLOB, depth BLOB, depth_scale, c2w BLOB (16 f64),
              fx, fy, cx, cy, width, height, timestamp, PK(agent_id, frame_id))
    fused(version INTEGER PK AUTOINCREMENT, info BLOB (serialized FuseResult), method, n_chunks)
    fused_chunks(version, idx, data BLOB, PK(version, idx))

Raw wire chunks are stored verbatim (bytes on the wire are reproducible and the assembled subset
after a restart is bit-identical to the one before). When a newer map version of an agent becomes
complete, the agent's older uploads and their chunks are deleted in the same transaction.
"""

from __future__ import annotations

import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Tuple

import numpy as np

DB_NAME = "fusion.sqlite3"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS sessions (
    agent_id TEXT PRIMARY KEY, task_text TEXT NOT NULL,
    fx REAL NOT NULL, fy REAL NOT NULL, cx REAL NOT NULL, cy REAL NOT NULL,
    width INTEGER NOT NULL, height INTEGER NOT NULL, opened_unix REAL NOT NULL);
CREATE TABLE IF NOT EXISTS uploads (
    agent_id TEXT NOT NULL, map_version INTEGER NOT NULL, n_chunks INTEGER NOT NULL,
    full_map_gaussians INTEGER NOT NULL DEFAULT 0, full_map_bytes INTEGER NOT NULL DEFAULT 0,
    total_count INTEGER, lossless INTEGER, complete INTEGER NOT NULL DEFAULT 0, completed_unix REAL,
    PRIMARY KEY (agent_id, map_version));
CREATE TABLE IF NOT EXISTS chunks (
    agent_id TEXT NOT NULL, map_version INTEGER NOT NULL, idx INTEGER NOT NULL,
    data BLOB NOT NULL, digest BLOB NOT NULL, n_gaussians INTEGER NOT NULL, wire_bytes INTEGER NOT NULL,
    PRIMARY KEY (agent_id, map_version, idx));
CREATE TABLE IF NOT EXISTS agents (
    agent_id TEXT PRIMARY KEY, latest_version INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS keyframes (
    agent_id TEXT NOT NULL, frame_id INTEGER NOT NULL, seq INTEGER NOT NULL,
    color BLOB NOT NULL, depth BLOB NOT NULL, depth_scale REAL NOT NULL, c2w BLOB NOT NULL,
    fx REAL NOT NULL, fy REAL NOT NULL, cx REAL NOT NULL, cy REAL NOT NULL,
    width INTEGER NOT NULL, height INTEGER NOT NULL, timestamp REAL NOT NULL,
    PRIMARY KEY (agent_id, frame_id));
CREATE INDEX IF NOT EXISTS keyframes_seq ON keyframes (agent_id, seq);
CREATE TABLE IF NOT EXISTS fused (
    version INTEGER PRIMARY KEY AUTOINCREMENT, info BLOB NOT NULL, method INTEGER NOT NULL,
    n_chunks INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS fused_chunks (
    version INTEGER NOT NULL, idx INTEGER NOT NULL, data BLOB NOT NULL, PRIMARY KEY (version, idx));
"""


class StoreError(RuntimeError):
    """The store is closed or its database is unusable."""


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
        chunk. complete (bool). stored (list[int]): sorted stored chunk indices. n_gaussians (int),
        wire_bytes (int): sums over the stored chunks.
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

    @property
    def missing(self) -> List[int]:
        s = set(self.stored)
        return [i for i in range(self.n_chunks) if i not in s]


@dataclass(frozen=True)
class StoredKeyframe:
    """A keyframe as stored (encoded images, metadata). ``c2w``: (4, 4) float64."""

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


class ChunkConflict(ValueError):
    """A chunk index is already stored with different content."""


class FusionStore:
    """Thread-safe SQLite store under ``data_dir`` (created when missing).

    Args:
        data_dir (str | Path): directory of the database.
    Raises:
        OSError: the directory cannot be created. sqlite3.DatabaseError: not a database.
    """

    def __init__(self, data_dir):
        self.data_dir = Path(data_dir)
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.path = self.data_dir / DB_NAME
        self._lock = threading.RLock()
        self._db: Optional[sqlite3.Connection] = sqlite3.connect(
            str(self.path), check_same_thread=False, isolation_level=None, timeout=30.0)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.execute("PRAGMA foreign_keys=OFF")
        self._db.executescript(_SCHEMA)

    # ------------------------------------------------------------------ plumbing
    def _conn(self) -> sqlite3.Connection:
        if self._db is None:
            raise StoreError("store is closed")
        return self._db

    def _tx(self):
        return _Tx(self)

    def close(self) -> None:
        """Checkpoint and close (idempotent)."""
        with self._lock:
            if self._db is not None:
                try:
                    self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
                finally:
                    self._db.close()
                    self._db = None

    # ------------------------------------------------------------------ sessions
    def open_session(self, s: Session) -> bool:
        """Insert or update a session; returns True when it was new."""
        with self._tx() as db:
            new = db.execute("SELECT 1 FROM sessions WHERE agent_id=?", (s.agent_id,)).fetchone() is None
            db.execute("INSERT INTO sessions VALUES (?,?,?,?,?,?,?,?,?) ON CONFLICT(agent_id) DO UPDATE SET "
                       "task_text=excluded.task_text, fx=excluded.fx, fy=excluded.fy, cx=excluded.cx, "
                       "cy=excluded.cy, width=excluded.width, height=excluded.height",
                       (s.agent_id, s.task_text, s.fx, s.fy, s.cx, s.cy, s.width, s.height, time.time()))
            return new

    def session(self, agent_id: str) -> Optional[Session]:
        """The agent's session or None."""
        with self._lock:
            row = self._conn().execute("SELECT agent_id, task_text, fx, fy, cx, cy, width, height FROM sessions "
                                       "WHERE agent_id=?", (agent_id,)).fetchone()
        return Session(*row) if row else None

    def sessions(self) -> List[Session]:
        """All sessions, sorted by agent id."""
        with self._lock:
            rows = self._conn().execute("SELECT agent_id, task_text, fx, fy, cx, cy, width, height FROM sessions "
                                        "ORDER BY agent_id").fetchall()
        return [Session(*r) for r in rows]

    # ------------------------------------------------------------------ uploads
    def latest_version(self, agent_id: str) -> Optional[int]:
        """The agent's latest complete map version, or None."""
        with self._lock:
            row = self._conn().execute("SELECT latest_version FROM agents WHERE agent_id=?", (agent_id,)).fetchone()
        return int(row[0]) if row else None

    def upload(self, agent_id: str, map_version: int) -> Optional[Upload]:
        """Upload state of (agent, version), or None when never announced."""
        with self._lock:
            return self._upload(self._conn(), agent_id, map_version)

    @staticmethod
    def _upload(db: sqlite3.Connection, agent_id: str, map_version: int) -> Optional[Upload]:
        row = db.execute("SELECT n_chunks, full_map_gaussians, full_map_bytes, total_count, lossless, complete "
                         "FROM uploads WHERE agent_id=? AND map_version=?", (agent_id, map_version)).fetchone()
        if row is None:
            return None
        stats = db.execute("SELECT idx, n_gaussians, wire_bytes FROM chunks WHERE agent_id=? AND map_version=? "
                           "ORDER BY idx", (agent_id, map_version)).fetchall()
        return Upload(agent_id, map_version, int(row[0]), int(row[1]), int(row[2]),
                      None if row[3] is None else int(row[3]), None if row[4] is None else bool(row[4]),
                      bool(row[5]), [int(r[0]) for r in stats], sum(int(r[1]) for r in stats),
                      sum(int(r[2]) for r in stats))

    def begin_upload(self, agent_id: str, map_version: int, n_chunks: int, full_map_gaussians: int,
                     full_map_bytes: int) -> Upload:
        """Create the upload record (or refresh its full-map sizes when nonzero).

        Raises:
            ValueError: the record exists with another chunk count and already holds chunks.
        """
        with self._tx() as db:
            up = self._upload(db, agent_id, map_version)
            if up is None:
                db.execute("INSERT INTO uploads (agent_id, map_version, n_chunks, full_map_gaussians, full_map_bytes) "
                           "VALUES (?,?,?,?,?)", (agent_id, map_version, n_chunks, full_map_gaussians, full_map_bytes))
            else:
                if up.n_chunks != n_chunks and not up.stored:  # announced, nothing stored: re-chunked
                    db.execute("UPDATE uploads SET n_chunks=? WHERE agent_id=? AND map_version=?",
                               (n_chunks, agent_id, map_version))
                elif up.n_chunks != n_chunks:
                    raise ValueError(f"map_version {map_version} of {agent_id!r} was announced with "
                                     f"{up.n_chunks} chunks, header says {n_chunks}")
                if full_map_gaussians:
                    db.execute("UPDATE uploads SET full_map_gaussians=? WHERE agent_id=? AND map_version=?",
                               (full_map_gaussians, agent_id, map_version))
                if full_map_bytes:
                    db.execute("UPDATE uploads SET full_map_bytes=? WHERE agent_id=? AND map_version=?",
                               (full_map_bytes, agent_id, map_version))
            return self._upload(db, agent_id, map_version)

    def put_chunk(self, agent_id: str, map_version: int, idx: int, data: bytes, digest: bytes,
                  n_gaussians: int, total_count: int, lossless: bool,
                  defer_complete: bool = False) -> Tuple[bool, Upload]:
        """Store one decoded-and-validated chunk; completes the upload when it is the last one.

        With ``defer_complete`` (delta uploads) the last chunk leaves the upload incomplete: the
        server rebuilds the full subset and completes it with :meth:`complete_rebuilt`.

        Completion of a version newer than the agent's latest complete one makes it the latest and
        deletes the agent's older uploads and chunks (same transaction).

        Returns:
            (new, upload): ``new`` False for an identical re-delivery (no-op).
        Raises:
            ChunkConflict: index stored with other content.
            ValueError: unknown upload, total/lossless disagreeing with earlier chunks, or Gaussian
            counts that exceed / do not add up to the subset total.
        """
        with self._tx() as db:
            up = self._upload(db, agent_id, map_version)
            if up is None:
                raise ValueError(f"no upload announced for {agent_id!r} v{map_version}")
            old = db.execute("SELECT digest FROM chunks WHERE agent_id=? AND map_version=? AND idx=?",
                             (agent_id, map_version, idx)).fetchone()
            if old is not None:
                if bytes(old[0]) != digest:
                    raise ChunkConflict(f"chunk {idx} of {agent_id!r} v{map_version} is already stored with "
                                        "different content")
                return False, up
            if up.total_count is not None and (up.total_count != total_count or up.lossless != lossless):
                raise ValueError(f"chunk {idx}: subset total {total_count} / lossless {lossless} disagree with "
                                 f"the stored chunks ({up.total_count} / {up.lossless})")
            if up.n_gaussians + n_gaussians > total_count:
                raise ValueError(f"chunk {idx}: chunks hold more Gaussians than the subset total {total_count}")
            last = len(up.stored) + 1 == up.n_chunks
            if last and up.n_gaussians + n_gaussians != total_count:
                raise ValueError(f"chunk {idx}: all chunks received but Gaussian counts add up to "
                                 f"{up.n_gaussians + n_gaussians}, not {total_count}")
            db.execute("INSERT INTO chunks VALUES (?,?,?,?,?,?,?)",
                       (agent_id, map_version, idx, data, digest, n_gaussians, len(data)))
            if up.total_count is None:
                db.execute("UPDATE uploads SET total_count=?, lossless=? WHERE agent_id=? AND map_version=?",
                           (total_count, int(lossless), agent_id, map_version))
            if last and not defer_complete:
                self._complete(db, agent_id, map_version)
            return True, self._upload(db, agent_id, map_version)

    @staticmethod
    def _complete(db: sqlite3.Connection, agent_id: str, map_version: int) -> None:
        db.execute("UPDATE uploads SET complete=1, completed_unix=? WHERE agent_id=? AND map_version=?",
                   (time.time(), agent_id, map_version))
        row = db.execute("SELECT latest_version FROM agents WHERE agent_id=?", (agent_id,)).fetchone()
        if row is None or int(row[0]) < map_version:
            db.execute("INSERT INTO agents VALUES (?,?) ON CONFLICT(agent_id) DO UPDATE SET "
                       "latest_version=excluded.latest_version", (agent_id, map_version))
            db.execute("DELETE FROM chunks WHERE agent_id=? AND map_version<?", (agent_id, map_version))
            db.execute("DELETE FROM uploads WHERE agent_id=? AND map_version<?", (agent_id, map_version))

    def complete_rebuilt(self, agent_id: str, map_version: int, chunks: List[Tuple[bytes, bytes, int]],
                         total_count: int, lossless: bool) -> Upload:
        """Replace a fully received delta upload by its rebuilt full subset and complete it, in one
        transaction (a crash before the commit leaves the delta chunks, and the rebuild is redone).

        Args:
            chunks: (data, digest, n_gaussians) of the rebuilt subset's wire chunks, index order.
        Raises:
            ValueError: unknown upload, or already complete.
        """
        with self._tx() as db:
            up = self._upload(db, agent_id, map_version)
            if up is None or up.complete:
                raise ValueError(f"{agent_id!r} v{map_version}: no incomplete upload to complete")
            db.execute("DELETE FROM chunks WHERE agent_id=? AND map_version=?", (agent_id, map_version))
            for idx, (data, digest, n) in enumerate(chunks):
                db.execute("INSERT INTO chunks VALUES (?,?,?,?,?,?,?)",
                           (agent_id, map_version, idx, data, digest, n, len(data)))
            db.execute("UPDATE uploads SET n_chunks=?, total_count=?, lossless=? WHERE agent_id=? AND map_version=?",
                       (len(chunks), total_count, int(lossless), agent_id, map_version))
            self._complete(db, agent_id, map_version)
            return self._upload(db, agent_id, map_version)

    def discard_upload(self, agent_id: str, map_version: int) -> None:
        """Delete an incomplete upload and its chunks (no-op when absent or complete)."""
        with self._tx() as db:
            up = self._upload(db, agent_id, map_version)
            if up is not None and not up.complete:
                db.execute("DELETE FROM chunks WHERE agent_id=? AND map_version=?", (agent_id, map_version))
                db.execute("DELETE FROM uploads WHERE agent_id=? AND map_version=?", (agent_id, map_version))

    def chunk_data(self, agent_id: str, map_version: int) -> List[bytes]:
        """Raw chunks of (agent, version) in index order."""
        with self._lock:
            rows = self._conn().execute("SELECT data FROM chunks WHERE agent_id=? AND map_version=? ORDER BY idx",
                                        (agent_id, map_version)).fetchall()
        return [bytes(r[0]) for r in rows]

    def latest_complete(self) -> Dict[str, int]:
        """agent id → latest complete map version (agents with one)."""
        with self._lock:
            rows = self._conn().execute("SELECT agent_id, latest_version FROM agents ORDER BY agent_id").fetchall()
        return {r[0]: int(r[1]) for r in rows}

    # ------------------------------------------------------------------ keyframes
    def put_keyframe(self, kf: StoredKeyframe, max_per_agent: int) -> Tuple[bool, int]:
        """Store a keyframe unless (agent, frame_id) exists; evict the oldest beyond ``max_per_agent``.

        Returns:
            (new, evicted): ``new`` False for a re-sent frame id (first write wins).
        """
        with self._tx() as db:
            if db.execute("SELECT 1 FROM keyframes WHERE agent_id=? AND frame_id=?",
                          (kf.agent_id, kf.frame_id)).fetchone():
                return False, 0
            seq = db.execute("SELECT COALESCE(MAX(seq), 0) + 1 FROM keyframes WHERE agent_id=?",
                             (kf.agent_id,)).fetchone()[0]
            db.execute("INSERT INTO keyframes VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                       (kf.agent_id, kf.frame_id, seq, kf.color, kf.depth, kf.depth_scale,
                        np.asarray(kf.c2w, "<f8").tobytes(), kf.fx, kf.fy, kf.cx, kf.cy, kf.width, kf.height,
                        kf.timestamp))
            n = db.execute("SELECT COUNT(*) FROM keyframes WHERE agent_id=?", (kf.agent_id,)).fetchone()[0]
            evicted = max(0, int(n) - max_per_agent)
            if evicted:
                db.execute("DELETE FROM keyframes WHERE agent_id=? AND seq IN (SELECT seq FROM keyframes "
                           "WHERE agent_id=? ORDER BY seq LIMIT ?)", (kf.agent_id, kf.agent_id, evicted))
            return True, evicted

    def keyframe_count(self, agent_id: Optional[str] = None) -> int:
        """Keyframes buffered for ``agent_id`` (all agents when None)."""
        with self._lock:
            if agent_id is None:
                return int(self._conn().execute("SELECT COUNT(*) FROM keyframes").fetchone()[0])
            return int(self._conn().execute("SELECT COUNT(*) FROM keyframes WHERE agent_id=?",
                                            (agent_id,)).fetchone()[0])

    def keyframes(self, agents: Optional[Iterable[str]] = None) -> List[StoredKeyframe]:
        """Stored keyframes (of ``agents`` when given), ordered by agent then arrival."""
        with self._lock:
            rows = self._conn().execute(
                "SELECT agent_id, frame_id, color, depth, depth_scale, c2w, fx, fy, cx, cy, width, height, timestamp "
                "FROM keyframes ORDER BY agent_id, seq").fetchall()
        want = None if agents is None else set(agents)
        out = []
        for r in rows:
            if want is not None and r[0] not in want:
                continue
            out.append(StoredKeyframe(r[0], int(r[1]), bytes(r[2]), bytes(r[3]), float(r[4]),
                                      np.frombuffer(bytes(r[5]), "<f8").reshape(4, 4).copy(), float(r[6]),
                                      float(r[7]), float(r[8]), float(r[9]), int(r[10]), int(r[11]), float(r[12])))
        return out

    # ------------------------------------------------------------------ fused maps
    def put_fused(self, info_fn, method: int, chunks_fn) -> int:
        """Persist a fused map atomically (one transaction) and return its new version (1, 2, ...).

        Args:
            info_fn (callable(version: int, nbytes: int) -> bytes): serialized result for the
                assigned version and the total chunk bytes.
            method (int): FuseMethod value (for filtering downloads).
            chunks_fn (callable(version: int) -> list[bytes]): wire chunks encoded for that version.
        """
        with self._tx() as db:
            version = int(db.execute("INSERT INTO fused (info, method, n_chunks) VALUES (x'', ?, 0)",
                                     (method,)).lastrowid)
            chunks = chunks_fn(version)
            db.execute("UPDATE fused SET info=?, n_chunks=? WHERE version=?",
                       (info_fn(version, sum(len(c) for c in chunks)), len(chunks), version))
            db.executemany("INSERT INTO fused_chunks VALUES (?,?,?)",
                           [(version, i, c) for i, c in enumerate(chunks)])
            return version

    def fused_info(self, version: int = 0, method: int = 0) -> Optional[Tuple[int, bytes, int]]:
        """(version, info bytes, n_chunks) of ``version`` (0 = latest, of ``method`` when nonzero)."""
        with self._lock:
            db = self._conn()
            if version:
                row = db.execute("SELECT version, info, n_chunks FROM fused WHERE version=?", (version,)).fetchone()
            elif method:
                row = db.execute("SELECT version, info, n_chunks FROM fused WHERE method=? ORDER BY version DESC "
                                 "LIMIT 1", (method,)).fetchone()
            else:
                row = db.execute("SELECT version, info, n_chunks FROM fused ORDER BY version DESC LIMIT 1").fetchone()
        return (int(row[0]), bytes(row[1]), int(row[2])) if row else None

    def fused_chunk(self, version: int, idx: int) -> bytes:
        """One stored chunk of a fused map. Raises KeyError when missing."""
        with self._lock:
            row = self._conn().execute("SELECT data FROM fused_chunks WHERE version=? AND idx=?",
                                       (version, idx)).fetchone()
        if row is None:
            raise KeyError((version, idx))
        return bytes(row[0])

    def fused_infos(self) -> List[bytes]:
        """Serialized results of every fused version, ascending."""
        with self._lock:
            return [bytes(r[0]) for r in self._conn().execute("SELECT info FROM fused ORDER BY version").fetchall()]


class _Tx:
    """``with store._tx() as db``: lock + BEGIN IMMEDIATE ... COMMIT (ROLLBACK on error)."""

    def __init__(self, store: FusionStore):
        self.store = store

    def __enter__(self) -> sqlite3.Connection:
        self.store._lock.acquire()
        try:
            db = self.store._conn()
            db.execute("BEGIN IMMEDIATE")
        except BaseException:
            self.store._lock.release()
            raise
        self.db = db
        return db

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None:
                self.db.execute("COMMIT")
            else:
                self.db.execute("ROLLBACK")
        finally:
            self.store._lock.release()


__all__ = ["FusionStore", "Session", "Upload", "StoredKeyframe", "ChunkConflict", "StoreError", "DB_NAME"]
