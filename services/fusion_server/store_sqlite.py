"""The embedded SQLite backend of the fusion store (:class:`SqliteFusionStore`, the default)."""

from __future__ import annotations

import contextlib
import sqlite3
import threading
import time
from pathlib import Path
from typing import Callable, Iterator, Optional

from gausslite_services.fusion_server.store_records import StoreError
from gausslite_services.fusion_server.store_sql import FUSE_LOCKS, SqlFusionStore

DB_NAME = "fusion.sqlite3"


class SqliteFusionStore(SqlFusionStore):
    """Thread-safe SQLite store under ``data_dir`` (created when missing): the embedded default.

    One connection guarded by a lock; writes are ``BEGIN IMMEDIATE ... COMMIT`` with WAL and
    ``synchronous=FULL`` (durable at commit). :meth:`fuse_lock` is an ``flock`` on a file beside the
    database.

    Args:
        data_dir (str | Path): directory of the database.
    Raises:
        OSError: the directory cannot be created. sqlite3.DatabaseError: not a database.
        SchemaTooNew: written by a newer GaussLite.
    """

    dialect = "sqlite"

    def __init__(self, data_dir):
        self.data_dir = Path(data_dir)
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.path = self.data_dir / DB_NAME
        self.location = str(self.path)
        self._lock = threading.RLock()
        self._db: Optional[sqlite3.Connection] = sqlite3.connect(
            str(self.path), check_same_thread=False, isolation_level=None, timeout=30.0)
        try:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute("PRAGMA foreign_keys=OFF")
            self._migrate()
        except BaseException:
            self._db.close()
            self._db = None
            raise

    def _conn(self) -> sqlite3.Connection:
        if self._db is None:
            raise StoreError("store is closed")
        return self._db

    @contextlib.contextmanager
    def _tx(self, agent=None, lock=None) -> Iterator[sqlite3.Connection]:
        with self._lock:  # BEGIN IMMEDIATE already serialises every writer of the file
            db = self._conn()
            db.execute("BEGIN IMMEDIATE")
            try:
                yield db
            except BaseException:
                db.execute("ROLLBACK")
                raise
            db.execute("COMMIT")

    @contextlib.contextmanager
    def _read(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            yield self._conn()

    @contextlib.contextmanager
    def fuse_lock(self, should_stop: Callable[[], bool], poll_s: float = 0.2, name: str = "fuse"):
        """``flock`` on ``<data_dir>/<name>.lock`` (``name`` one of :data:`FUSE_LOCKS`): excludes every store (thread
        or process) on this file."""
        # lazy: fcntl exists on POSIX only
        import fcntl

        FUSE_LOCKS[name]  # noqa: B018 - an unknown name is a KeyError, as on PostgreSQL
        with open(self.data_dir / f"{name}.lock", "a+b") as f:
            while True:
                try:
                    fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if should_stop():
                        raise InterruptedError("stopped while waiting for the fuse lock") from None
                    time.sleep(poll_s)
            try:
                yield
            finally:
                fcntl.flock(f.fileno(), fcntl.LOCK_UN)

    def close(self) -> None:
        """Checkpoint and close (idempotent)."""
        with self._lock:
            if self._db is not None:
                try:
                    self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
                finally:
                    self._db.close()
                    self._db = None
