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
client offering ``foxglove.sdk.v1`` passes through untouched. What a client sends is bounded
here (MAX_CLIENT_MESSAGE), as the SDK does not let its own 16 MiB be lowered. ROS-free;
standard library.
"""
from __future__ import annotations

import logging
import socket
import struct
import threading

#: the subprotocol of foxglove-sdk's server, and the older name of the same protocol
SUBPROTOCOL = "foxglove.sdk.v1"
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
HEADER_LIMIT = 16 * 1024        # bytes of an HTTP handshake header, at most
PIECE = 64 * 1024               # bytes passed on per read
#: bytes of a client's message (all its frames), at most: what a client sends is small
#: (subscribe / unsubscribe with channel ids, a few kB for every topic sim_node has; the live
#: view takes no client publishing), while foxglove-sdk's own limit is 16 MiB and cannot be
#: lowered; a client over it is disconnected, with one (throttled) warning
MAX_CLIENT_MESSAGE = 64 * 1024
#: the logger of the front's warnings: under foxglove-sdk's, so that the live view's
#: ClientProblemLog takes them to the node's log like the SDK's own
log = logging.getLogger("foxglove.live_view_front")


class ClientMessageLimit:
    """Follows the WebSocket frames a client sends (RFC 6455: a 2-byte head, a 16- or 64-bit
    extended length, a 4-byte mask) and says when a message, the payloads of its frames up
    to the final one, grows beyond `limit` bytes, before those bytes are passed on."""

    def __init__(self, limit: int = MAX_CLIENT_MESSAGE):
        self.limit = limit
        self.buffer = b""         # the head of the next frame, read so far
        self.payload_left = 0     # bytes of the current frame's payload still to come
        self.message = 0          # payload bytes of the current message so far

    def feed(self, data: bytes) -> bool:
        """Take the next bytes of the stream; False when the message is over the limit."""
        while data:
            if self.payload_left:
                n = min(self.payload_left, len(data))
                self.payload_left -= n
                data = data[n:]
                continue
            self.buffer += data
            data = b""
            head = self._frame_head()
            if head is None:
                return True           # a head not complete yet
            size, fin, used = head
            self.message = size if self.message == 0 else self.message + size
            if self.message > self.limit:
                return False
            if fin:
                self.message = 0
            data, self.buffer = self.buffer[used:], b""
            self.payload_left = size
        return True

    def _frame_head(self):
        """(payload size, final frame, head length) of the frame head in `buffer`, or None
        while it is incomplete."""
        b = self.buffer
        if len(b) < 2:
            return None
        fin, size, used = b[0] & 0x80, b[1] & 0x7F, 2
        if size == 126:
            if len(b) < 4:
                return None
            size, used = struct.unpack(">H", b[2:4])[0], 4
        elif size == 127:
            if len(b) < 10:
                return None
            size, used = struct.unpack(">Q", b[2:10])[0], 10
        used += 4 if b[1] & 0x80 else 0
        if len(b) < used:
            return None
        return size, bool(fin), used


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
        self.oversized_clients = 0       # connections closed for a message over the limit
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
        self._pump(client, backend, ClientMessageLimit())

    def _pump(self, src, dst, limit=None):
        """Bytes from src to dst until either side closes (or, from a client, a message
        over `limit`: one warning); then both are closed."""
        try:
            while True:
                data = src.recv(PIECE)
                if not data:
                    break
                if limit is not None and not limit.feed(data):
                    self.oversized_clients += 1
                    log.warning(f"a client sent a message over {limit.limit} bytes (the live "
                                "view's clients send a few kB); disconnected it")
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
