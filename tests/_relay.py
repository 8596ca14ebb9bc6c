"""A TCP relay that can cut a link: the database (or any server) behind it "goes down" for its clients
without stopping the real server, which other users may share (not a test module). Used by the database-outage
tests and by ``bench.fleet --db-outage``."""

from __future__ import annotations

import socket
import threading
from typing import List, Optional, Tuple


class TcpRelay:
    """Forwards connections to ``127.0.0.1:port`` to ``target`` (host, port).

    :meth:`cut` closes the listening socket and every relayed connection: clients see their connections
    reset and new ones refused, as when the server behind is stopped. :meth:`restore` listens on the same
    port again. Threads of this process; loopback only.

    Args:
        target: (host, port) of the real server.
        port: local port (0 = an ephemeral one, see :attr:`port`).
    Raises:
        OSError: the port cannot be bound.
    """

    def __init__(self, target: Tuple[str, int], port: int = 0):
        self.target = (str(target[0]), int(target[1]))
        self._lock = threading.Lock()
        self._conns: List[socket.socket] = []
        self._listener: Optional[socket.socket] = None
        self.port = int(port)
        self.up = False
        self.restore()

    def restore(self) -> None:
        """Listen again (on the same port). Raises OSError when the port cannot be bound."""
        with self._lock:
            if self.up:
                return
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind(("127.0.0.1", self.port))
            s.listen(128)
            self.port = s.getsockname()[1]
            self._listener = s
            self.up = True
        threading.Thread(target=self._accept, args=(s,), name="tcp-relay-accept", daemon=True).start()

    def cut(self) -> None:
        """Drop every relayed connection and refuse new ones until :meth:`restore`."""
        with self._lock:
            self.up = False
            listener, self._listener = self._listener, None
            conns, self._conns = self._conns, []
        if listener is not None:
            _close(listener)
        for c in conns:
            _close(c)

    close = cut

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:
                return  # cut
            try:
                upstream = socket.create_connection(self.target, timeout=5)
                upstream.settimeout(None)
            except OSError:
                _close(client)
                continue
            with self._lock:
                if not self.up:
                    _close(client)
                    _close(upstream)
                    return
                self._conns += [client, upstream]
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=_pump, args=(a, b), name="tcp-relay-pump", daemon=True).start()


def _pump(src: socket.socket, dst: socket.socket) -> None:
    try:
        while True:
            data = src.recv(65536)
            if not data:
                break
            dst.sendall(data)
    except OSError:
        pass
    _close(src)
    _close(dst)


def _close(s: socket.socket) -> None:
    try:
        s.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    try:
        s.close()
    except OSError:
        pass
