"""The PostgreSQL backend of the fusion store (:class:`PostgresFusionStore`), shared by fusion replicas through
psycopg 3 and a ``psycopg_pool`` connection pool."""

from __future__ import annotations

import contextlib
import time
from typing import Callable, Dict, Iterator

from gausslite_services.fusion_server.store_records import StoreError, StoreUnavailable
from gausslite_services.fusion_server.store_sql import LOCK_AGENT, FUSE_LOCKS, SqlFusionStore


def redact_dsn(dsn: str) -> str:
    """The DSN without its password (for logs and error messages)."""
    try:
        # lazy: heavy optional dependency, loaded only on this path
        from psycopg.conninfo import conninfo_to_dict, make_conninfo

        params = conninfo_to_dict(dsn)
        if "password" in params:
            params["password"] = "***"
        return make_conninfo("", **params)
    except Exception:  # noqa: BLE001 - unparsable: show only the scheme
        return dsn.split("://", 1)[0] + "://…"


class _PgConn:
    """Adapts a psycopg connection to the sqlite3-style ``execute(sql, params)`` used above
    (``?`` placeholders → ``%s``)."""

    _cache: Dict[str, str] = {}

    def __init__(self, conn):
        self.conn = conn

    @classmethod
    def _sql(cls, sql: str) -> str:
        out = cls._cache.get(sql)
        if out is None:
            out = cls._cache[sql] = sql.replace("?", "%s")
        return out

    def execute(self, sql: str, params=()):
        return self.conn.execute(self._sql(sql), params)

    def executemany(self, sql: str, rows) -> None:
        with self.conn.cursor() as cur:
            cur.executemany(self._sql(sql), rows)


_RECONNECT_TIMEOUT_S = 5.0  # one background reconnection series of the pool (see PostgresFusionStore)


