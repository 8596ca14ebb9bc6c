"""Shared gRPC server helpers for the GaussLite services: bounded message sizes, health +
reflection, optional bearer token, optional TLS, graceful shutdown. See :mod:`services.common.server`."""

from .server import (
    BearerTokenInterceptor,
    ServerOptions,
    build_server,
    run_until_signalled,
    server_credentials,
)

__all__ = ["BearerTokenInterceptor", "ServerOptions", "build_server", "run_until_signalled", "server_credentials"]
