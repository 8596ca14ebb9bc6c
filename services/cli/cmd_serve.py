"""``gausslite serve SERVICE``: run one GaussLite gRPC service until SIGTERM/SIGINT (``docs/fusion-and-deploy.md``).

Adding a service is one entry in :data:`SERVICES`: the module must define
``run(options: gausslite_services.common.ServerOptions, config_path: str | None) -> int``. The module is
imported lazily inside the handler, so the core ``gausslite`` package never imports gRPC.

Every option falls back to an environment variable: ``GAUSSLITE_<SERVICE>_HOST``,
``GAUSSLITE_<SERVICE>_PORT``, ``GAUSSLITE_<SERVICE>_CONFIG``, ``GAUSSLITE_TOKEN``,
``GAUSSLITE_TLS_CERT``, ``GAUSSLITE_TLS_KEY``, ``GAUSSLITE_TLS_CLIENT_CA`` (mutual TLS),
``GAUSSLITE_AGENT_TOKENS_FILE`` (per-agent token hashes), ``GAUSSLITE_FLEET_TOKEN_WRITES``,
``GAUSSLITE_<SERVICE>_METRICS_PORT`` / ``GAUSSLITE_METRICS_PORT`` (Prometheus ``/metrics`` port; 0 or
unset = off), ``GAUSSLITE_LOG_LEVEL``; fusion only: ``GAUSSLITE_FUSION_STORE`` (``--store``),
``GAUSSLITE_FUSION_PORT_FILE`` (``--port-file``). ``gausslite serve fusion`` and
``python -m gausslite_services.fusion_server`` take the same options
(:mod:`gausslite_services.fusion_server.options`). Credentials and who may write what: ``docs/security.md``.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from typing import Dict, NamedTuple

# grpc-free: the command line registers the options without loading the services
from gausslite_services.common.cli_options import (add_server_arguments, configure_log_level, log_level_from,
                                                   server_options_from_args)
from gausslite_services.fusion_server import options as fusion_options
from gausslite_services.fusion_server.options import add_fusion_arguments


class ServiceEntry(NamedTuple):
    """``module`` defines ``run(options, config_path)``; ``default_port``, ``max_workers`` (handler threads) and
    ``grace_s`` (shutdown grace period, seconds) apply when no option or environment variable gives them."""

    module: str
    default_port: int
    max_workers: int = 8
    grace_s: float = 5.0


#: Service name → entry. One port per service everywhere (deploy/, the docs, the clients): parser 50051,
#: fusion 50052, agents 50061 and up.
SERVICES: Dict[str, ServiceEntry] = {
    "parser": ServiceEntry("gausslite_services.parser.server", 50051),
    "fusion": ServiceEntry("gausslite_services.fusion_server.server", fusion_options.DEFAULT_PORT,
                           fusion_options.DEFAULT_MAX_WORKERS, fusion_options.DEFAULT_GRACE_S),
    "agent": ServiceEntry("gausslite_services.agent.server", 50061),
}


def register(subparsers) -> None:
    """Add the ``serve`` subcommand to ``subparsers``: the options of every server
    (:func:`gausslite_services.common.cli_options.add_server_arguments`) and those of the fusion server
    (:func:`gausslite_services.fusion_server.options.add_fusion_arguments`, shared with
    ``python -m gausslite_services.fusion_server``)."""
    p = subparsers.add_parser("serve", help="run a GaussLite gRPC service",
                              description="Run a GaussLite gRPC service until SIGTERM/SIGINT.")
    p.add_argument("service", choices=sorted(SERVICES), help="which service")
    add_server_arguments(p)
    add_fusion_arguments(p.add_argument_group("fusion server options (gausslite serve fusion)"))
    p.set_defaults(func=_handle)


def resolve_options(args: argparse.Namespace, env=None):
    """Merge CLI arguments with environment fallbacks into (ServerOptions, config_path)
    (:func:`gausslite_services.common.cli_options.server_options_from_args` with the service's defaults).

    Raises:
        ValueError: a port from the environment is not an integer; ``--agent-tokens``, ``--store`` or
            ``--port-file`` for another service than fusion.
    """
    env = os.environ if env is None else env
    entry = SERVICES[args.service]
    if args.service != "fusion":
        given = [flag for dest, flag in fusion_options.FUSION_ONLY.items() if getattr(args, dest, None)]
        if given:
            raise ValueError(f"{', '.join(given)} apply to the fusion server only")
    return server_options_from_args(args, args.service, env, default_port=entry.default_port,
                                    max_workers=entry.max_workers, grace_s=entry.grace_s)


def _handle(args: argparse.Namespace) -> int:
    try:
        configure_log_level(None if getattr(args, "verbose", False) else log_level_from(args))
        opts, config_path = resolve_options(args)
        module = importlib.import_module(SERVICES[args.service].module)
        extra = fusion_options.fusion_run_arguments(args) if args.service == "fusion" else {}
        return int(module.run(opts, config_path, **extra) or 0)
    except (ValueError, OSError, RuntimeError) as e:
        print(f"gausslite serve {args.service}: error: {e}", file=sys.stderr)
        return 2
