"""Shared gRPC server helpers for the GaussLite services: bounded message sizes, health +
reflection, caller authentication (fleet token, per-agent tokens, client certificates;
:mod:`gausslite_services.common.auth`), optional TLS / mutual TLS with certificate reload, graceful shutdown.
See :mod:`gausslite_services.common.server`. The command-line options the servers and clients share:
:mod:`gausslite_services.common.cli_options`.

The names below are loaded on first use, so a submodule without gRPC (``cli_options``) imports without it."""

from __future__ import annotations

import importlib

__all__ = ["AuthInterceptor", "BearerTokenInterceptor", "ServerOptions", "TlsFiles", "authenticator_from_options",
           "build_server", "run_until_signalled", "server_credentials"]


def __getattr__(name: str):
    """The names of :data:`__all__`, from :mod:`gausslite_services.common.server` (imported on first use).

    Raises:
        AttributeError: ``name`` is none of them.
    """
    if name in __all__:
        return getattr(importlib.import_module(".server", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
