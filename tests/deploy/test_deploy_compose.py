"""deploy/: compose-file schema, ``docker-compose config -q``, and every compose service's own command and
environment started locally (service host names → 127.0.0.1, container ports → free local ports,
volumes → temp/bind folders, the ``postgres`` service → the test PostgreSQL, the replicas' network
alias ``dns:///fusion:PORT`` → ``ipv4:`` of both local replicas) until its healthcheck passes (two fusion
replicas on one PostgreSQL).

Per-robot credentials: compose secrets (``/run/secrets/<name>`` → the secret's file when started
locally), made for the test by the documented one command (``gausslite certs provision``); each agent gets
only its own fusion token, certificate and key, the replicas the token hashes and the server certificate, and
each token identifies its own agent. Every server runs TLS (the fusion replicas with client certificates), and
no container runs as root."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gausslite.config import load_config

from tests._ci import missing
from tests._waits import STARTUP_S
import yaml

from gausslite.cli import build_parser
from gausslite_services.sim import free_port

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
SERVERS = ("parser", "fusion_server", "fusion_server_2", "agent_a", "agent_b")
FUSION = ("fusion_server", "fusion_server_2")


@pytest.fixture(scope="module", autouse=True)
def secrets_dir(tmp_path_factory):
    """The compose secrets, made as the compose file says (``gausslite certs provision``), in a temp dir that
    ``GAUSSLITE_SECRETS_DIR`` points at for this module."""
    from gausslite.cli import main

    d = tmp_path_factory.mktemp("secrets")
    assert main(["certs", "provision", "--dir", str(d), "agent_a", "agent_b", "report"]) == 0
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("GAUSSLITE_SECRETS_DIR", str(d))
        yield d


@pytest.fixture(scope="module")
def compose():
    return yaml.safe_load((DEPLOY / "docker-compose.yml").read_text())


def _env(svc) -> dict:
    env = svc.get("environment") or {}
    if isinstance(env, list):
        env = dict(e.split("=", 1) for e in env)
    return {k: ("" if v is None else str(v)) for k, v in env.items()}


def test_compose_schema(compose):
    services = compose["services"]
    assert set(SERVERS) <= set(services)
    assert "gausslite-data" in compose["volumes"]
    for name in SERVERS:
        svc = services[name]
        assert svc["image"] == "gausslite:latest"
        test = svc["healthcheck"]["test"]
        assert test[0] == "CMD" and "health" in test and "--target" in test
        assert any(v.startswith("gausslite-data:") for v in svc.get("volumes", [])) or name in ("parser",) + FUSION
    # PostgreSQL shared by the fusion replicas, which the agents reach through one DNS name
    pg = services["postgres"]
    assert pg["image"].startswith("postgres:") and "pg_isready" in pg["healthcheck"]["test"]
    assert any(v.startswith("gausslite-pg:") for v in pg["volumes"]) and "gausslite-pg" in compose["volumes"]
    for name in FUSION:
        svc = services[name]
        assert _env(svc)["GAUSSLITE_FUSION_STORE"].startswith("postgresql://") and "@postgres:5432/" in \
            _env(svc)["GAUSSLITE_FUSION_STORE"]
        assert svc["depends_on"]["postgres"]["condition"] == "service_healthy"
        assert "fusion" in svc["networks"]["default"]["aliases"]
    for name in ("agent_a", "agent_b"):
        dep = services[name]["depends_on"]
        assert dep["parser"]["condition"] == "service_healthy"
        assert all(dep[f]["condition"] == "service_healthy" for f in FUSION)
        assert dep["scene"]["condition"] == "service_completed_successfully"
        assert _env(services[name])["GAUSSLITE_PARSER_ADDR"].startswith("parser:")
        assert _env(services[name])["GAUSSLITE_FUSION_ADDR"] == "dns:///fusion:50052"
    ta, tb = (_env(services[n])["GAUSSLITE_AGENT_TASK_ID"] for n in ("agent_a", "agent_b"))
    assert ta != tb
    assert services["report"]["depends_on"]["agent_a"]["condition"] == "service_healthy"
    # the report job's command is a valid CLI invocation attached to the four services
    cmd = services["report"]["command"]
    args = build_parser().parse_args(cmd[1:])
    assert args.command == "sim" and {kv.split("=")[0] for kv in args.attach.split(",")} == \
        {"parser", "fusion_server", "agent_a", "agent_b"}
    # the compose team maps and scores the sim's default scene as `gausslite sim` does: its frames, and the same
    # frames withheld from both mappers and scored as novel (a mismatch would score frames a robot mapped)
    scene = load_config().sim.scene
    sc = services["scene"]["command"]
    assert sc[1] == "make-scene" and int(sc[sc.index("--frames") + 1]) == scene.frames
    held = f"agent.scoring.novel_every={scene.novel_every}"
    assert all(_env(services[n])["GAUSSLITE_AGENT_SET"] == held for n in ("agent_a", "agent_b"))
    assert args.overrides == [held]
    df = (DEPLOY / "Dockerfile").read_text()
    assert "FROM python:3.11-slim" in df
    assert "torch==2.13.0" in df and "download.pytorch.org/whl/cpu" in df
    assert (DEPLOY / "gausslite.yaml").is_file()


def _secret_file(compose: dict, name: str) -> Path:
    """Local path of a compose secret's ``file`` (compose variable substitution, relative to deploy/)."""
    return (DEPLOY / _interpolate(compose["secrets"][name]["file"])).resolve()


