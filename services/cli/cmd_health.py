"""``gausslite health --target HOST:PORT [--service NAME]``: query the standard gRPC health service
(``grpc.health.v1.Health/Check``) of a GaussLite server; exit 0 when SERVING, 1 otherwise (also on
connection errors or when the deadline passes). Used by the docker-compose healthchecks.

Environment fallbacks: ``GAUSSLITE_HEALTH_TARGET``, ``GAUSSLITE_TLS_CA`` (PEM CA → TLS),
``GAUSSLITE_TLS_CLIENT_CERT`` / ``GAUSSLITE_TLS_CLIENT_KEY`` (client certificate for a server that
requires mutual TLS). The TLS options are those of every client command
(:func:`gausslite_services.common.cli_options.add_client_credential_arguments`).
"""

from __future__ import annotations

import argparse
import sys

from gausslite.core.environment import EnvironmentSettings
# grpc-free: the command line registers the options without loading the services
from gausslite_services.common.cli_options import add_client_credential_arguments, client_tls_paths


def register(subparsers) -> None:
    """Add the ``health`` subcommand to ``subparsers``."""
    p = subparsers.add_parser("health", help="check a gRPC service's health (exit 0 = SERVING)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--target", default=None, help="host:port (env GAUSSLITE_HEALTH_TARGET)")
    p.add_argument("--service", default="", help="service name, e.g. gausslite.v1.Agent ('' = whole server)")
    p.add_argument("--timeout", type=float, default=3.0, help="deadline in seconds (default 3)")
    add_client_credential_arguments(p, token=False, server="the service")
    p.set_defaults(func=_handle)


def check_health(target: str, service: str = "", timeout_s: float = 3.0, tls_ca: str | None = None,
                 client_cert: str | None = None, client_key: str | None = None) -> str:
    """Health status name of ``service`` at ``target`` (``SERVING``, ``NOT_SERVING``, ``SERVICE_UNKNOWN``...),
    or ``UNREACHABLE: <code>`` when the call fails.

    Args:
        tls_ca (str | None): PEM CA file → TLS. client_cert, client_key (str | None): PEM files of a
            client certificate (mutual TLS).
    Raises:
        OSError: a PEM file is unreadable. ValueError: only one of client certificate and key.
    """
    # lazy: the command line starts without loading the services or gRPC
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    if bool(client_cert) != bool(client_key):
        raise ValueError("a client certificate needs its key (--tls-client-cert and --tls-client-key)")
    if tls_ca or client_cert:
        read = lambda p: open(p, "rb").read() if p else None  # noqa: E731
        creds = grpc.ssl_channel_credentials(read(tls_ca), read(client_key), read(client_cert))
        ch = grpc.secure_channel(target, creds)
    else:
        ch = grpc.insecure_channel(target)
    with ch:
        try:
            r = health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(service=service),
                                                     timeout=timeout_s, wait_for_ready=True)
        except grpc.RpcError as e:
            return f"UNREACHABLE: {e.code().name}"
        return health_pb2.HealthCheckResponse.ServingStatus.Name(r.status)


def _handle(args: argparse.Namespace) -> int:
    try:
        target = args.target or EnvironmentSettings.read().health_target
    except ValueError as e:
        print(f"gausslite health: error: {e}", file=sys.stderr)
        return 2
    if not target:
        print("gausslite health: error: --target HOST:PORT is required", file=sys.stderr)
        return 2
    try:
        status = check_health(target, args.service, args.timeout, *client_tls_paths(args))
    except (ValueError, OSError) as e:
        print(f"gausslite health: error: {e}", file=sys.stderr)
        return 2
    print(f"{target} {args.service or '(server)'}: {status}")
    return 0 if status == "SERVING" else 1
