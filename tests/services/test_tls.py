"""TLS and mutual TLS of the gRPC services (services/common/server.py) with a throwaway CA made in a
temp dir (tests/_pki.py, the openssl command line): a call over TLS succeeds; plaintext to the TLS port,
a client trusting another CA and (with mTLS) a client without a certificate are refused; the client
certificate's CN is the agent id on the fusion server; certificates rotate without a restart
(docs/security.md). Real in-process servers on ephemeral loopback ports."""

from __future__ import annotations

import logging
import shutil

import grpc
import pytest

from tests._pki import Pem, make_ca, make_leaf
from gausslite.camera import Intrinsics
from gausslite_services.cli.cmd_health import check_health
from gausslite_rpc import fusion_pb2, fusion_pb2_grpc
from gausslite_services.common.server import ServerOptions, TlsFiles, tls_files
from gausslite_services.fusion_server.client import FusionClient
from gausslite_services.fusion_server.server import serve

INTR = Intrinsics(30.0, 30.0, 15.5, 11.5, 32, 24)
#: a fresh connection per channel (gRPC shares connections between identical channels otherwise)
OPTS = [("grpc.use_local_subchannel_pool", 1)]


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    d = tmp_path_factory.mktemp("pki")
    ca, other = make_ca(d, "ca"), make_ca(d, "other-ca")
    return {"dir": d, "ca": ca, "other": other,
            "server": make_leaf(d, "server", ca, "fusion"),
            "robot-a": make_leaf(d, "robot-a", ca, "robot-a"),
            "robot-b": make_leaf(d, "robot-b", ca, "robot-b"),
            "viewer": make_leaf(d, "viewer", ca, "Fleet Viewer"),  # CN that is no agent id
            "intruder": make_leaf(d, "intruder", other, "robot-a")}  # right CN, wrong CA


def start(tmp_path, pki, *, mtls=False, **kw):
    return serve(ServerOptions(port=0, max_workers=8, grace_s=0.5, tls_cert=str(pki["server"].cert),
                               tls_key=str(pki["server"].key),
                               tls_client_ca=str(pki["ca"].cert) if mtls else None, **kw),
                 data_dir=str(tmp_path / "data"))


def channel(port, ca: Pem = None, client: Pem = None):
    if ca is None and client is None:
        return grpc.insecure_channel(f"127.0.0.1:{port}", OPTS)
    creds = grpc.ssl_channel_credentials(ca.cert_bytes() if ca else None, client.key_bytes() if client else None,
                                         client.cert_bytes() if client else None)
    return grpc.secure_channel(f"127.0.0.1:{port}", creds, OPTS)


def stats_code(port, ca=None, client=None, token=None):
    """Status code of a GetStats call (OK when it succeeds)."""
    md = (("authorization", f"Bearer {token}"),) if token else None
    with channel(port, ca, client) as ch:
        try:
            fusion_pb2_grpc.FusionStub(ch).GetStats(fusion_pb2.StatsRequest(), timeout=5, metadata=md)
        except grpc.RpcError as e:
            return e.code()
    return grpc.StatusCode.OK


def fusion_client(port, ca: Pem, client: Pem = None, token=None) -> FusionClient:
    return FusionClient(f"127.0.0.1:{port}", token=token, root_cert=ca.cert_bytes(),
                        client_cert=client.cert_bytes() if client else None,
                        client_key=client.key_bytes() if client else None, timeout_s=5)


def test_tls_call_succeeds_and_plaintext_or_wrong_ca_fails(tmp_path, pki):
    srv = start(tmp_path, pki)
    try:
        with fusion_client(srv.port, pki["ca"]) as c:
            c.wait_ready(10)
            c.open_session("robot-a", "find the cup", INTR)  # no credentials configured: open server
            assert "robot-a" in c.stats()["agents"]
        assert stats_code(srv.port, pki["ca"]) == grpc.StatusCode.OK
        # plaintext to the TLS port, and a client that trusts another CA: no connection
        assert stats_code(srv.port) == grpc.StatusCode.UNAVAILABLE
        assert stats_code(srv.port, pki["other"]) == grpc.StatusCode.UNAVAILABLE
        # health over TLS for orchestrators (gausslite health --tls-ca)
        assert check_health(srv.address, "gausslite.v1.Fusion", 5, str(pki["ca"].cert)) == "SERVING"
        assert check_health(srv.address, "", 1, None).startswith("UNREACHABLE")  # waits out its timeout
    finally:
        srv.stop(0.5)


