"""Command-line options that the GaussLite servers and clients share: every entry point spells them the same way and
falls back to the same environment variables.

* Servers (``gausslite serve parser|fusion|agent``, ``python -m gausslite_services.fusion_server``):
  :func:`add_server_arguments` adds the options every server takes, :func:`server_options_from_args` turns them,
  with their environment fallbacks, into a :class:`gausslite_services.common.server.ServerOptions`.
* Clients (``gausslite health``, ``gausslite view --fusion``): :func:`add_client_credential_arguments` adds
  ``--tls-ca``, ``--tls-client-cert``, ``--tls-client-key`` (and ``--token``, ``--token-file``),
  :func:`client_tls_paths` and :func:`client_credentials_from_args` resolve them against the environment
  (``GAUSSLITE_TLS_CA``, ``GAUSSLITE_TLS_CLIENT_CERT``, ``GAUSSLITE_TLS_CLIENT_KEY``, ``GAUSSLITE_FUSION_TOKEN``,
  ``GAUSSLITE_FUSION_TOKEN_FILE``, ``GAUSSLITE_TOKEN``) the way the agents and
  :func:`gausslite_services.fusion_server.client.client_credentials_from_env` do.

Every option defaults to None in the parser, so a given flag always wins over its environment variable; the variables
are read through :class:`gausslite.core.environment.EnvironmentSettings`. This module imports neither gRPC nor a
server: the command line registers the options without loading them.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Mapping, Optional, Tuple

from gausslite.core.environment import LOG_LEVELS, EnvironmentSettings


def add_server_arguments(parser, service: Optional[str] = None, *, default_port: Optional[int] = None,
                         max_workers: int = 8, grace_s: float = 5.0) -> None:
    """Add the options every GaussLite server takes to ``parser`` (an ``ArgumentParser`` or an argument group).

    Args:
        parser: where the options go.
        service (str | None): the one service the parser starts (``"fusion"``): the help names its environment
            variables and defaults; None for a parser of several services (``gausslite serve SERVICE``).
        default_port (int | None), max_workers (int), grace_s (float): the defaults the help states (applied by
            :func:`server_options_from_args`).
    """
    env = f"GAUSSLITE_{service.upper()}_" if service else "GAUSSLITE_<SERVICE>_"
    per = (lambda value: f"default {value}") if service else (lambda value: "default per service")
    parser.add_argument("--host", default=None, help=f"bind address (env {env}HOST, default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=None,
                        help=f"port, 0 = ephemeral (env {env}PORT, {per(default_port)})")
    parser.add_argument("--token", default=None,
                        help="fleet bearer token: require 'authorization: Bearer TOKEN' (env GAUSSLITE_TOKEN)")
    parser.add_argument("--tls-cert", default=None, help="PEM certificate → TLS (env GAUSSLITE_TLS_CERT)")
    parser.add_argument("--tls-key", default=None, help="its PEM private key (env GAUSSLITE_TLS_KEY)")
    parser.add_argument("--tls-client-ca", default=None,
                        help="PEM CA of client certificates: mutual TLS, the certificate's CN is the agent id "
                             "(env GAUSSLITE_TLS_CLIENT_CA)")
    parser.add_argument("--config", default=None, help=f"service config file (env {env}CONFIG)")
    data = ("the fusion server's store (the SQLite database fusion.sqlite3 with every subset, keyframe and fused map "
            "it acknowledged; default ./gausslite_fusion_data; not used with --store)")
    parser.add_argument("--data-dir", default=None,
                        help=f"persistent data folder: {data}" + ("" if service else "; an agent's results "
                                                                   "(map.ply + summary.json)")
                             + " (env GAUSSLITE_DATA_DIR)")
    parser.add_argument("--max-workers", type=int, default=None,
                        help=f"handler threads (default {max_workers})" if service
                        else "handler threads (default 16 for fusion, 8 for the parser and the agents)")
    parser.add_argument("--max-message-bytes", type=int, default=None,
                        help="gRPC message bound in bytes (default 4 MiB; the fusion server needs at least 128 KiB: a "
                             "wire chunk may take it minus 16 bytes, SessionInfo.max_chunk_bytes)")
    parser.add_argument("--grace", type=float, default=None,
                        help=f"shutdown grace period in seconds ({per(grace_s)})")
    parser.add_argument("--metrics-port", type=int, default=None,
                        help=f"Prometheus /metrics HTTP port, 0 = off (env {env}METRICS_PORT, GAUSSLITE_METRICS_PORT; "
                             "default off)")
    parser.add_argument("--log-level", default=None, type=str.upper, choices=LOG_LEVELS, metavar="LEVEL",
                        help=f"{', '.join(LOG_LEVELS)} (env GAUSSLITE_LOG_LEVEL, default INFO)")


def server_options_from_args(args: argparse.Namespace, service: str, env: Optional[Mapping[str, str]] = None, *,
                             default_port: int, max_workers: int = 8, grace_s: float = 5.0):
    """The :class:`~gausslite_services.common.server.ServerOptions` of the options of :func:`add_server_arguments`
    (and the credential options of the fusion server, ``--agent-tokens`` / ``--fleet-token-writes``, when ``args``
    has them), each falling back to its environment variable, then to its default.

    Args:
        args (argparse.Namespace): parsed options; a missing attribute counts as not given.
        service (str): ``"parser"``, ``"fusion"`` or ``"agent"`` (the environment variables' prefix).
        env (Mapping | None): environment (default ``os.environ``).
        default_port (int), max_workers (int), grace_s (float): the service's defaults.
    Returns:
        (ServerOptions, config_path): ``config_path`` is ``--config`` or ``GAUSSLITE_<SERVICE>_CONFIG`` (None when
        neither is set).
    Raises:
        ValueError: a ``GAUSSLITE_*`` variable that does not parse (a port that is not an integer; naming it), a bad
            metrics port, or ``--agent-tokens`` for another service than fusion (the only one that checks which agent
            writes what).
    """
    # lazy: the command line registers the options without loading gRPC
    from gausslite_services.common.metrics import metrics_port_from
    from gausslite_services.common.server import ServerOptions

    variables = EnvironmentSettings.read(env)
    given = lambda name: getattr(args, name, None)  # noqa: E731
    host, env_port, config, env_metrics_port = variables.service(service)
    agent_tokens = given("agent_tokens")
    if agent_tokens and service != "fusion":
        raise ValueError("--agent-tokens applies to the fusion server only (the service that checks which agent "
                         "writes what); the parser and agent services take the fleet token or client certificates")
    if service == "fusion":
        agent_tokens = agent_tokens or variables.agent_tokens_file
    port = given("port")
    if port is None:
        port = env_port if env_port is not None else int(default_port)
    fleet_writes = given("fleet_token_writes") or variables.fleet_token_writes
    opts = ServerOptions(
        host=given("host") or host or "127.0.0.1",
        port=port,
        token=given("token") or variables.token,
        tls_cert=given("tls_cert") or variables.tls_cert,
        tls_key=given("tls_key") or variables.tls_key,
        tls_client_ca=given("tls_client_ca") or variables.tls_client_ca,
        agent_tokens_file=agent_tokens or None,
        fleet_token_writes=True if fleet_writes else None,
        max_workers=given("max_workers") if given("max_workers") is not None else max_workers,
        grace_s=given("grace") if given("grace") is not None else grace_s,
        metrics_port=metrics_port_from(given("metrics_port"), env_metrics_port),
    )
    if given("max_message_bytes") is not None:
        opts.max_message_bytes = given("max_message_bytes")
    return opts, given("config") or config


def log_level_from(args: argparse.Namespace, env: Optional[Mapping[str, str]] = None) -> Optional[str]:
    """``--log-level``, else ``GAUSSLITE_LOG_LEVEL``, upper-cased; None when neither is set.

    Raises:
        ValueError: not one of :data:`LOG_LEVELS`, or another ``GAUSSLITE_*`` variable that does not parse.
    """
    level = getattr(args, "log_level", None) or EnvironmentSettings.read(env).log_level
    if level is None:
        return None
    if level.upper() not in LOG_LEVELS:
        raise ValueError(f"log level must be one of {', '.join(LOG_LEVELS)}, got {level!r}")
    return level.upper()


def add_client_credential_arguments(parser, *, token: bool = True, server: str = "the server") -> None:
    """Add a client's TLS options (``--tls-ca``, ``--tls-client-cert``, ``--tls-client-key``) and, with ``token``,
    its fusion-server token options (``--token``, ``--token-file``) to ``parser``.

    Args:
        parser: an ``ArgumentParser`` or an argument group.
        token (bool): add the token options too (a health check needs none).
        server (str): what the client connects to, for the help.
    """
    parser.add_argument("--tls-ca", default=None, metavar="PEM",
                        help=f"CA certificate(s) {server}'s certificate chains to → TLS (env GAUSSLITE_TLS_CA)")
    parser.add_argument("--tls-client-cert", default=None, metavar="PEM",
                        help="this client's certificate, for a server that requires mutual TLS "
                             "(env GAUSSLITE_TLS_CLIENT_CERT)")
    parser.add_argument("--tls-client-key", default=None, metavar="PEM",
                        help="its private key (env GAUSSLITE_TLS_CLIENT_KEY)")
    if token:
        parser.add_argument("--token", default=None,
                            help="bearer token: a per-agent token or the fleet token (env GAUSSLITE_FUSION_TOKEN, "
                                 "else GAUSSLITE_TOKEN)")
        parser.add_argument("--token-file", default=None, metavar="FILE",
                            help="read the bearer token from this file, e.g. a mounted secret "
                                 "(env GAUSSLITE_FUSION_TOKEN_FILE)")


def client_tls_paths(args: argparse.Namespace, env: Optional[Mapping[str, str]] = None
                     ) -> Tuple[Optional[str], Optional[str], Optional[str]]:
    """(CA, client certificate, client key) PEM paths: each option of :func:`add_client_credential_arguments`, else
    its environment variable, else None.

    Raises:
        ValueError: only one of the client certificate and its key; a ``GAUSSLITE_*`` variable that does not parse.
    """
    variables = EnvironmentSettings.read(env)
    ca = getattr(args, "tls_ca", None) or variables.tls_ca
    cert = getattr(args, "tls_client_cert", None) or variables.tls_client_cert
    key = getattr(args, "tls_client_key", None) or variables.tls_client_key
    if bool(cert) != bool(key):
        raise ValueError("mutual TLS needs both the client certificate and its key (--tls-client-cert and "
                         "--tls-client-key, or GAUSSLITE_TLS_CLIENT_CERT and GAUSSLITE_TLS_CLIENT_KEY)")
    return ca, cert, key


def client_credentials_from_args(args: argparse.Namespace, env: Optional[Mapping[str, str]] = None) -> dict:
    """A fusion-server client's credentials from the options of :func:`add_client_credential_arguments` and the
    environment, as keyword arguments of :class:`gausslite_services.fusion_server.client.FusionClient`.

    Token: ``--token``, else the file ``--token-file``, else ``GAUSSLITE_FUSION_TOKEN``, else the file
    ``GAUSSLITE_FUSION_TOKEN_FILE``, else ``GAUSSLITE_TOKEN``, else None. TLS material: :func:`client_tls_paths`,
    read from the files.

    Returns:
        dict with keys ``token``, ``root_cert``, ``client_cert``, ``client_key`` (PEM bytes; None when unset).
    Raises:
        ValueError: both ``--token`` and ``--token-file``; only one of the client certificate and key; an empty or
            invalid token file. OSError: an unreadable file.
    """
    # lazy: the command line registers the options without loading the services
    from gausslite_services.common.auth import read_secret

    variables = EnvironmentSettings.read(env)
    if getattr(args, "token", None) and getattr(args, "token_file", None):
        raise ValueError("give --token or --token-file, not both")
    token_file = getattr(args, "token_file", None)
    token = getattr(args, "token", None) or (read_secret(token_file) if token_file else None)
    token = token or variables.fusion_token
    if token is None and variables.fusion_token_file:
        token = read_secret(variables.fusion_token_file)
    token = token or variables.token
    read = lambda p: Path(p).read_bytes() if p else None  # noqa: E731
    ca, cert, key = client_tls_paths(args, env)
    return {"token": token, "root_cert": read(ca), "client_cert": read(cert), "client_key": read(key)}


def configure_log_level(level: Optional[str]) -> None:
    """Set the root logger's level to ``level`` (one of :data:`LOG_LEVELS`; None leaves it as it is)."""
    if level is not None:
        logging.getLogger().setLevel(level)


__all__ = ["LOG_LEVELS", "add_server_arguments", "server_options_from_args", "log_level_from", "configure_log_level",
           "add_client_credential_arguments", "client_tls_paths", "client_credentials_from_args"]
