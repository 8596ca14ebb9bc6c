"""The fusion server's command line, one builder for both of its entry points: ``gausslite serve fusion`` and
``python -m gausslite_services.fusion_server`` take the same options with the same environment fallbacks and
defaults (:func:`build_parser` for the module, :func:`add_fusion_arguments` beside the options of every server).

Imports neither gRPC nor the server: ``gausslite`` registers these options without loading them.
"""

from __future__ import annotations

import argparse
from typing import Mapping, Optional

from gausslite.core.environment import EnvironmentSettings
from gausslite_services.common.cli_options import add_server_arguments

#: the fusion server's port (``deploy/``, the docs and the clients use it too)
DEFAULT_PORT = 50052
#: handler threads of the fusion server
DEFAULT_MAX_WORKERS = 16
#: its shutdown grace period, seconds
DEFAULT_GRACE_S = 10.0
#: options of :func:`add_fusion_arguments` that no other service takes (argparse dest → flag)
FUSION_ONLY = {"store": "--store", "port_file": "--port-file"}


def add_fusion_arguments(parser) -> None:
    """Add the options only the fusion server takes to ``parser`` (an ``ArgumentParser`` or an argument group):
    ``--agent-tokens``, ``--fleet-token-writes``, ``--store``, ``--port-file``; all default to None (their
    environment variables apply in :func:`gausslite_services.common.cli_options.server_options_from_args` and
    :func:`fusion_run_arguments`)."""
    parser.add_argument("--agent-tokens", default=None, metavar="FILE",
                        help="JSON/YAML file of per-agent token hashes, re-read when it changes or on SIGHUP "
                             "(env GAUSSLITE_AGENT_TOKENS_FILE; `gausslite tokens` makes it)")
    parser.add_argument("--fleet-token-writes", action="store_true", default=None,
                        help="the fleet token keeps write access to every agent next to per-agent credentials "
                             "(migration; env GAUSSLITE_FLEET_TOKEN_WRITES=1)")
    parser.add_argument("--store", default=None, metavar="DSN",
                        help="postgresql://user:pw@host:port/db to share a PostgreSQL store between replicas "
                             "(env GAUSSLITE_FUSION_STORE; default: SQLite in --data-dir)")
    parser.add_argument("--port-file", default=None, metavar="FILE",
                        help="write the bound port to this file once serving (env GAUSSLITE_FUSION_PORT_FILE)")


def build_parser(prog: str = "python -m gausslite_services.fusion_server") -> argparse.ArgumentParser:
    """The parser of ``python -m gausslite_services.fusion_server``: the options of every server
    (:func:`gausslite_services.common.cli_options.add_server_arguments`) and :func:`add_fusion_arguments`."""
    p = argparse.ArgumentParser(prog=prog, description="GaussLite fusion server (gausslite.v1.Fusion); the same "
                                "options as `gausslite serve fusion`.")
    add_server_arguments(p, "fusion", default_port=DEFAULT_PORT, max_workers=DEFAULT_MAX_WORKERS,
                         grace_s=DEFAULT_GRACE_S)
    g = p.add_argument_group("fusion server options")
    add_fusion_arguments(g)
    g.add_argument("--set", dest="config_overrides", action="append", default=None, metavar="KEY=VALUE",
                   help="configuration override, e.g. fusion.team_map.refine_iters=100 (repeatable; env "
                        "GAUSSLITE_FUSION_SET, ';'-separated)")
    return p


def fusion_run_arguments(args: argparse.Namespace, env: Optional[Mapping[str, str]] = None) -> dict:
    """Keyword arguments of :func:`gausslite_services.fusion_server.server.run` beyond the server options:
    ``data_dir``, ``store`` and ``port_file``, each the option, else its environment variable
    (``GAUSSLITE_DATA_DIR``, ``GAUSSLITE_FUSION_STORE``, ``GAUSSLITE_FUSION_PORT_FILE``), else None; and ``overrides``,
    the ``--set KEY=VALUE`` options, else ``GAUSSLITE_FUSION_SET`` (``;``-separated). The variables are read through
    :class:`gausslite.core.environment.EnvironmentSettings` (``env``: default ``os.environ``).

    Raises:
        ValueError: a ``GAUSSLITE_*`` variable that does not parse.
    """
    variables = EnvironmentSettings.read(env)
    given = getattr(args, "config_overrides", None)
    return {"data_dir": getattr(args, "data_dir", None) or variables.data_dir,
            "store": getattr(args, "store", None) or variables.fusion_store,
            "port_file": getattr(args, "port_file", None) or variables.fusion_port_file,
            "overrides": list(given) if given else list(variables.fusion_set)}


__all__ = ["DEFAULT_PORT", "DEFAULT_MAX_WORKERS", "DEFAULT_GRACE_S", "FUSION_ONLY", "add_fusion_arguments",
           "build_parser", "fusion_run_arguments"]