def test_mtls_requires_a_client_certificate_of_the_ca(tmp_path, pki):
    srv = start(tmp_path, pki, mtls=True)
    try:
        assert stats_code(srv.port, pki["ca"], pki["robot-a"]) == grpc.StatusCode.OK
        # no client certificate, or one from another CA: the handshake fails
        assert stats_code(srv.port, pki["ca"]) == grpc.StatusCode.UNAVAILABLE
        assert stats_code(srv.port, pki["ca"], pki["intruder"]) == grpc.StatusCode.UNAVAILABLE
        assert stats_code(srv.port) == grpc.StatusCode.UNAVAILABLE
        ok = check_health(srv.address, "gausslite.v1.Fusion", 5, str(pki["ca"].cert), str(pki["viewer"].cert),
                          str(pki["viewer"].key))
        assert ok == "SERVING"
        assert check_health(srv.address, "", 1, str(pki["ca"].cert)).startswith("UNREACHABLE")  # waits out its timeout
    finally:
        srv.stop(0.5)


def test_mtls_certificate_cn_is_the_agent_id(tmp_path, pki, caplog):
    srv = start(tmp_path, pki, mtls=True)
    try:
        caplog.set_level(logging.WARNING)
        with fusion_client(srv.port, pki["ca"], pki["robot-a"]) as a, \
                fusion_client(srv.port, pki["ca"], pki["robot-b"]) as b, \
                fusion_client(srv.port, pki["ca"], pki["viewer"]) as viewer:
            assert a.open_session("robot-a", "find the cup", INTR).created
            b.open_session("robot-b", "find the desk", INTR)
            with pytest.raises(grpc.RpcError) as ei:
                a.open_session("robot-b", "hijack", INTR)
            assert ei.value.code() == grpc.StatusCode.PERMISSION_DENIED
            assert "agent 'robot-a' (mtls)" in ei.value.details()
            with pytest.raises(grpc.RpcError) as ei:
                viewer.open_session("robot-a", "x", INTR)
            assert ei.value.code() == grpc.StatusCode.PERMISSION_DENIED
            assert set(viewer.stats()["agents"]) == {"robot-a", "robot-b"}  # reads: every team member
        assert any("rejected OpenSession" in r.getMessage() and "PERMISSION_DENIED" in r.getMessage()
                   for r in caplog.records)
    finally:
        srv.stop(0.5)


def test_mtls_together_with_per_agent_tokens(tmp_path, pki):
    from gausslite_services.common import auth

    path = tmp_path / "tokens.json"
    tok = {a: auth.issue_token(path, a) for a in ("robot-a", "robot-b")}
    srv = start(tmp_path, pki, mtls=True, agent_tokens_file=str(path))
    try:
        ca, a_cert = pki["ca"], pki["robot-a"]
        assert stats_code(srv.port, ca, a_cert) == grpc.StatusCode.OK  # the certificate alone suffices
        assert stats_code(srv.port, ca, a_cert, tok["robot-a"]) == grpc.StatusCode.OK
        # a token of another agent than the certificate, or an unknown token: refused
        assert stats_code(srv.port, ca, a_cert, tok["robot-b"]) == grpc.StatusCode.UNAUTHENTICATED
        assert stats_code(srv.port, ca, a_cert, "nope") == grpc.StatusCode.UNAUTHENTICATED
        # a certificate that names no agent plus robot-b's token: robot-b
        with fusion_client(srv.port, ca, pki["viewer"], token=tok["robot-b"]) as c:
            c.open_session("robot-b", "find the desk", INTR)
        # revoking robot-a in the token file refuses it with either credential: token, certificate, or both
        assert auth.revoke_token(path, "robot-a")
        for t in (None, tok["robot-a"]):
            assert stats_code(srv.port, ca, a_cert, t) == grpc.StatusCode.UNAUTHENTICATED, t
        assert stats_code(srv.port, ca, pki["viewer"], tok["robot-a"]) == grpc.StatusCode.UNAUTHENTICATED
        assert stats_code(srv.port, ca, pki["viewer"], tok["robot-b"]) == grpc.StatusCode.OK  # the others still work
    finally:
        srv.stop(0.5)


