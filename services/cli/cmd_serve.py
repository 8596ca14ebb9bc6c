"""``gausslite serve SERVICE``: run one GaussLite gRPC service until SIGTERM/SIGINT (``docs/fusion-and-deploy.md``).

Adding a service is one entry in :data:`SERVICES`: the module must define
``run(options: gausslite_services.common.ServerOptions, config_path: str | None) -> int``. The module is
imported lazily inside the handler, so the core ``gausslite`` package never imports gRPC.

Every option falls back to an environment variable: ``GAUSSLITE_<SERVICE>_HOST``,
``GAUSSLITE_<SERVICE>_PORT``, ``GAUSSLITE_<SERVICE>_CONFIG``, ``GAUSSLITE_TOKEN``,
``GAUSSLITE_TLS_CERT``, ``GAUSSLITE_TLS_KEY``, ``GAUSSLITE_TLS_CLIENT_CA`` (mutual TLS),
``GAUSSLITE_AGENT_TOKENS_FILE`` (per-agent token hashes), ``GAUSSLITE_FLEET_TOKEN_WRITES``,
``GAUSSLITE_<SERVICE>_METRICS_PORT`` / ``GAUSSLITE_METRICS_PORT`` (Prometheus ``/metrics`` port; 0 or
unset = off). Credentials and who may write what: ``docs/security.md``.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from typing import Dict, NamedTuple


class ServiceEntry(NamedTuple):
    """``module`` defines ``run(options, config_path)``; ``default_port`` when none is given."""

    module: str
    default_port: int


#: Service name → entry. Add ``"agent"`` / ``"fusion"`` here.
SERVICES: Dict[str, ServiceEntry] = {
    "parser": ServiceEntry("gausslite_services.parser.server", 50051),
    "fusion": ServiceEntry("gausslite_services.fusion_server.server", 50053),
    "agent": ServiceEntry("gausslite_services.agent.server", 50061),
}


def register(subparsers) -> None:
    """Add the ``serve`` subcommand to ``subparsers``."""
    p = subparsers.add_parser("serve", help="run a GaussLite gRPC service",
                              description="Run a GaussLite gRPC service until SIGTERM/SIGINT.")
    p.add_argument("service", choices=sorted(SERVICES), help="which service")
    p.add_argument("--host", default=None, help="bind address (env GAUSSLITE_<SERVICE>_HOST, default 127.0.0.1)")
    p.add_argument("--port", type=int, default=None,
                   help="port, 0 = ephemeral (env GAUSSLITE_<SERVICE>_PORT, default per service)")
    p.add_argument("--token", default=None, help="require 'authorization: Bearer TOKEN' (env GAUSSLITE_TOKEN)")
    p.add_argument("--tls-cert", default=None, help="PEM certificate (env GAUSSLITE_TLS_CERT)")
    p.add_argument("--tls-key", default=None, help="PEM private key (env GAUSSLITE_TLS_KEY)")
    p.add_argument("--tls-client-ca", default=None,
                   help="PEM CA of client certificates: mutual TLS, certificate CN = agent id (env GAUSSLITE_TLS_CLIENT_CA)")
    p.add_argument("--agent-tokens", default=None,
                   help="fusion only: JSON/YAML file of per-agent token hashes (env GAUSSLITE_AGENT_TOKENS_FILE; "
                        "`gausslite tokens`)")
    p.add_argument("--fleet-token-writes", action="store_true", default=None,
                   help="the fleet token keeps write access to every agent next to per-agent credentials "
                        "(migration; env GAUSSLITE_FLEET_TOKEN_WRITES=1)")
    p.add_argument("--config", default=None, help="service config file (env GAUSSLITE_<SERVICE>_CONFIG)")
    p.add_argument("--max-workers", type=int, default=8, help="handler threads")
    p.add_argument("--grace", type=float, default=5.0, help="shutdown grace period, seconds")
    p.add_argument("--metrics-port", type=int, default=None,
                   help="Prometheus /metrics HTTP port, 0 = off (env GAUSSLITE_<SERVICE>_METRICS_PORT, "
                        "GAUSSLITE_METRICS_PORT; default off)")
    p.set_defaults(func=_handle)


def resolve_options(args: argparse.Namespace, env=None):
    """Merge CLI arguments with environment fallbacks into (ServerOptions, config_path).

    Raises:
        ValueError: a port from the environment is not an integer; ``--agent-tokens`` for another
            service than fusion (the only one that checks who writes what).
    """
    # lazy: the command line starts without loading the services or gRPC
    from gausslite_services.common.metrics import metrics_port_from
    from gausslite_services.common.server import ServerOptions

    env = os.environ if env is None else env
    entry = SERVICES[args.service]
    prefix = f"GAUSSLITE_{args.service.upper()}_"
    agent_tokens = getattr(args, "agent_tokens", None)
    if agent_tokens and args.service != "fusion":
        raise ValueError("--agent-tokens applies to the fusion server only (the service that checks which agent "
                         "writes what); the parser and agent services take the fleet token or client certificates")
    if args.service == "fusion":
        agent_tokens = agent_tokens or env.get("GAUSSLITE_AGENT_TOKENS_FILE") or None
    port = args.port if args.port is not None else int(env.get(prefix + "PORT", entry.default_port))
    opts = ServerOptions(
        host=args.host or env.get(prefix + "HOST", "127.0.0.1"),
        port=port,
        token=args.token or env.get("GAUSSLITE_TOKEN") or None,
        tls_cert=args.tls_cert or env.get("GAUSSLITE_TLS_CERT") or None,
        tls_key=args.tls_key or env.get("GAUSSLITE_TLS_KEY") or None,
        tls_client_ca=getattr(args, "tls_client_ca", None) or env.get("GAUSSLITE_TLS_CLIENT_CA") or None,
        agent_tokens_file=agent_tokens or None,
        fleet_token_writes=(True if getattr(args, "fleet_token_writes", None)
                            or env.get("GAUSSLITE_FLEET_TOKEN_WRITES", "").lower() in ("1", "true", "yes") else None),
        max_workers=args.max_workers,
        grace_s=args.grace,
        metrics_port=metrics_port_from(getattr(args, "metrics_port", None),
                                       env.get(prefix + "METRICS_PORT") or env.get("GAUSSLITE_METRICS_PORT")),
    )
    return opts, args.config or env.get(prefix + "CONFIG") or None


def _handle(args: argparse.Namespace) -> int:
    try:
        opts, config_path = resolve_options(args)
        module = importlib.import_module(SERVICES[args.service].module)
        return int(module.run(opts, config_path) or 0)
    except (ValueError, OSError, RuntimeError) as e:
        print(f"gausslite serve {args.service}: error: {e}", file=sys.stderr)
        return 2
