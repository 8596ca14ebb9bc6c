"""deploy/k8s/: every manifest validates offline against the Kubernetes OpenAPI schemas bundled with
``kubernetes-validate`` (strict: unknown fields are errors), and the pieces fit together: fusion
replicas on the PostgreSQL DSN Secret with gRPC health probes behind a headless Service that the
agent reaches with ``dns:///`` round-robin.

Without ``kubernetes-validate`` (the ``dev`` extra) the schema tests skip on a user's machine but
fail under CI (``CI=true``), like the shared data and PostgreSQL fixtures in conftest.py."""

from __future__ import annotations

import copy
import sys
from pathlib import Path

import pytest
import yaml

from tests._ci import missing

K8S = Path(__file__).resolve().parents[2] / "deploy" / "k8s"
K8S_VERSION = "1.30.0"  # a release every managed Kubernetes still offers


def _require_validator():
    """The ``kubernetes_validate`` module; skips when it is not installed (fails under CI=true)."""
    try:
        import kubernetes_validate
    except ImportError as e:
        missing(f"kubernetes-validate not installed ({e}; pip install -e '.[dev]')")
    return kubernetes_validate


@pytest.fixture(scope="module")
def kubernetes_validate():
    """``kubernetes_validate`` (see :func:`_require_validator`)."""
    return _require_validator()


def docs():
    out = []
    for p in sorted(K8S.glob("*.yaml")):
        out += [(p.name, d) for d in yaml.safe_load_all(p.read_text()) if d]
    return out


def by_kind(kind: str, name: str) -> dict:
    hits = [d for _, d in docs() if d["kind"] == kind and d["metadata"]["name"] == name]
    assert len(hits) == 1, f"{kind}/{name}"
    return hits[0]


def test_every_manifest_validates_against_the_bundled_schemas(kubernetes_validate):
    found = docs()
    assert {d["kind"] for _, d in found} >= {"Secret", "Service", "StatefulSet", "Deployment"}
    for fname, d in found:
        kubernetes_validate.validate(d, K8S_VERSION, strict=True)  # raises ValidationError


def test_validator_rejects_broken_manifests(kubernetes_validate):
    d = copy.deepcopy(by_kind("Deployment", "fusion"))
    d["spec"]["replicas"] = "two"
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(d, K8S_VERSION, strict=True)
    d = copy.deepcopy(by_kind("Deployment", "fusion"))
    d["spec"]["template"]["spec"]["containers"][0]["readinessProbe"]["exec"]["comand"] = ["typo"]
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(d, K8S_VERSION, strict=True)


def test_missing_validator_skips_but_fails_under_ci(monkeypatch):
    monkeypatch.setitem(sys.modules, "kubernetes_validate", None)  # `import kubernetes_validate` raises
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="kubernetes-validate not installed .*required under CI=true"):
        _require_validator()
    monkeypatch.setenv("CI", "")
    with pytest.raises(pytest.skip.Exception, match="kubernetes-validate not installed"):
        _require_validator()


def _container(deploy: dict) -> dict:
    return deploy["spec"]["template"]["spec"]["containers"][0]


def _env(c: dict) -> dict:
    return {e["name"]: e for e in c.get("env", [])}


def test_fusion_replicas_share_the_store_and_probe_grpc_health():
    fusion = by_kind("Deployment", "fusion")
    assert fusion["spec"]["replicas"] >= 2
    c = _container(fusion)
    port = c["ports"][0]["containerPort"]
    assert c["command"][:3] == ["python", "-m", "gausslite_services.fusion_server"]
    assert c["command"][c["command"].index("--port") + 1] == str(port)
    ready, live = c["readinessProbe"]["exec"]["command"], c["livenessProbe"]["exec"]["command"]
    for probe in (ready, live):  # gausslite health over (mutual) TLS: the kubelet's gRPC probe cannot
        assert probe[:4] == ["gausslite", "health", "--target", f"127.0.0.1:{port}"] and "--tls-ca" in probe
        assert "--tls-client-cert" in probe
    assert ready[ready.index("--service") + 1] == "gausslite.v1.Fusion" and "--service" not in live
    ref = _env(c)["GAUSSLITE_FUSION_STORE"]["valueFrom"]["secretKeyRef"]
    secret = by_kind("Secret", ref["name"])
    assert secret["stringData"][ref["key"]].startswith("postgresql://")
    assert "@postgres:5432/" in secret["stringData"][ref["key"]]
    svc = by_kind("Service", "fusion")
    assert svc["spec"]["clusterIP"] == "None"  # headless: one DNS record per ready replica
    assert svc["spec"]["selector"] == fusion["spec"]["selector"]["matchLabels"]
    assert svc["spec"]["ports"][0]["port"] == port
    pg = by_kind("StatefulSet", "postgres")
    assert _container(pg)["image"].startswith("postgres:") and pg["spec"]["volumeClaimTemplates"]
    assert by_kind("Service", "postgres")["spec"]["ports"][0]["port"] == 5432