def test_certificates_rotate_without_a_restart(tmp_path, pki, caplog):
    d = tmp_path / "live"
    d.mkdir()
    cert, key, client_ca = d / "server.pem", d / "server.key", d / "clients.pem"
    shutil.copy(pki["server"].cert, cert)
    shutil.copy(pki["server"].key, key)
    shutil.copy(pki["ca"].cert, client_ca)
    srv = serve(ServerOptions(port=0, grace_s=0.5, tls_cert=str(cert), tls_key=str(key), tls_client_ca=str(client_ca)),
                data_dir=str(tmp_path / "data"))
    try:
        old_ca, robot = pki["ca"], pki["robot-a"]
        assert stats_code(srv.port, old_ca, robot) == grpc.StatusCode.OK
        # 1. a new CA: clients first trust both CAs and the server accepts client certificates of both
        new_ca = make_ca(tmp_path / "new", "new-ca")
        new_server = make_leaf(tmp_path / "new", "server", new_ca, "fusion")
        new_robot = make_leaf(tmp_path / "new", "robot-a", new_ca, "robot-a")
        both = tmp_path / "both.pem"
        both.write_bytes(old_ca.cert_bytes() + new_ca.cert_bytes())
        client_ca.write_bytes(both.read_bytes())
        assert stats_code(srv.port, Pem(both, both), new_robot) == grpc.StatusCode.OK
        assert stats_code(srv.port, old_ca, robot) == grpc.StatusCode.OK
        # 2. half-written rotation (new certificate, old key): the server keeps serving the old pair
        caplog.set_level(logging.INFO)
        cert.write_bytes(new_server.cert_bytes())
        assert stats_code(srv.port, old_ca, robot) == grpc.StatusCode.OK
        assert any("still serving the previous certificate" in r.getMessage() for r in caplog.records)
        # 3. the new key lands: new connections get the new certificate, no restart
        key.write_bytes(new_server.key_bytes())
        assert stats_code(srv.port, new_ca, new_robot) == grpc.StatusCode.OK
        assert stats_code(srv.port, old_ca, robot) == grpc.StatusCode.UNAVAILABLE  # trusts only the old CA
        assert stats_code(srv.port, Pem(both, both), robot) == grpc.StatusCode.OK  # old client cert still accepted
        assert any("TLS material reloaded" in r.getMessage() for r in caplog.records)
        # 4. the old CA retires: its client certificates stop working
        client_ca.write_bytes(new_ca.cert_bytes())
        assert stats_code(srv.port, Pem(both, both), robot) == grpc.StatusCode.UNAVAILABLE
        assert stats_code(srv.port, new_ca, new_robot) == grpc.StatusCode.OK
    finally:
        srv.stop(0.5)


def test_bad_tls_options_are_precise_errors(tmp_path, pki):
    s, k = str(pki["server"].cert), str(pki["server"].key)
    with pytest.raises(ValueError, match="both a certificate and a key"):
        tls_files(s, None)
    with pytest.raises(ValueError, match="needs TLS"):
        tls_files(None, None, s)
    with pytest.raises(FileNotFoundError):
        tls_files(s, str(tmp_path / "missing.key"))
    with pytest.raises(ValueError, match="does not match"):
        TlsFiles(s, str(pki["robot-a"].key))
    junk = tmp_path / "junk.pem"
    junk.write_text("not a certificate")
    with pytest.raises(ValueError, match="client CA"):
        TlsFiles(s, k, str(junk))
    with pytest.raises(ValueError):
        FusionClient("127.0.0.1:1", client_cert=b"x")
    assert tls_files(None, None) is None
