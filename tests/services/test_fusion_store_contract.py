"""The fusion-store contract, run against both backends: the embedded SQLite store and the
PostgreSQL store (psycopg 3 + psycopg_pool) that fusion replicas share.

Each test opens stores through ``opener()``; a second ``opener()`` is a second, independent store
on the same database (another connection, or another replica)."""

from __future__ import annotations

import dataclasses
import sqlite3
import threading
import time

import numpy as np
import pytest

from gausslite.wire.codec import LOSSLESS, decode_chunk, encode_subset, peek_header
from gausslite_services.fusion_server.store import (SCHEMA_VERSION, ChunkConflict, PostgresFusionStore, SchemaTooNew,
                                                    Session, SqliteFusionStore, StoredKeyframe, StoreError, open_store)
from tests.services.test_fusion_server import rand_subset


@pytest.fixture(params=["sqlite", "postgresql"])
def backend(request, tmp_path):
    """(kind, opener, raw_sql) for one backend; every store opened is closed after the test."""
    opened = []
    if request.param == "sqlite":
        spec = str(tmp_path / "store")

        def raw(sql):
            with sqlite3.connect(str(tmp_path / "store" / "fusion.sqlite3")) as db:
                db.execute(sql)
    else:
        spec = request.getfixturevalue("pg_schema_dsn")

        def raw(sql):
            import psycopg

            with psycopg.connect(spec, autocommit=True) as conn:
                conn.execute(sql)

    def opener():
        s = open_store(spec)
        opened.append(s)
        return s

    yield request.param, opener, raw
    for s in opened:
        s.close()


def chunks_of(agent, version, n=900, per=300, seed=0):
    """Real wire chunks of a random subset: [(data, digest, count, total, lossless)]."""
    out = []
    for c in encode_subset(rand_subset(n, 0.0, seed), agent, version, chunk_gaussians=per, quant=LOSSLESS):
        h = peek_header(c)
        out.append((c, decode_chunk(c).digest, h.count, h.total_count, h.lossless))
    return out


def put(store, agent, version, chunk, idx):
    data, digest, count, total, lossless = chunk
    return store.put_chunk(agent, version, idx, data, digest, count, total, lossless)


def test_backend_selected_by_spec(backend):
    kind, opener, _ = backend
    s = opener()
    assert isinstance(s, PostgresFusionStore if kind == "postgresql" else SqliteFusionStore)
    assert s.schema_version() == SCHEMA_VERSION


def test_every_write_is_persisted_before_it_returns(backend):
    _, opener, _ = backend
    a = opener()
    assert a.open_session(Session("r1", "find the cup", 30.0, 31.0, 15.5, 11.5, 32, 24))
    ch = chunks_of("r1", 1)
    a.begin_upload("r1", 1, len(ch), 9000, 0)
    new, up = put(a, "r1", 1, ch[0], 0)
    assert new and up.stored == [0] and not up.complete
    b = opener()  # another connection / another replica sees it at once
    assert b.session("r1") == Session("r1", "find the cup", 30.0, 31.0, 15.5, 11.5, 32, 24)
    up_b = b.upload("r1", 1)
    assert up_b.stored == [0] and up_b.missing == [1, 2] and up_b.full_map_gaussians == 9000
    assert up_b.n_gaussians == 300 and up_b.wire_bytes == len(ch[0][0])
    assert b.chunk_data("r1", 1) == [ch[0][0]]
    a.close()
    c = opener()
    assert c.upload("r1", 1).stored == [0]


def test_uploads_are_idempotent_and_resumable_across_stores(backend):
    _, opener, _ = backend
    a, b = opener(), opener()
    ch = chunks_of("r1", 4)
    a.begin_upload("r1", 4, 3, 0, 0)
    assert put(a, "r1", 4, ch[2], 2)[0]
    assert not put(b, "r1", 4, ch[2], 2)[0]  # identical re-delivery through another store: no-op
    with pytest.raises(ChunkConflict):
        put(b, "r1", 4, ch[0], 2)  # same index, other content
    with pytest.raises(ValueError, match="announced with 3 chunks"):
        b.begin_upload("r1", 4, 5, 0, 0)
    up = b.begin_upload("r1", 4, 3, 0, 0)  # resume elsewhere: the state says what is missing
    assert up.missing == [0, 1]
    put(b, "r1", 4, ch[0], 0)
    new, up = put(a, "r1", 4, ch[1], 1)
    assert new and up.complete and up.n_gaussians == 900
    assert a.latest_version("r1") == 4 and b.latest_complete() == {"r1": 4}
    assert b"".join(b.chunk_data("r1", 4)) == b"".join(c[0] for c in ch)
    with pytest.raises(ValueError, match="no upload announced"):
        put(a, "r1", 99, ch[0], 0)


