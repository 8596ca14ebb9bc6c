"""``python -m gausslite_services.fusion_server`` startup: ``$GAUSSLITE_FUSION_STORE`` alone selects
the PostgreSQL store, and a store whose schema is newer than this server supports is refused with
exit code 2 and a clear message."""

from __future__ import annotations

import signal
import sqlite3
import sys

from gausslite_services.fusion_server.client import FusionClient
from gausslite_services.fusion_server.store import SCHEMA_VERSION, SqliteFusionStore
from tests.services.test_fusion_server import INTR
from tests.services.test_fusion_server_restart import _kill, _start


def test_store_env_var_alone_selects_postgresql(tmp_path, pg_schema_dsn):
    """No ``--store``: the DSN comes from ``$GAUSSLITE_FUSION_STORE`` only. The server logs
    "(postgresql, schema N)", writes its sessions to that database and leaves --data-dir unused."""
    import psycopg

    data_dir, port_file = tmp_path / "data", tmp_path / "port"
    proc, port = _start([sys.executable, "-m", "gausslite_services.fusion_server", "--port", "0", "--data-dir",
                         str(data_dir), "--port-file", str(port_file), "--log-level", "INFO"], data_dir, port_file,
                        {"GAUSSLITE_FUSION_STORE": pg_schema_dsn})
    try:
        with FusionClient(f"127.0.0.1:{port}", timeout_s=10) as c:
            c.wait_ready(20)
            c.open_session("env-agent", "inspect the valve", INTR)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0
        out = (tmp_path / "port.log").read_text()  # the server's output, as _start writes it
    finally:
        _kill(proc)
    assert f"(postgresql, schema {SCHEMA_VERSION})" in out, out[-2000:]
    with psycopg.connect(pg_schema_dsn) as conn:
        assert conn.execute("SELECT agent_id FROM sessions").fetchall() == [("env-agent",)]
        assert conn.execute("SELECT version FROM schema_meta").fetchone()[0] == SCHEMA_VERSION
    assert not (data_dir / "fusion.sqlite3").exists()


def test_newer_store_schema_is_refused_at_startup(tmp_path, capsys, monkeypatch):
    from gausslite_services.fusion_server.server import main

    monkeypatch.delenv("GAUSSLITE_FUSION_STORE", raising=False)  # the SQLite store in --data-dir
    data_dir = tmp_path / "data"
    SqliteFusionStore(data_dir).close()
    with sqlite3.connect(str(data_dir / "fusion.sqlite3")) as db:
        db.execute(f"UPDATE schema_meta SET version = {SCHEMA_VERSION + 1} WHERE id = 1")
    rc = main(["--port", "0", "--data-dir", str(data_dir), "--port-file", str(tmp_path / "port")])
    err = capsys.readouterr().err
    assert rc == 2
    assert "fusion server: error:" in err
    assert f"has schema version {SCHEMA_VERSION + 1}, newer than this server supports ({SCHEMA_VERSION})" in err
    assert "upgrade GaussLite" in err
    assert not (tmp_path / "port").exists()  # never served
    with sqlite3.connect(str(data_dir / "fusion.sqlite3")) as db:  # and left the newer store untouched
        assert db.execute("SELECT version FROM schema_meta").fetchone()[0] == SCHEMA_VERSION + 1
