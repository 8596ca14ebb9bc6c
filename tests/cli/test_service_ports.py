"""One port per service everywhere: the parser on 50051, the fusion server on 50052, the agents on 50061 and up — in
the code's defaults (``gausslite serve``, ``python -m gausslite_services.fusion_server``), the README, the docs, the
deployment files (compose, Kubernetes, the Dockerfile) and the clients' docstrings. A mismatch names the file, the
line and what it found."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Iterator, List, Tuple

import yaml

from gausslite_services.cli.cmd_serve import SERVICES
from gausslite_services.fusion_server import options as fusion_options
from gausslite_services.fusion_server import server as fusion_server
from tests.deploy._policy import server_kind

REPO = Path(__file__).resolve().parents[2]
PARSER_PORT, FUSION_PORT, AGENT_PORT = 50051, 50052, 50061
#: what the checks read: the docs, the deployment files and the product's code
SCANNED = ("README.md", "docs", "deploy", "services", "gausslite", "scripts")
#: text that ties a port to one service (the port is the last group)
REFERENCES = {
    FUSION_PORT: [r"fusion[\w.-]*:(\d{5})\b",  # fusion:P, fusion_server:P, fusion-host:P, fusion.example:P
                  r"--fusion[= ]\S*?:(\d{5})\b", r"FUSION_ADDR\W+[^\s,]*?:(\d{5})\b",
                  r"FusionClient\(\s*\"[^\"]*?:(\d{5})\b",
                  r"(?:serve fusion|gausslite_services\.fusion_server)\b[^\n]*?--port\W+(\d{5})\b"],
    PARSER_PORT: [r"parser[\w.-]*:(\d{5})\b", r"--parser[= ]\S*?:(\d{5})\b", r"PARSER_ADDR\W+[^\s,]*?:(\d{5})\b",
                  r"serve parser\b[^\n]*?--port\W+(\d{5})\b"],
}


def _files() -> List[Path]:
    out = []
    for name in SCANNED:
        path = REPO / name
        out += [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file()
                                                    and p.suffix in (".md", ".py", ".yml", ".yaml", ".sh", "")
                                                    and "__pycache__" not in p.parts)
    return out


def _lines() -> Iterator[Tuple[str, int, str]]:
    for path in _files():
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        for i, line in enumerate(text.splitlines(), 1):
            yield str(path.relative_to(REPO)), i, line


def test_the_code_defaults_are_the_service_ports():
    assert SERVICES["parser"].default_port == PARSER_PORT
    assert SERVICES["fusion"].default_port == fusion_options.DEFAULT_PORT == fusion_server.DEFAULT_PORT == FUSION_PORT
    assert SERVICES["agent"].default_port == AGENT_PORT
    help_text = fusion_options.build_parser().format_help()
    assert f"default {FUSION_PORT})" in " ".join(help_text.split())


def test_no_other_port_in_the_services_range():
    """A number 50050..50059 that is no service's port (e.g. a fusion server documented on 50053) is a mismatch."""
    bad = [f"{f}:{i}: {m.group(0)} in: {line.strip()[:160]}" for f, i, line in _lines()
           for m in re.finditer(r"(?<![\d.])5005\d(?!\d)", line) if int(m.group(0)) not in (PARSER_PORT, FUSION_PORT)]
    assert not bad, "ports of no service:\n" + "\n".join(bad)


def test_every_reference_to_a_service_uses_its_port():
    bad, seen = [], {FUSION_PORT: 0, PARSER_PORT: 0}
    for f, i, line in _lines():
        for port, patterns in REFERENCES.items():
            for pattern in patterns:
                for m in re.finditer(pattern, line):
                    seen[port] += 1
                    if int(m.group(m.lastindex)) != port:
                        bad.append(f"{f}:{i}: {m.group(0)!r} (expected port {port})")
    assert not bad, "service addresses with another service's port:\n" + "\n".join(bad)
    assert seen[FUSION_PORT] >= 10 and seen[PARSER_PORT] >= 5, seen  # the patterns still find the docs' addresses


def _containers(node) -> Iterator[dict]:
    """Every mapping with a ``command`` list (compose services, Kubernetes containers)."""
    if isinstance(node, dict):
        if isinstance(node.get("command"), list):
            yield node
        for v in node.values():
            yield from _containers(v)
    elif isinstance(node, list):
        for v in node:
            yield from _containers(v)


def _health_targets(container: dict) -> List[str]:
    probes = [(container.get("healthcheck") or {}).get("test")]
    probes += [((container.get(k) or {}).get("exec") or {}).get("command") for k in ("readinessProbe", "livenessProbe")]
    return [p[p.index("--target") + 1] for p in probes if isinstance(p, list) and "--target" in p]


def test_deployment_files_serve_and_probe_each_service_on_its_port():
    expected = {"parser": PARSER_PORT, "fusion": FUSION_PORT}
    checked = set()
    for path in sorted((REPO / "deploy").rglob("*.y*ml")):
        for doc in yaml.safe_load_all(path.read_text(encoding="utf-8")):
            for c in _containers(doc):
                cmd = [str(x) for x in c["command"]]
                kind = server_kind(cmd)
                if kind not in expected:
                    continue
                port = int(cmd[cmd.index("--port") + 1])
                assert port == expected[kind], f"{path.name}: the {kind} server listens on {port}"
                for target in _health_targets(c):
                    assert target.endswith(f":{port}"), f"{path.name}: the {kind} health check targets {target}"
                for p in c.get("ports") or []:
                    if isinstance(p, dict) and "containerPort" in p:
                        assert p["containerPort"] == port, f"{path.name}: {kind} containerPort {p['containerPort']}"
                checked.add((path.name, kind))
            if isinstance(doc, dict) and doc.get("kind") == "Service" and doc["metadata"]["name"] in expected:
                name = doc["metadata"]["name"]
                assert [p["port"] for p in doc["spec"]["ports"]] == [expected[name]], f"{path.name}: Service {name}"
    assert {("docker-compose.yml", "fusion"), ("docker-compose.yml", "parser"), ("fusion.yaml", "fusion"),
            ("parser.yaml", "parser")} <= checked, checked
    exposed = re.search(r"^EXPOSE (.+)$", (REPO / "deploy" / "Dockerfile").read_text(), re.M).group(1).split()
    assert {str(PARSER_PORT), str(FUSION_PORT), str(AGENT_PORT)} <= set(exposed)
