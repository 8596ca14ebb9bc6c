"""``gausslite view --fusion`` and ``gausslite health`` speak TLS and mutual TLS with the options every client command
takes (``--tls-ca``, ``--tls-client-cert``, ``--tls-client-key``, ``--token`` / ``--token-file``; shared by
:mod:`gausslite_services.common.cli_options`) and the same environment fallbacks, against in-process fusion servers
that require a client certificate of the team's CA (throwaway PKI from tests/_pki.py)."""

from __future__ import annotations

import argparse
import logging
import threading
import time

import numpy as np
import pytest

from tests._pki import make_ca, make_leaf
from gausslite.camera import Intrinsics
from gausslite.cli import main
from gausslite.wire.codec import GaussianArrays
from gausslite_services.common.cli_options import client_credentials_from_args, client_tls_paths
from gausslite_services.common.server import ServerOptions
from gausslite_services.fusion_server.client import FusionClient
from gausslite_services.fusion_server.server import serve
from gausslite_services.sim import free_port

#: in-process gRPC servers and browser-page servers: end to end (tests/conftest.py, ``integration``)
pytestmark = pytest.mark.integration

INTR = Intrinsics(30.0, 30.0, 15.5, 11.5, 32, 24)


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    d = tmp_path_factory.mktemp("pki")
    ca = make_ca(d, "ca")
    return {"ca": ca, "server": make_leaf(d, "server", ca, "fusion"), "robot-a": make_leaf(d, "robot-a", ca, "robot-a"),
            "viewer": make_leaf(d, "viewer", ca, "fleet-viewer")}


def _subset(n: int = 400) -> GaussianArrays:
    r = np.random.default_rng(3)
    return GaussianArrays(means=r.normal(size=(n, 3)).astype(np.float32), quats=r.normal(size=(n, 4)).astype(np.float32),
                          log_scales=np.full((n, 3), -3.0, np.float32), opacity_logits=np.ones(n, np.float32),
                          colors=r.uniform(size=(n, 3)).astype(np.float32), kappa=r.integers(0, 50, n),
                          active=np.ones(n, bool))


@pytest.fixture()
def mtls_fusion(tmp_path, pki):
    """A fusion server that requires a client certificate of the CA, holding one fused version (robot-a's subset)."""
    srv = serve(ServerOptions(port=0, max_workers=8, grace_s=0.5, tls_cert=str(pki["server"].cert),
                              tls_key=str(pki["server"].key), tls_client_ca=str(pki["ca"].cert)),
                data_dir=str(tmp_path / "fusion"))
    robot = FusionClient(f"127.0.0.1:{srv.port}", root_cert=pki["ca"].cert_bytes(),
                         client_cert=pki["robot-a"].cert_bytes(), client_key=pki["robot-a"].key_bytes(), timeout_s=10)
    try:
        robot.wait_ready(10)
        robot.open_session("robot-a", "find the cup", INTR)
        assert robot.upload_subset("robot-a", 1, _subset(), full_map_gaussians=2000).complete
        fused = robot.fuse("concat")
        yield srv, fused
    finally:
        robot.close()
        srv.stop(0.5)


def _view(argv, seconds: float):
    """``gausslite view ARGV --timeout SECONDS`` in-process on a thread: (thread, result dict with "rc")."""
    result = {}
    t = threading.Thread(target=lambda: result.update(rc=main(["view", *argv, "--timeout", str(seconds)])),
                         daemon=True)
    t.start()
    return t, result