def test_newer_complete_version_supersedes_older(backend):
    _, opener, _ = backend
    s = opener()
    v1, v2 = chunks_of("r1", 1, n=300), chunks_of("r1", 2, n=600, seed=1)
    s.begin_upload("r1", 1, 1, 0, 0)
    s.begin_upload("r1", 2, 2, 0, 0)
    put(s, "r1", 2, v2[0], 0)
    assert put(s, "r1", 1, v1[0], 0)[1].complete
    assert s.latest_version("r1") == 1
    assert put(s, "r1", 2, v2[1], 1)[1].complete
    assert s.latest_version("r1") == 2
    assert s.upload("r1", 1) is None and s.chunk_data("r1", 1) == []  # older data deleted
    # completing an older version after a newer one never moves "latest" back
    v0 = chunks_of("r1", 0, n=300, seed=2)
    s.begin_upload("r1", 0, 1, 0, 0)
    put(s, "r1", 0, v0[0], 0)
    assert opener().latest_version("r1") == 2


def _kf(agent, frame_id, k=0.0):
    c2w = np.eye(4)
    c2w[0, 3] = k
    return StoredKeyframe(agent, frame_id, b"\xff\xd8\xff" + bytes([frame_id % 256]), b"png", 5000.0, c2w,
                          30.0, 30.0, 15.5, 11.5, 32, 24, 1.5 * frame_id)


def test_keyframes_are_bounded_and_idempotent(backend):
    _, opener, _ = backend
    a, b = opener(), opener()
    results = [(a if i % 2 else b).put_keyframe(_kf("r1", i, 0.1 * i), 4) for i in range(7)]
    assert [r[0] for r in results] == [True] * 7 and sum(r[1] for r in results) == 3
    assert a.put_keyframe(_kf("r1", 6), 4) == (False, 0)  # re-sent frame id: first write wins
    a.put_keyframe(_kf("r2", 0), 4)
    assert b.keyframe_count("r1") == 4 and b.keyframe_count() == 5
    kept = b.keyframes(["r1"])
    assert [k.frame_id for k in kept] == [3, 4, 5, 6]  # oldest by arrival evicted
    assert kept[-1].c2w[0, 3] == pytest.approx(0.6) and kept[-1].timestamp == 9.0
    assert kept[0].color == _kf("r1", 3).color and kept[0].depth_scale == 5000.0
    assert kept[0].roi == b""  # no ROI sent
    # a keyframe's task ROI (schema 3) round-trips
    a.put_keyframe(dataclasses.replace(_kf("r3", 1), roi=b"\x89PNG-roi"), 4)
    assert [k.roi for k in b.keyframes(["r3"])] == [b"\x89PNG-roi"]


