"""deploy/k8s/: every manifest validates offline against the Kubernetes OpenAPI schemas bundled with
``kubernetes-validate`` (strict: unknown fields are errors), and the pieces fit together: fusion
replicas on the PostgreSQL DSN Secret with gRPC health probes behind a headless Service that the
agent reaches with ``dns:///`` round-robin (issue 14)."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

kubernetes_validate = pytest.importorskip("kubernetes_validate")

K8S = Path(__file__).resolve().parents[1] / "deploy" / "k8s"
K8S_VERSION = "1.30.0"  # a release every managed Kubernetes still offers


def docs():
    out = []
    for p in sorted(K8S.glob("*.yaml")):
        out += [(p.name, d) for d in yaml.safe_load_all(p.read_text()) if d]
    return out


def by_kind(kind: str, name: str) -> dict:
    hits = [d for _, d in docs() if d["kind"] == kind and d["metadata"]["name"] == name]
    assert len(hits) == 1, f"{kind}/{name}"
    return hits[0]


def test_every_manifest_validates_against_the_bundled_schemas():
    found = docs()
    assert {d["kind"] for _, d in found} >= {"Secret", "Service", "StatefulSet", "Deployment"}
    for fname, d in found:
        kubernetes_validate.validate(d, K8S_VERSION, strict=True)  # raises ValidationError


def test_validator_rejects_broken_manifests():
    d = copy.deepcopy(by_kind("Deployment", "fusion"))
    d["spec"]["replicas"] = "two"
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(d, K8S_VERSION, strict=True)
    d = copy.deepcopy(by_kind("Deployment", "fusion"))
    d["spec"]["template"]["spec"]["containers"][0]["readinessProbe"]["grpc"]["servce"] = "typo"
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(d, K8S_VERSION, strict=True)


def _container(deploy: dict) -> dict:
    return deploy["spec"]["template"]["spec"]["containers"][0]


def _env(c: dict) -> dict:
    return {e["name"]: e for e in c.get("env", [])}


def test_fusion_replicas_share_the_store_and_probe_grpc_health():
    fusion = by_kind("Deployment", "fusion")
    assert fusion["spec"]["replicas"] >= 2
    c = _container(fusion)
    port = c["ports"][0]["containerPort"]
    assert c["command"][:3] == ["python", "-m", "services.fusion_server"]
    assert c["command"][c["command"].index("--port") + 1] == str(port)
    assert c["readinessProbe"]["grpc"] == {"port": port, "service": "gausslite.v1.Fusion"}
    assert c["livenessProbe"]["grpc"]["port"] == port
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
    assert parser["readinessProbe"]["grpc"]["service"] == "gausslite.v1.Parser"
    agent = _container(by_kind("Deployment", "agent-example"))
    env = _env(agent)
    fport = by_kind("Service", "fusion")["spec"]["ports"][0]["port"]
    pport = by_kind("Service", "parser")["spec"]["ports"][0]["port"]
    assert env["GAUSSLITE_FUSION_ADDR"]["value"] == f"dns:///fusion:{fport}"
    assert env["GAUSSLITE_PARSER_ADDR"]["value"] == f"parser:{pport}"
    assert agent["readinessProbe"]["grpc"]["service"] == "gausslite.v1.Agent"
    from gausslite.cli import build_parser

    for c in (parser, agent):  # the commands are valid CLI invocations
        args = build_parser().parse_args(c["command"][1:])
        assert args.command == "serve"