def _secret_names(svc: dict) -> list:
    return [s if isinstance(s, str) else s["source"] for s in svc.get("secrets", [])]


def test_compose_provisions_per_robot_credentials(compose):
    from gausslite_services.common.auth import AgentTokens, read_secret

    services = compose["services"]

    def secret_of(name: str, var: str) -> str:
        path = _env(services[name])[var]
        assert path.startswith("/run/secrets/"), (name, var, path)
        secret = path[len("/run/secrets/"):]
        assert secret in _secret_names(services[name]) and secret in compose["secrets"]
        return secret

    hashes = {secret_of(n, "GAUSSLITE_AGENT_TOKENS_FILE") for n in FUSION}
    assert len(hashes) == 1
    hashes = hashes.pop()
    store = AgentTokens(_secret_file(compose, hashes))  # a valid token file: only hashes
    identity = {}
    from gausslite_services.common.pki import certificate_info

    for name in ("agent_a", "agent_b", "report"):
        secret = secret_of(name, "GAUSSLITE_FUSION_TOKEN_FILE")
        cert, key = secret_of(name, "GAUSSLITE_TLS_CLIENT_CERT"), secret_of(name, "GAUSSLITE_TLS_CLIENT_KEY")
        # its own token, certificate and key, and the CA's certificate: nothing else
        assert sorted(_secret_names(services[name])) == sorted([secret, "tls_ca", cert, key])
        assert certificate_info(_secret_file(compose, cert))["subject_cn"] == name
        token = read_secret(_secret_file(compose, secret))
        assert token not in _secret_file(compose, hashes).read_text()
        identity[name] = store.identify(token)
    assert identity == {"agent_a": "agent_a", "agent_b": "agent_b", "report": "report"}
    for name in ("agent_a", "agent_b"):  # each agent pushes under the id its token names
        assert _env(services[name])["GAUSSLITE_AGENT_ID"] == identity[name]
    for name, svc in services.items():  # only the fusion replicas see the token hashes
        assert (hashes in _secret_names(svc)) == (name in FUSION), name
        # the server key only on the parser and the replicas, a robot's key only on that robot
        assert ("server_key" in _secret_names(svc)) == (name in ("parser",) + FUSION), name
        for robot in ("agent_a", "agent_b", "report"):
            assert (f"{robot}_key" in _secret_names(svc)) == (name == robot), (name, robot)
    assert "ca.key" not in " ".join(str(s.get("file")) for s in compose["secrets"].values())


def test_compose_runs_tls_and_per_robot_identity_and_no_root(compose):
    """The fusion replicas never listen without TLS, client certificates and per-agent tokens; parser and agents
    serve TLS; the image and every service run as a non-root user."""
    import copy

    from tests.deploy._policy import compose_problems

    dockerfile = (DEPLOY / "Dockerfile").read_text()
    assert compose_problems(compose, dockerfile) == []
    # the check fails a manifest that exposes the fusion server in plaintext, or a root container
    plain = copy.deepcopy(compose)
    del plain["services"]["fusion_server"]["environment"]["GAUSSLITE_TLS_CERT"]
    assert any("fusion_server: the fusion server runs without GAUSSLITE_TLS_CERT" in p
               for p in compose_problems(plain, dockerfile))
    no_mtls = copy.deepcopy(compose)
    del no_mtls["services"]["fusion_server"]["environment"]["GAUSSLITE_TLS_CLIENT_CA"]
    assert compose_problems(no_mtls, dockerfile)
    unmounted = copy.deepcopy(compose)
    unmounted["services"]["agent_a"]["secrets"].remove("agent_a_key")
    assert any("not provided by a mounted secret" in p for p in compose_problems(unmounted, dockerfile))
    assert any("root" in p for p in compose_problems(compose, dockerfile + "\nUSER root\n"))


