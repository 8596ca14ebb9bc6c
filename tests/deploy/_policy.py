"""What every deployment manifest in deploy/ must hold (docs/security.md): the fusion server never listens without TLS
and always checks per-robot identity (client certificates and per-agent tokens); the parser and the agents serve
TLS too; no container runs as root. Each function returns the problems it finds (empty: the manifest is fine)."""

from __future__ import annotations

from typing import Dict, List, Optional

#: (option, environment variable) pairs a GaussLite server reads its credentials from
TLS_CERT = ("--tls-cert", "GAUSSLITE_TLS_CERT")
TLS_KEY = ("--tls-key", "GAUSSLITE_TLS_KEY")
CLIENT_CA = ("--tls-client-ca", "GAUSSLITE_TLS_CLIENT_CA")
AGENT_TOKENS = ("--agent-tokens", "GAUSSLITE_AGENT_TOKENS_FILE")


def server_kind(command: List[str]) -> Optional[str]:
    """``"fusion"``, ``"parser"`` or ``"agent"`` for a command that runs a GaussLite server, else None."""
    cmd = [str(c) for c in command or []]
    if "gausslite_services.fusion_server" in cmd:
        return "fusion"
    if "serve" in cmd:
        i = cmd.index("serve")
        return cmd[i + 1] if i + 1 < len(cmd) else None
    return None


def _setting(command: List[str], env: Dict[str, str], pair) -> str:
    flag, var = pair
    cmd = [str(c) for c in command]
    if flag in cmd and cmd.index(flag) + 1 < len(cmd):
        return cmd[cmd.index(flag) + 1]
    return str(env.get(var) or "")


def server_problems(name: str, command: List[str], env: Dict[str, str], mounted) -> List[str]:
    """Problems of one server container: ``mounted(path) -> bool`` tells whether a file path is provided (a secret)."""
    kind = server_kind(command)
    if kind is None:
        return []
    out = []
    needs = [TLS_CERT, TLS_KEY] + ([CLIENT_CA, AGENT_TOKENS] if kind == "fusion" else [])
    for pair in needs:
        value = _setting(command, env, pair)
        if not value or value.startswith("${"):
            out.append(f"{name}: the {kind} server runs without {pair[1]} / {pair[0]}"
                       + (" (TLS)" if pair in (TLS_CERT, TLS_KEY) else " (per-robot identity)"))
        elif not mounted(value):
            out.append(f"{name}: {pair[1]}={value} is not provided by a mounted secret")
    return out


def compose_problems(compose: dict, dockerfile: str) -> List[str]:
    """Problems of ``deploy/docker-compose.yml`` (parsed) with its image's ``deploy/Dockerfile`` (text)."""
    out = []
    users = [ln.split(None, 1)[1].strip() for ln in dockerfile.splitlines() if ln.strip().upper().startswith("USER ")]
    if not users or users[-1].split(":")[0] in ("root", "0"):
        out.append("Dockerfile: the image runs as root (no final non-root USER)")
    for name, svc in (compose.get("services") or {}).items():
        env = svc.get("environment") or {}
        if isinstance(env, list):
            env = dict(e.split("=", 1) for e in env)
        secrets = {s if isinstance(s, str) else s.get("target", s["source"]) for s in svc.get("secrets", [])}
        mounted = lambda p: p.startswith("/run/secrets/") and p[len("/run/secrets/"):] in secrets  # noqa: E731
        out += server_problems(name, svc.get("command") or [], env, mounted)
        if str(svc.get("user", "")).split(":")[0] in ("root", "0"):
            out.append(f"{name}: runs as root")
    return out


def k8s_problems(docs: List[dict]) -> List[str]:
    """Problems of the parsed documents of ``deploy/k8s/*.yaml``."""
    out = []
    for d in docs:
        if d.get("kind") not in ("Deployment", "StatefulSet", "DaemonSet", "Job"):
            continue
        pod = d["spec"]["template"]["spec"]
        name = f"{d['kind']}/{d['metadata']['name']}"
        sc = pod.get("securityContext") or {}
        secret_volumes = {v["name"] for v in pod.get("volumes", []) if "secret" in v}
        for c in pod.get("initContainers", []) + pod.get("containers", []):
            csc = {**sc, **(c.get("securityContext") or {})}
            if not csc.get("runAsNonRoot") or csc.get("runAsUser", 1) == 0:
                out.append(f"{name}/{c['name']}: may run as root (runAsNonRoot not set)")
            env = {e["name"]: e.get("value", "") for e in c.get("env", [])}
            mounts = [m["mountPath"].rstrip("/") + "/" for m in c.get("volumeMounts", []) if m["name"] in secret_volumes]
            mounted = lambda p: any(p.startswith(m) for m in mounts)  # noqa: E731
            problems = server_problems(f"{name}/{c['name']}", c.get("command") or [], env, mounted)
            out += problems
            if server_kind(c.get("command") or []) and not problems:
                for probe in ("readinessProbe", "livenessProbe"):
                    if "grpc" in (c.get(probe) or {}):
                        out.append(f"{name}/{c['name']}: {probe} uses the kubelet's gRPC probe, which cannot speak TLS")
    return out
