"""Shared gRPC server helpers for the GaussLite services: bounded message sizes, health +
reflection, caller authentication (fleet token, per-agent tokens, client certificates;
:mod:`gausslite_services.common.auth`), optional TLS / mutual TLS with certificate reload, graceful shutdown.
See :mod:`gausslite_services.common.server`."""

from .server import (
    AuthInterceptor,
    BearerTokenInterceptor,
    ServerOptions,
    TlsFiles,
    authenticator_from_options,
    build_server,
    run_until_signalled,
    server_credentials,
)

__all__ = ["AuthInterceptor", "BearerTokenInterceptor", "ServerOptions", "TlsFiles", "authenticator_from_options",
           "build_server", "run_until_signalled", "server_credentials"]