def test_parser_and_agent_example_are_wired_to_the_services():
    parser = _container(by_kind("Deployment", "parser"))
    assert "gausslite.v1.Parser" in parser["readinessProbe"]["exec"]["command"]
    agent = _container(by_kind("Deployment", "agent-example"))
    env = _env(agent)
    fport = by_kind("Service", "fusion")["spec"]["ports"][0]["port"]
    pport = by_kind("Service", "parser")["spec"]["ports"][0]["port"]
    assert env["GAUSSLITE_FUSION_ADDR"]["value"] == f"dns:///fusion:{fport}"
    assert env["GAUSSLITE_PARSER_ADDR"]["value"] == f"parser:{pport}"
    assert "gausslite.v1.Agent" in agent["readinessProbe"]["exec"]["command"]
    from gausslite.cli import build_parser

    for c in (parser, agent):  # the commands and probes are valid CLI invocations
        args = build_parser().parse_args(c["command"][1:])
        assert args.command == "serve"
        for probe in ("readinessProbe", "livenessProbe"):
            assert build_parser().parse_args(c[probe]["exec"]["command"][1:]).command == "health"


def _secret_mount(deploy: dict, path: str) -> tuple:
    """(volume mount, Secret name) that provide the file ``path`` in ``deploy``'s first container."""
    c = _container(deploy)
    mounts = [m for m in c.get("volumeMounts", []) if path.startswith(m["mountPath"].rstrip("/") + "/")]
    assert len(mounts) == 1, path
    volumes = {v["name"]: v for v in deploy["spec"]["template"]["spec"]["volumes"]}
    return mounts[0], volumes[mounts[0]["name"]]["secret"]["secretName"]


def test_per_robot_credentials_come_from_their_own_secrets():
    fusion, agent = by_kind("Deployment", "fusion"), by_kind("Deployment", "agent-example")
    tokens_path = _env(_container(fusion))["GAUSSLITE_AGENT_TOKENS_FILE"]["value"]
    mount, tokens_secret = _secret_mount(fusion, tokens_path)
    # a whole-volume mount (no subPath): the kubelet's Secret updates reach the pod, revocations apply live
    assert "subPath" not in mount and mount.get("readOnly") is True
    token_path = _env(_container(agent))["GAUSSLITE_FUSION_TOKEN_FILE"]["value"]
    amount, agent_secret = _secret_mount(agent, token_path)
    assert "subPath" not in amount and agent_secret != tokens_secret
    # the token file's key is the file name the server reads; the robot sees only its own token
    assert tokens_path.rsplit("/", 1)[1] == "fusion_tokens.json" and token_path.rsplit("/", 1)[1] == "token"
    names = {v.get("secret", {}).get("secretName") for v in agent["spec"]["template"]["spec"]["volumes"]}
    assert tokens_secret not in names
    readme = (K8S / "README.md").read_text()
    assert tokens_secret in readme and agent_secret in readme and "gausslite tokens" in readme


def test_every_server_runs_tls_and_per_robot_identity_and_no_pod_runs_as_root():
    """A manifest that exposes the fusion server without TLS (or without client certificates and per-agent
    tokens), a GaussLite server without TLS, or a pod that may run as root fails here."""
    from tests.deploy._policy import k8s_problems

    assert k8s_problems([d for _, d in docs()]) == []
    fusion = _container(by_kind("Deployment", "fusion"))
    env = {e["name"]: e["value"] for e in fusion["env"] if "value" in e}
    mount, secret = _secret_mount(by_kind("Deployment", "fusion"), env["GAUSSLITE_TLS_CERT"])
    assert secret == "gausslite-server-tls" and mount["readOnly"] is True
    assert env["GAUSSLITE_TLS_CLIENT_CA"].startswith(mount["mountPath"])
    readme = (K8S / "README.md").read_text()
    assert "gausslite certs provision" in readme and "gausslite-server-tls" in readme
    assert "gausslite-agent-example-tls" in readme


def test_the_policy_check_catches_plaintext_and_root():
    from tests.deploy._policy import k8s_problems

    def problems(mutate):
        found = copy.deepcopy([d for _, d in docs()])
        mutate({(d["kind"], d["metadata"]["name"]): d for d in found})
        return k8s_problems(found)

    def fusion_env(ds):
        return ds[("Deployment", "fusion")]["spec"]["template"]["spec"]["containers"][0]["env"]

    def drop(var):
        return lambda ds: fusion_env(ds).remove(next(e for e in fusion_env(ds) if e["name"] == var))

    assert any("without GAUSSLITE_TLS_CERT" in p for p in problems(drop("GAUSSLITE_TLS_CERT")))
    assert any("without GAUSSLITE_TLS_CLIENT_CA" in p for p in problems(drop("GAUSSLITE_TLS_CLIENT_CA")))
    assert any("without GAUSSLITE_AGENT_TOKENS_FILE" in p for p in problems(drop("GAUSSLITE_AGENT_TOKENS_FILE")))

    def unmount(ds):
        c = ds[("Deployment", "fusion")]["spec"]["template"]["spec"]["containers"][0]
        c["volumeMounts"] = [m for m in c["volumeMounts"] if m["name"] != "tls"]

    assert any("not provided by a mounted secret" in p for p in problems(unmount))

    def root(ds):
        ds[("Deployment", "parser")]["spec"]["template"]["spec"]["securityContext"]["runAsNonRoot"] = False

    assert any("parser" in p and "root" in p for p in problems(root))

    def grpc_probe(ds):
        c = ds[("Deployment", "agent-example")]["spec"]["template"]["spec"]["containers"][0]
        c["readinessProbe"] = {"grpc": {"port": 50061}}

    assert any("cannot speak TLS" in p for p in problems(grpc_probe))