class PostgresFusionStore(SqlFusionStore):
    """PostgreSQL store shared by any number of fusion replicas (psycopg 3 + psycopg_pool).

    Args:
        dsn (str): ``postgresql://user:password@host:port/dbname[?options]`` (libpq syntax; e.g.
            ``?options=-csearch_path%3Dmyschema`` to use a schema).
        pool_size (int): most connections held by this process (one per concurrent store call).
        connect_timeout_s (float): how long to wait for the first connection.
        acquire_timeout_s (float): how long a call waits for a pooled connection (and a new connection for
            its TCP/login handshake) before it fails with :class:`StoreUnavailable`; keeps calls short while
            the database is down, so clients see UNAVAILABLE and retry.
    Raises:
        StoreError: psycopg missing, or the database cannot be reached within ``connect_timeout_s``.
        SchemaTooNew: the schema was written by a newer GaussLite.
    """

    dialect = "postgresql"

    def __init__(self, dsn: str, pool_size: int = 12, connect_timeout_s: float = 10.0, acquire_timeout_s: float = 5.0):
        try:
            # lazy: heavy optional dependency, loaded only on this path
            import psycopg
            from psycopg_pool import ConnectionPool, PoolTimeout
        except ImportError as e:  # pragma: no cover - dependencies of the package
            raise StoreError(f"PostgreSQL store needs psycopg 3 and psycopg_pool, the 'fusion' extra "
                             f"(pip install 'gausslite[fusion]'): {e}") from e
        self.dsn = dsn
        self.location = redact_dsn(dsn)
        #: errors meaning "the database is not reachable now" (StoreUnavailable)
        self._transient = (psycopg.OperationalError, psycopg.InterfaceError, PoolTimeout)
        self._pool_timeout = PoolTimeout
        self._connect_timeout = max(1, int(acquire_timeout_s))
        self._degraded = False  # the pool found no usable connection at the last attempt
        # check: a pooled connection is tested before use, so connections broken by a database restart are
        # replaced instead of failing one call each. The pool reconnects in the background with a backoff that
        # doubles from 1 s; a short reconnect_timeout ends each such series early and the next call waiting for
        # a connection starts a fresh one (first attempt at once), so the pool refills within seconds of the
        # database's return even after a long outage
        self._pool = ConnectionPool(dsn, min_size=1, max_size=max(2, int(pool_size)), open=False,
                                    kwargs={"autocommit": False, "connect_timeout": self._connect_timeout},
                                    check=ConnectionPool.check_connection, timeout=float(acquire_timeout_s),
                                    reconnect_timeout=_RECONNECT_TIMEOUT_S, name="gausslite-fusion")
        try:
            self._pool.open(wait=True, timeout=connect_timeout_s)
        except Exception as e:  # noqa: BLE001 - PoolTimeout and friends
            self._pool.close()
            raise StoreError(f"cannot connect to the PostgreSQL fusion store {self.location} within "
                             f"{connect_timeout_s:.0f}s: {e}") from e
        self._closed = False
        try:
            self._migrate()
        except BaseException:
            self._pool.close()
            raise

    @contextlib.contextmanager
    def _reachable(self) -> Iterator[None]:
        """Translate "database unreachable" errors raised in the block into :class:`StoreUnavailable`."""
        try:
            yield
        except self._transient as e:
            if self._closed:
                raise StoreError("store is closed") from e
            raise StoreUnavailable(f"PostgreSQL fusion store {self.location} unavailable: {type(e).__name__}: "
                                   f"{str(e).strip()[:300]}") from e

    @contextlib.contextmanager
    def _connection(self) -> Iterator["object"]:
        """A connection for one transaction (committed on success, rolled back on error), from the pool.

        While the pool has no usable connection after a database outage (it reconnects in the background with
        a backoff that grows over a long outage), a call takes a connection of its own instead, so service
        resumes as soon as the database accepts connections again."""
        if self._closed:
            raise StoreError("store is closed")
        pooled, degraded = True, self._degraded
        try:
            conn = self._pool.getconn(timeout=0.05 if degraded else None)
            self._degraded = False
        except self._pool_timeout:
            if not degraded:
                self._degraded = True
                raise
            # lazy: heavy optional dependency, loaded only on this path
            import psycopg

            conn = psycopg.connect(self.dsn, autocommit=False, connect_timeout=self._connect_timeout)
            pooled = False
        try:
            with conn:  # commit / rollback; closes only a connection of its own
                yield conn
        finally:
            if pooled:
                self._pool.putconn(conn)

    @contextlib.contextmanager
    def _tx(self, agent=None, lock=None) -> Iterator[_PgConn]:
        # one transaction: committed on exit (an unreachable database at commit raises: nothing acknowledged)
        with self._reachable(), self._connection() as conn:
            if agent is not None:
                conn.execute("SELECT pg_advisory_xact_lock(%s, hashtext(%s))", (LOCK_AGENT, agent))
            if lock is not None:
                conn.execute("SELECT pg_advisory_xact_lock(%s, 0)", (lock,))
            yield _PgConn(conn)

    @contextlib.contextmanager
    def _read(self) -> Iterator[_PgConn]:
        with self._reachable(), self._connection() as conn:
            yield _PgConn(conn)

    @contextlib.contextmanager
    def fuse_lock(self, should_stop: Callable[[], bool], poll_s: float = 0.2, name: str = "fuse"):
        """Session-level advisory lock (class :data:`FUSE_LOCKS` ``[name]``) on a dedicated connection; released when
        the block ends or the connection drops (a SIGKILLed replica never blocks the others)."""
        # lazy: heavy optional dependency, loaded only on this path
        import psycopg

        lock = FUSE_LOCKS[name]
        with self._reachable(), psycopg.connect(self.dsn, autocommit=True) as conn:
            while not conn.execute("SELECT pg_try_advisory_lock(%s, 0)", (lock,)).fetchone()[0]:
                if should_stop():
                    raise InterruptedError("stopped while waiting for the fuse lock")
                time.sleep(poll_s)
            try:
                yield
            finally:
                conn.execute("SELECT pg_advisory_unlock(%s, 0)", (lock,))

    def close(self) -> None:
        """Close the pool (idempotent)."""
        if not self._closed:
            self._closed = True
            self._pool.close()
