"""Shared test fixtures, and the ``integration`` marker.

``integration``: end-to-end tests (``INTEGRATION``): they start processes or gRPC servers, build and export the real
detector / segmenter architectures, or run a benchmark end to end on a tiny input. The rest are unit tests:
``pytest -m "not integration"`` runs them alone (in about a minute).

``shared_datasets``: the research datasets in ``../shared/datasets``. They are never copied into the
repo. When absent, tests that need them skip on a user's machine but fail under CI (``CI=true``).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests._ci import missing

REPO = Path(__file__).resolve().parents[1]

#: test files (relative to tests/) that start processes or gRPC servers, export real model architectures, or run a
#: benchmark end to end
INTEGRATION = {
    "attention/test_onnx_real_models.py", "cli/test_cli_export_models.py",
    "bench/test_bench_long_mission.py", "bench/test_bench_odometry.py", "odometry/test_camera_only_walk.py",
    "bench/test_bench_fleet.py", "bench/test_bench_realtime.py",
    "deploy/test_deploy_compose.py", "parser/test_parser_facade.py",
    "services/test_agent_live.py", "services/test_agent_service.py", "services/test_agent_update_task.py", "services/test_bag_services.py",
    "services/test_client_errors.py", "services/test_delta_server.py", "services/test_fusion_db_outage.py",
    "services/test_fusion_hostile.py", "services/test_fusion_identity.py", "services/test_fusion_replicas.py",
    "services/test_fusion_server.py", "services/test_fusion_light_install.py",
    "services/test_fusion_server_cli.py", "services/test_fusion_server_restart.py",
    "services/test_fusion_store_contract.py", "services/test_grpc_fuzz.py", "services/test_link_outage.py",
    "services/test_metrics_services.py", "services/test_proto_parser_service.py", "services/test_sim.py",
    "services/test_tls.py", "services/test_viewer.py",
    "services/test_team_frame.py", "services/test_third_party_kappa.py", "services/test_team_doc.py",
}


def pytest_collection_modifyitems(config, items):
    """Mark the tests of the ``INTEGRATION`` files, then put every integration test (those files' and the doc
    pages') before the unit tests, in their collected order otherwise: the long tests start first and the short
    ones fill the workers' gaps at the end (longest-processing-time-first, with ``--dist worksteal``), instead of one
    worker starting a page of a minute and a half while the others run out of tests."""
    here = Path(__file__).resolve().parent
    for item in items:
        try:
            rel = Path(str(item.fspath)).resolve().relative_to(here).as_posix()
        except ValueError:
            continue
        if rel in INTEGRATION:
            item.add_marker(pytest.mark.integration)
    items.sort(key=lambda item: item.get_closest_marker("integration") is None)


SHARED = Path(os.environ.get("GAUSSLITE_SHARED", REPO.parent / "shared")).resolve()


def _require(path: Path) -> Path:
    if not path.exists():
        missing(f"shared data not found: {path}")
    return path


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """``../shared`` (or $GAUSSLITE_SHARED)."""
    return _require(SHARED)


@pytest.fixture(scope="session")
def room0_dir() -> Path:
    """Replica room0 sequence folder (``.../Replica_room0/room0``)."""
    return _require(SHARED / "datasets" / "Replica_room0" / "room0")


@pytest.fixture(scope="session")
def office0_dir() -> Path:
    """Replica office0 sequence folder (4 frames, 2000-line traj.txt)."""
    return _require(SHARED / "datasets" / "Replica_office0" / "office0")


@pytest.fixture(scope="session")
def tum_rpy_dir() -> Path:
    """TUM RGB-D fr1_rpy subset (150 frames)."""
    return _require(SHARED / "datasets" / "TUM_rgbd_dataset_freiburg1_rpy")


@pytest.fixture(scope="session")
def tasks_dir() -> Path:
    """``../shared/tasks`` with phrasings.jsonl."""
    return _require(SHARED / "tasks")


# ---------------------------------------------------------------------------------------------
# PostgreSQL (fusion store backend): $GAUSSLITE_TEST_PG_DSN, set up by .ci/run
# ---------------------------------------------------------------------------------------------
PG_DSN_ENV = "GAUSSLITE_TEST_PG_DSN"


def _pg_unavailable(reason: str):
    missing(f"PostgreSQL not available: {reason}", ci_hint=f"; .ci/run starts it and exports {PG_DSN_ENV}",
            user_hint=f" (start PostgreSQL and set {PG_DSN_ENV}=postgresql://user:pw@127.0.0.1:5432/db)")


@pytest.fixture(scope="session")
def pg_dsn() -> str:
    """DSN of a reachable PostgreSQL test database (skips / fails under CI when there is none)."""
    dsn = os.environ.get(PG_DSN_ENV, "")
    if not dsn:
        _pg_unavailable(f"${PG_DSN_ENV} is not set")
    try:
        import psycopg

        with psycopg.connect(dsn, connect_timeout=5) as conn:
            conn.execute("SELECT 1")
    except Exception as e:  # noqa: BLE001 - any connection failure means "not reachable"
        _pg_unavailable(f"cannot connect to ${PG_DSN_ENV}: {type(e).__name__}: {e}")
    return dsn


def dsn_with_schema(dsn: str, schema: str) -> str:
    """``dsn`` (URL form) with ``search_path`` set to ``schema`` (libpq ``options``)."""
    return dsn + ("&" if "?" in dsn else "?") + f"options=-csearch_path%3D{schema}"


@pytest.fixture()
def pg_schema_dsn(pg_dsn):
    """A DSN whose search_path is a fresh, empty schema (dropped after the test)."""
    import uuid

    import psycopg

    schema = "gl_test_" + uuid.uuid4().hex[:12]
    with psycopg.connect(pg_dsn, autocommit=True) as conn:
        conn.execute(f"CREATE SCHEMA {schema}")
    try:
        yield dsn_with_schema(pg_dsn, schema)
    finally:
        with psycopg.connect(pg_dsn, autocommit=True) as conn:
            conn.execute(f"DROP SCHEMA IF EXISTS {schema} CASCADE")


# ---------------------------------------------------------------------------------------------
# Real detector / segmenter architectures exported once (tests/_real_models.py)
# ---------------------------------------------------------------------------------------------
def run_folder(tmp_path_factory) -> Path:
    """The folder of this pytest run that its pytest-xdist workers share (each worker's base folder is a child of
    it); the base folder when the run has no workers."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@pytest.fixture(scope="session")
def exported_models(tmp_path_factory) -> dict:
    """``gausslite export models`` on the tiny random-weight Grounding DINO checkpoint and yolov8n-seg.yaml, built
    once per run for all its workers (:func:`tests._real_models.export_models_once` in :func:`run_folder`): the
    torch.onnx export of Grounding DINO is the slow part, and the CLI test and the ONNX backend tests read the same
    files (the tests only read them)."""
    from tests._real_models import export_models_once

    return export_models_once(run_folder(tmp_path_factory) / "exported-models")
