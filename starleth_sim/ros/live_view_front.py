"""The live view's front door: a TCP front of foxglove-sdk's WebSocket server that also lets
in the clients that offer only the older subprotocol name.

foxglove-sdk's server accepts the subprotocol ``foxglove.sdk.v1`` only; Lichtblick releases
before its support of that name (lichtblick PR 819, December 2025) and other older clients
offer only ``foxglove.websocket.v1`` and get HTTP 400. The two names carry the same
protocol (Foxglove's own statement, quoted in that PR). So the front accepts each
connection on the live view's port, and for a client offering only the older name it
rewrites the one handshake header on the way in (``Sec-WebSocket-Protocol``: the SDK's
name) and on the way back (the name the client asked for); the WebSocket accept key does
not depend on that header. After the handshake it passes the bytes through both ways. A
client offering ``foxglove.sdk.v1`` passes through untouched. ROS-free; standard library.
"""
from __future__ import annotations

import socket
import threading

#: the subprotocol of foxglove-sdk's server, and the older name of the same protocol
SUBPROTOCOL = "foxglove.sdk.v1"
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
HEADER_LIMIT = 16 * 1024        # bytes of an HTTP handshake header, at most
PIECE = 64 * 1024               # bytes passed on per read


def read_header(sock) -> tuple:
    """(the HTTP header up to and including its blank line, the bytes read after it) from
    `sock`; ValueError past HEADER_LIMIT bytes or when the peer closes first."""
    data = b""
    while b"\r\n\r\n" not in data:
        if len(data) > HEADER_LIMIT:
            raise ValueError(f"handshake header over {HEADER_LIMIT} bytes")
        piece = sock.recv(4096)
        if not piece:
            raise ValueError("connection closed during the handshake")
        data += piece
    end = data.index(b"\r\n\r\n") + 4
    return data[:end], data[end:]


def offered_protocols(header: bytes) -> list:
    """The subprotocols a handshake header names (Sec-WebSocket-Protocol, any case)."""
    out = []
    for line in header.split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"sec-websocket-protocol":
            out += [p.strip().decode("latin-1") for p in value.split(b",") if p.strip()]
    return out


def with_protocol(header: bytes, protocol: str) -> bytes:
    """`header` with its Sec-WebSocket-Protocol value replaced by `protocol`."""
    lines = header.split(b"\r\n")
    for i, line in enumerate(lines):
        if line.partition(b":")[0].strip().lower() == b"sec-websocket-protocol":
            lines[i] = b"Sec-WebSocket-Protocol: " + protocol.encode("latin-1")
    return b"\r\n".join(lines)


class SubprotocolFront:
    """Listens on host:port (OSError if it cannot bind) and hands every connection to the
    SDK's server at 127.0.0.1:backend_port, translating the older subprotocol name (module
    docstring). Its threads are daemons; :meth:`stop` closes every socket."""

    def __init__(self, host: str, port: int, backend_port: int):
        self.backend = ("127.0.0.1", backend_port)
        self.listener = socket.create_server((host, port))
        self.port = self.listener.getsockname()[1]
        self.legacy_clients = 0          # connections translated from the older name
        self._sockets = set()
        self._lock = threading.Lock()
        self._stopped = False
        threading.Thread(target=self._accept, name="live_view_front", daemon=True).start()

    def _track(self, *socks):
        with self._lock:
            if self._stopped:
                raise OSError("stopped")
            self._sockets.update(socks)

    def _accept(self):
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:           # the listener was closed: stop
                return
            threading.Thread(target=self._connect, args=(client,), daemon=True).start()

    def _connect(self, client):
        """One client: the handshake (translated when it offers only the older name), then
        a pump each way."""
        backend = None
        try:
            self._track(client)
            request, rest = read_header(client)
            offered = offered_protocols(request)
            legacy = LEGACY_SUBPROTOCOL in offered and SUBPROTOCOL not in offered
            backend = socket.create_connection(self.backend)
            self._track(backend)
            backend.sendall((with_protocol(request, SUBPROTOCOL) if legacy else request)
                            + rest)
            if legacy:
                self.legacy_clients += 1
                response, after = read_header(backend)
                client.sendall(with_protocol(response, LEGACY_SUBPROTOCOL) + after)
        except (OSError, ValueError):
            self._close(client, backend)
            return
        threading.Thread(target=self._pump, args=(backend, client), daemon=True).start()
        self._pump(client, backend)

    def _pump(self, src, dst):
        """Bytes from src to dst until either side closes; then both are closed."""
        try:
            while True:
                data = src.recv(PIECE)
                if not data:
                    break
                dst.sendall(data)
        except OSError:
            pass
        self._close(src, dst)

    def _close(self, *socks):
        for s in socks:
            if s is None:
                continue
            with self._lock:
                self._sockets.discard(s)
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()

    def stop(self):
        """Close the listener and every connection (idempotent)."""
        with self._lock:
            self._stopped = True
            socks = list(self._sockets)
        self.listener.close()
        self._close(*socks)
