"""``gausslite certs``: the team's CA, certificates and tokens in one command (gausslite_services.common.pki;
docs/security.md), and that what it makes works: a fusion server with mutual TLS and per-agent tokens accepts a
provisioned robot and refuses what it must."""

from __future__ import annotations

import stat

import grpc
import pytest

from gausslite.cli import main
from gausslite_services.common import auth, pki
from gausslite_services.common.server import ServerOptions
from gausslite_services.fusion_server.client import FusionClient
from gausslite_services.fusion_server.server import serve
from tests.services.test_fusion_server import INTR


def test_provision_makes_every_file_with_private_keys_and_keeps_them(tmp_path):
    d = tmp_path / "s"
    assert main(["certs", "provision", "--dir", str(d), "robot1", "robot2"]) == 0
    for name in ("ca.pem", "ca.key", "server.pem", "server.key", "robot1.pem", "robot1.key", "robot2.pem",
                 "robot2.key", "robot1.token", "robot2.token", "fusion_tokens.json"):
        assert (d / name).is_file(), name
    for key in ("ca.key", "server.key", "robot1.key", "robot1.token"):
        assert stat.S_IMODE((d / key).stat().st_mode) == 0o600, key
    info = pki.certificate_info(d / "robot1.pem")
    assert info["subject_cn"] == "robot1" and info["issuer_cn"] == "GaussLite team CA"
    assert {"robot1", "localhost", "127.0.0.1"} <= set(info["names"])
    assert pki.certificate_info(d / "server.pem")["subject_cn"] == pki.SERVER_CN
    before = (d / "robot1.pem").read_bytes()
    assert main(["certs", "provision", "--dir", str(d), "robot1", "robot3"]) == 0  # adds robot3, keeps robot1
    assert (d / "robot1.pem").read_bytes() == before and (d / "robot3.pem").is_file()
    assert main(["certs", "issue", "robot1", "--dir", str(d)]) == 0  # renewal: a new certificate, same CA
    assert (d / "robot1.pem").read_bytes() != before
    assert main(["certs", "show", str(d / "robot1.pem")]) == 0
    assert main(["certs", "provision", "--dir", str(d), "bad id!"]) == 2


def test_a_provisioned_robot_reaches_a_secure_fusion_server(tmp_path):
    d = tmp_path / "s"
    assert main(["certs", "provision", "--dir", str(d), "robot1", "robot2"]) == 0
    srv = serve(ServerOptions(port=0, host="127.0.0.1", tls_cert=str(d / "server.pem"), tls_key=str(d / "server.key"),
                              tls_client_ca=str(d / "ca.pem"), agent_tokens_file=str(d / "fusion_tokens.json")),
                data_dir=str(tmp_path / "data"))
    read = lambda n: (d / n).read_bytes()  # noqa: E731
    try:
        with FusionClient(f"localhost:{srv.port}", token=auth.read_secret(d / "robot1.token"), root_cert=read("ca.pem"),
                          client_cert=read("robot1.pem"), client_key=read("robot1.key"), timeout_s=10) as c:
            c.open_session("robot1", "find the cup", INTR)
            with pytest.raises(grpc.RpcError) as e:  # robot1 may not write robot2's data
                c.open_session("robot2", "find the desk", INTR)
            assert e.value.code() == grpc.StatusCode.PERMISSION_DENIED
        with FusionClient(f"localhost:{srv.port}", root_cert=read("ca.pem"), timeout_s=5) as c:
            with pytest.raises(grpc.RpcError):  # no client certificate: the TLS handshake fails
                c.stats()
    finally:
        srv.stop(0.5)
