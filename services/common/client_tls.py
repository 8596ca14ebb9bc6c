"""Process-wide default TLS material of the service clients
(:class:`gausslite_services.fusion_server.client.FusionClient`, :class:`gausslite_services.agent.client.AgentClient`).

A client given no TLS material of its own uses these defaults; without defaults it speaks plaintext. Nothing sets
them implicitly: a command that drives services of a TLS deployment sets them once from its options
(``gausslite sim --attach`` from ``--tls-ca`` / ``--tls-client-cert`` / ``--tls-client-key``, env
``GAUSSLITE_TLS_CA``, ``GAUSSLITE_TLS_CLIENT_CERT``, ``GAUSSLITE_TLS_CLIENT_KEY``).
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Optional, Tuple

__all__ = ["set_default_client_tls", "default_client_tls", "client_tls_from_files"]

_lock = threading.Lock()
_default: Tuple[Optional[bytes], Optional[bytes], Optional[bytes]] = (None, None, None)


def set_default_client_tls(root_cert: Optional[bytes] = None, client_cert: Optional[bytes] = None,
                           client_key: Optional[bytes] = None) -> None:
    """Set (or, with no arguments, clear) the default TLS material of clients created afterwards.

    Args:
        root_cert (bytes | None): PEM CA bundle the servers' certificates must chain to.
        client_cert (bytes | None), client_key (bytes | None): PEM client certificate and key (mutual TLS).
    Raises:
        ValueError: only one of the client certificate and key.
    """
    global _default
    if (client_cert is None) != (client_key is None):
        raise ValueError("mutual TLS needs both the client certificate and its key")
    with _lock:
        _default = (root_cert, client_cert, client_key)


def default_client_tls() -> Tuple[Optional[bytes], Optional[bytes], Optional[bytes]]:
    """(root_cert, client_cert, client_key) set by :func:`set_default_client_tls`; all None when unset."""
    with _lock:
        return _default


def client_tls_from_files(ca: Optional[str], cert: Optional[str], key: Optional[str]):
    """(root_cert, client_cert, client_key) bytes read from PEM files (None where no path is given).

    Raises:
        OSError: an unreadable file. ValueError: only one of ``cert`` and ``key``.
    """
    if bool(cert) != bool(key):
        raise ValueError("mutual TLS needs both --tls-client-cert and --tls-client-key")
    read = lambda p: Path(p).read_bytes() if p else None  # noqa: E731
    return read(ca), read(cert), read(key)