def test_fused_versions_are_allocated_by_the_database_and_monotonic(backend):
    _, opener, _ = backend
    stores = [opener(), opener()]
    got, errors = [], []

    def work(s, k):
        try:
            for i in range(5):
                v = s.put_fused(lambda v, n: f"info {v} {n}".encode(), 1 + (i % 2),
                                lambda v: [bytes([v % 256]) * 10, b"x" * (v + k)])
                got.append(v)
        except Exception as e:  # noqa: BLE001
            errors.append(e)

    threads = [threading.Thread(target=work, args=(stores[i % 2], i)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors
    assert sorted(got) == list(range(1, 21))
    s = opener()
    infos = s.fused_infos()
    assert [int(i.split()[1]) for i in infos] == list(range(1, 21))
    version, info, n = s.fused_info()
    assert version == 20 and n == 2 and info.startswith(b"info 20 ")
    assert s.fused_info(0, method=1)[0] == max(v for v in range(1, 21) if s.fused_info(v)[1])  # exists
    assert s.fused_chunk(7, 0) == bytes([7]) * 10
    with pytest.raises(KeyError):
        s.fused_chunk(7, 2)
    assert s.fused_info(21) is None


def test_fuse_lock_serialises_fusions_across_stores(backend):
    _, opener, _ = backend
    a, b = opener(), opener()
    inside = threading.Event()
    release = threading.Event()

    def holder():
        with a.fuse_lock(lambda: False):
            inside.set()
            release.wait(30)

    t = threading.Thread(target=holder)
    t.start()
    assert inside.wait(10)
    t0 = time.monotonic()
    with pytest.raises(InterruptedError):  # b waits while a holds it, and gives up when told to
        with b.fuse_lock(lambda: time.monotonic() - t0 > 0.5, poll_s=0.05):
            pytest.fail("entered while another store held the fuse lock")
    assert time.monotonic() - t0 >= 0.5
    release.set()
    t.join(10)
    with b.fuse_lock(lambda: False, poll_s=0.05):
        pass


def test_newer_schema_is_refused_with_a_clear_error(backend):
    _, opener, raw = backend
    opener().close()
    raw(f"UPDATE schema_meta SET version = {SCHEMA_VERSION + 1} WHERE id = 1")
    with pytest.raises(SchemaTooNew, match=f"schema version {SCHEMA_VERSION + 1}, newer than this server "
                                           f"supports \\({SCHEMA_VERSION}\\)"):
        opener()
    assert issubclass(SchemaTooNew, StoreError)


def test_sqlite_store_of_the_pre_migration_layout_is_upgraded(tmp_path):
    d = tmp_path / "old"
    d.mkdir()
    with sqlite3.connect(str(d / "fusion.sqlite3")) as db:  # the layout before versioned migrations
        db.executescript(
            "CREATE TABLE sessions (agent_id TEXT PRIMARY KEY, task_text TEXT NOT NULL, fx REAL NOT NULL, "
            "fy REAL NOT NULL, cx REAL NOT NULL, cy REAL NOT NULL, width INTEGER NOT NULL, height INTEGER NOT NULL, "
            "opened_unix REAL NOT NULL);"
            "CREATE TABLE fused (version INTEGER PRIMARY KEY AUTOINCREMENT, info BLOB NOT NULL, "
            "method INTEGER NOT NULL, n_chunks INTEGER NOT NULL);"
            "INSERT INTO sessions VALUES ('old', 't', 1, 1, 0, 0, 2, 2, 0);"
            "INSERT INTO fused (info, method, n_chunks) VALUES (x'01', 1, 0);")
    s = SqliteFusionStore(d)
    try:
        assert s.schema_version() == SCHEMA_VERSION
        assert s.session("old").task_text == "t"
        assert s.put_fused(lambda v, n: b"i", 1, lambda v: []) == 2  # continues the old numbering
        with sqlite3.connect(str(d / "fusion.sqlite3")) as db:
            names = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='index'")}
        assert "fused_method_version" in names  # migration 2 ran
        with sqlite3.connect(str(d / "fusion.sqlite3")) as db:
            cols = {r[1] for r in db.execute("PRAGMA table_info(keyframes)")}
        assert "roi" in cols  # migration 3 ran
    finally:
        s.close()


def test_unreachable_postgres_is_a_clear_store_error():
    with pytest.raises(StoreError, match="cannot connect to the PostgreSQL fusion store .*\\*\\*\\*"):
        PostgresFusionStore("postgresql://nobody:secret@127.0.0.1:1/none", connect_timeout_s=1)


def test_delta_upload_completes_only_with_its_rebuilt_subset(backend):
    """Delta pushes: the last delta chunk leaves the upload incomplete; the rebuilt full
    subset replaces the delta chunks and completes it in one transaction; an abandoned delta is
    discarded. Same contract on both backends."""
    _, opener, _ = backend
    a, b = opener(), opener()
    delta = chunks_of("r1", 2, n=300, per=300, seed=1)
    a.begin_upload("r1", 2, len(delta), 0, 0)
    new, up = a.put_chunk("r1", 2, 0, delta[0][0], delta[0][1], delta[0][2], delta[0][3], delta[0][4],
                          defer_complete=True)
    assert new and not up.complete and b.latest_complete() == {}
    full = chunks_of("r1", 2, n=900, per=300, seed=2)
    done = b.complete_rebuilt("r1", 2, [(c[0], c[1], c[2]) for c in full], 900, True)
    assert done.complete and done.n_gaussians == 900 and a.latest_version("r1") == 2
    assert a.chunk_data("r1", 2) == [c[0] for c in full]
    with pytest.raises(ValueError, match="no incomplete upload"):
        a.complete_rebuilt("r1", 2, [(c[0], c[1], c[2]) for c in full], 900, True)
    a.begin_upload("r1", 3, 1, 0, 0)
    a.put_chunk("r1", 3, 0, delta[0][0], delta[0][1], delta[0][2], delta[0][3], delta[0][4], defer_complete=True)
    b.discard_upload("r1", 3)
    assert a.upload("r1", 3) is None and a.latest_version("r1") == 2


def test_sessions_are_listed_in_pages(backend):
    """``sessions(after, limit)``: agent-id order, at most ``limit``, strictly after ``after`` (GetStats paging)."""
    _, opener, _ = backend
    s = opener()
    ids = ["r-b", "r-a", "r-d", "r-c", "r-e"]
    for a in ids:
        s.open_session(Session(a, "find the cup", 30.0, 31.0, 15.5, 11.5, 32, 24))
    assert [x.agent_id for x in s.sessions()] == sorted(ids)
    assert [x.agent_id for x in s.sessions(limit=2)] == ["r-a", "r-b"]
    assert [x.agent_id for x in s.sessions(after="r-b", limit=2)] == ["r-c", "r-d"]
    assert [x.agent_id for x in s.sessions(after="r-d", limit=2)] == ["r-e"]
    assert s.sessions(after="r-e") == []