def test_docker_compose_config_validates():
    exe = shutil.which("docker-compose")
    if exe is None:
        missing("docker-compose binary not installed", ci_hint="; .ci/run installs it")
    r = subprocess.run([exe, "-f", str(DEPLOY / "docker-compose.yml"), "config", "-q"], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stderr


def _local_command(name: str, svc: dict, local_port: dict, paths: dict, pg_dsn: str = ""):
    hosts = {n: local_port[n] for n in local_port}
    argv = list(svc["command"])
    container_port = None
    if "--port" in argv:
        container_port = argv[argv.index("--port") + 1]
    res = []
    for i, a in enumerate(argv):
        a = str(a)
        if i > 0 and argv[i - 1] == "--port":
            a = str(local_port[name])
        elif i > 0 and argv[i - 1] == "--host":
            a = "127.0.0.1"
        else:
            a = _map(a, hosts, paths)
        res.append(a)
    env = {k: (pg_dsn if k == "GAUSSLITE_FUSION_STORE" else _map(v, hosts, paths)) for k, v in _env(svc).items()}
    if res[0] == "gausslite":
        res = [sys.executable, "-m", "gausslite.cli", *res[1:]]
    elif res[0] == "python":
        res = [sys.executable, *res[1:]]
    health = None
    if "healthcheck" in svc:
        t = [str(x) for x in svc["healthcheck"]["test"][1:]]
        t = [f"127.0.0.1:{local_port[name]}" if container_port and x == f"127.0.0.1:{container_port}"
             else _map(x, hosts, paths) for x in t]  # the probe's secrets (TLS files) too
        health = [sys.executable, "-m", "gausslite.cli", *t[1:]] if t[0] == "gausslite" else t
    return res, env, health


def _interpolate(value: str) -> str:
    """Compose variable substitution: ``${VAR}``, ``${VAR:-default}`` from the test's environment."""
    return re.sub(r"\$\{(\w+)(?::?-([^}]*))?\}", lambda m: os.environ.get(m.group(1)) or (m.group(2) or ""), value)


def _map(value: str, hosts: dict, paths: dict) -> str:
    value = _interpolate(value)
    if value.startswith("dns:///fusion:"):  # the replicas' network alias → both local replicas
        return "ipv4:" + ",".join(f"127.0.0.1:{hosts[n]}" for n in FUSION)
    for host, port in hosts.items():
        if ":" in value and value.split(":")[0] == host and value.split(":")[1].isdigit():
            return f"127.0.0.1:{port}"
    for container, local in sorted(paths.items(), key=lambda kv: -len(kv[0])):
        if value == container or value.startswith(container + "/"):
            return local + value[len(container):]
    return value


def test_each_compose_service_starts_locally_and_gets_healthy(compose, tmp_path, pg_schema_dsn):
    services = compose["services"]
    local_port = {n: free_port() for n in SERVERS}
    paths = {}
    for name, svc in services.items():
        for v in svc.get("volumes", []):
            src, dst = v.split(":")[:2]
            if src.startswith("."):
                paths[dst] = str((DEPLOY / src).resolve())
            else:
                (tmp_path / src).mkdir(exist_ok=True)
                paths[dst] = str(tmp_path / src)
        for secret in svc.get("secrets", []):  # compose mounts secrets at /run/secrets/<target>
            src = secret if isinstance(secret, str) else secret["source"]
            target = secret if isinstance(secret, str) else secret.get("target", src)
            paths[f"/run/secrets/{target}"] = str(_secret_file(compose, src))
    base_env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
    procs = {}
    try:
        # the one-shot scene generator first (agents depend on it completing successfully)
        cmd, env, _ = _local_command("scene", services["scene"], local_port, paths)
        r = subprocess.run(cmd, env={**base_env, **env}, cwd=str(REPO), capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr[-2000:]
        assert (Path(paths["/data"]) / "scene" / "agent_a" / "traj.txt").is_file()
        for group in (("parser",) + FUSION, ("agent_a", "agent_b")):  # depends_on order (postgres: the test's)
            checks = {}
            for name in group:
                cmd, env, health = _local_command(name, services[name], local_port, paths, pg_schema_dsn)
                assert health is not None and str(local_port[name]) in " ".join(health)
                log = open(tmp_path / f"{name}.log", "w")
                procs[name] = subprocess.Popen(cmd, env={**base_env, **env}, cwd=str(REPO), stdout=log,
                                               stderr=subprocess.STDOUT, start_new_session=True)
                checks[name] = health
            for name, health in checks.items():
                deadline = time.monotonic() + STARTUP_S
                ok = False
                while time.monotonic() < deadline and not ok:
                    assert procs[name].poll() is None, (tmp_path / f"{name}.log").read_text()[-2000:]
                    ok = subprocess.run(health, env=base_env, cwd=str(REPO), capture_output=True,
                                        timeout=30).returncode == 0
                    if not ok:
                        time.sleep(0.5)
                assert ok, f"{name} not healthy: " + (tmp_path / f"{name}.log").read_text()[-2000:]
        # the agents really started their missions with the compose settings
        from gausslite_services.agent.client import AgentClient

        def secret_bytes(service: str, var: str) -> bytes:
            return Path(paths[_env(services[service])[var]]).read_bytes()

        report_tls = {"root_cert": secret_bytes("report", "GAUSSLITE_TLS_CA"),
                      "client_cert": secret_bytes("report", "GAUSSLITE_TLS_CLIENT_CERT"),
                      "client_key": secret_bytes("report", "GAUSSLITE_TLS_CLIENT_KEY")}
        for name in ("agent_a", "agent_b"):
            token = _interpolate(_env(services[name]).get("GAUSSLITE_TOKEN", "")) or None
            with AgentClient(f"127.0.0.1:{local_port[name]}", token=None) as plain:  # TLS only
                with pytest.raises(Exception):
                    plain.wait_ready(2)
            with AgentClient(f"127.0.0.1:{local_port[name]}", token=token, **report_tls) as c:
                deadline = time.monotonic() + STARTUP_S
                while True:
                    try:
                        st = c.status()
                        break
                    except Exception:
                        assert time.monotonic() < deadline
                        time.sleep(0.5)
                assert st.agent_id == name
                assert st.task_id == _env(services[name])["GAUSSLITE_AGENT_TASK_ID"]
        # the replicas know each robot by its own token: agent_a reads, but may not write agent_b
        import grpc

        from gausslite.camera import Intrinsics
        from gausslite_services.common.auth import read_secret
        from gausslite_services.fusion_server.client import FusionClient

        token_a = read_secret(paths[_env(services["agent_a"])["GAUSSLITE_FUSION_TOKEN_FILE"]])
        tls_a = {"root_cert": secret_bytes("agent_a", "GAUSSLITE_TLS_CA"),
                 "client_cert": secret_bytes("agent_a", "GAUSSLITE_TLS_CLIENT_CERT"),
                 "client_key": secret_bytes("agent_a", "GAUSSLITE_TLS_CLIENT_KEY")}
        fusion_addr = f"127.0.0.1:{local_port['fusion_server']}"
        with FusionClient(fusion_addr, token=token_a, max_retries=0, **tls_a) as fc:
            fc.stats()
            with pytest.raises(grpc.RpcError) as ei:
                fc.open_session("agent_b", "probe", Intrinsics(100.0, 100.0, 31.5, 23.5, 64, 48))
            assert ei.value.code() == grpc.StatusCode.PERMISSION_DENIED
        # without a client certificate, or in plaintext, the replicas take nothing
        for kw in ({"root_cert": tls_a["root_cert"]}, {}):
            with FusionClient(fusion_addr, token=token_a, max_retries=0, timeout_s=3, **kw) as fc:
                with pytest.raises(grpc.RpcError) as ei:
                    fc.stats()
                assert ei.value.code() == grpc.StatusCode.UNAVAILABLE
    finally:
        # An agent stopped with SIGTERM ends its mission first (share fine-tune, final pass, final push retried
        # for up to agent.push.final_timeout_s), which is not what this test checks: the agents and their share
        # workers (one process group each) are killed outright. The parser and the replicas stop on SIGTERM.
        for name, p in procs.items():
            if name.startswith("agent") and p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
            elif p.poll() is None:
                p.terminate()
        for p in procs.values():
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)