def _wait_for(caplog, text: str, t: threading.Thread, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if any(text in r.getMessage() for r in caplog.records):
            return True
        if not t.is_alive():
            break
        time.sleep(0.1)
    return any(text in r.getMessage() for r in caplog.records)


def test_view_follows_a_mutual_tls_fusion_server_with_the_client_flags(mtls_fusion, pki, caplog, monkeypatch):
    srv, fused = mtls_fusion
    for var in ("GAUSSLITE_TLS_CA", "GAUSSLITE_TLS_CLIENT_CERT", "GAUSSLITE_TLS_CLIENT_KEY", "GAUSSLITE_TOKEN",
                "GAUSSLITE_FUSION_TOKEN", "GAUSSLITE_FUSION_TOKEN_FILE"):
        monkeypatch.delenv(var, raising=False)
    caplog.set_level(logging.INFO)
    t, result = _view(["--fusion", f"127.0.0.1:{srv.port}", "--port", str(free_port()), "--poll", "0.2",
                       "--tls-ca", str(pki["ca"].cert), "--tls-client-cert", str(pki["viewer"].cert),
                       "--tls-client-key", str(pki["viewer"].key)], seconds=6)
    try:
        shown = f"showing fused version {fused.fused_version} ({fused.n_gaussians} Gaussians)"
        assert _wait_for(caplog, shown, t, 60), [r.getMessage() for r in caplog.records][-10:]
    finally:
        t.join(60)
    assert not t.is_alive() and result["rc"] == 0


def test_view_takes_the_client_certificate_from_the_environment_too(mtls_fusion, pki, caplog, monkeypatch):
    srv, fused = mtls_fusion
    monkeypatch.setenv("GAUSSLITE_TLS_CA", str(pki["ca"].cert))
    monkeypatch.setenv("GAUSSLITE_TLS_CLIENT_CERT", str(pki["viewer"].cert))
    monkeypatch.setenv("GAUSSLITE_TLS_CLIENT_KEY", str(pki["viewer"].key))
    caplog.set_level(logging.INFO)
    t, result = _view(["--fusion", f"127.0.0.1:{srv.port}", "--port", str(free_port()), "--poll", "0.2"], seconds=6)
    try:
        assert _wait_for(caplog, f"showing fused version {fused.fused_version}", t, 60)
    finally:
        t.join(60)
    assert result["rc"] == 0


def test_view_refuses_half_a_client_certificate(pki, capsys, monkeypatch):
    monkeypatch.delenv("GAUSSLITE_TLS_CLIENT_KEY", raising=False)
    rc = main(["view", "--fusion", "127.0.0.1:1", "--port", str(free_port()), "--timeout", "1",
               "--tls-ca", str(pki["ca"].cert), "--tls-client-cert", str(pki["viewer"].cert)])
    assert rc == 2
    assert "needs both the client certificate and its key" in capsys.readouterr().err


def test_health_uses_the_same_client_flags(mtls_fusion, pki, capsys, monkeypatch):
    srv, _ = mtls_fusion
    for var in ("GAUSSLITE_TLS_CA", "GAUSSLITE_TLS_CLIENT_CERT", "GAUSSLITE_TLS_CLIENT_KEY"):
        monkeypatch.delenv(var, raising=False)
    target = f"127.0.0.1:{srv.port}"
    assert main(["health", "--target", target, "--service", "gausslite.v1.Fusion", "--tls-ca", str(pki["ca"].cert),
                 "--tls-client-cert", str(pki["viewer"].cert), "--tls-client-key", str(pki["viewer"].key)]) == 0
    assert "SERVING" in capsys.readouterr().out
    # without a client certificate the server's handshake refuses the check
    assert main(["health", "--target", target, "--timeout", "1", "--tls-ca", str(pki["ca"].cert)]) == 1
    assert "UNREACHABLE" in capsys.readouterr().out


def test_client_credentials_flags_win_over_the_environment(tmp_path, pki):
    token_file = tmp_path / "viewer.token"
    token_file.write_text("file-token-0123456789abcdef\n")
    env = {"GAUSSLITE_TLS_CA": "/missing/ca.pem", "GAUSSLITE_FUSION_TOKEN": "env-token-0123456789abcdef",
           "GAUSSLITE_TOKEN": "fleet-token-0123456789abcdef"}
    args = argparse.Namespace(tls_ca=str(pki["ca"].cert), tls_client_cert=str(pki["viewer"].cert),
                              tls_client_key=str(pki["viewer"].key), token=None, token_file=str(token_file))
    creds = client_credentials_from_args(args, env)
    assert creds["token"] == "file-token-0123456789abcdef"
    assert creds["root_cert"] == pki["ca"].cert_bytes() and creds["client_key"] == pki["viewer"].key_bytes()
    # nothing given: the environment, as the agents read it
    none = argparse.Namespace(tls_ca=None, tls_client_cert=None, tls_client_key=None, token=None, token_file=None)
    assert client_credentials_from_args(none, {"GAUSSLITE_TOKEN": "fleet-token-0123456789abcdef"})["token"] == \
        "fleet-token-0123456789abcdef"
    assert client_credentials_from_args(none, {**env, "GAUSSLITE_TLS_CA": str(pki["ca"].cert)})["token"] == \
        "env-token-0123456789abcdef"
    assert client_tls_paths(none, env) == ("/missing/ca.pem", None, None)
    with pytest.raises(ValueError, match="--token or --token-file"):
        client_credentials_from_args(argparse.Namespace(**{**vars(none), "token": "a", "token_file": "f"}), {})
    with pytest.raises(ValueError, match="both the client certificate and its key"):
        client_tls_paths(none, {"GAUSSLITE_TLS_CLIENT_KEY": "k.pem"})
