"""sim_node's live view: a Foxglove WebSocket server (the ``foxglove-sdk`` package, the optional
extra ``live``: requirements-live.txt) that serves the topics sim_node publishes, /tf and
/tf_static included, to Foxglove or Lichtblick: each topic a channel with its ``ros2msg``
schema (the recording's, :func:`~.recording.message_definition`) and ``cdr`` messages, the
very bytes sim_node publishes and records (no second serialisation), logged at the stamp of
the state (sim time).

A topic is served only while a WebSocket client subscribes to it (:meth:`LiveView.wants`,
which :class:`~.topic_output.TopicOutput` asks before it builds a topic nobody else wants);
a latched topic (robot_description, /tf_static) is sent again to each new subscriber. The
server runs in threads of the SDK; nothing of it runs unless ``live_view`` is true (this
module imports ``foxglove`` only in :meth:`LiveView.open`); a front of it
(:mod:`.live_view_front`) takes the connections, so that clients offering either name of the
protocol's subprotocol connect. What is served and the URLs to open: doc/sim_node.md, "Live
view".

A robot's meshes (the files its URDF's ``<mesh filename>`` name: package:// URIs under its
spec's package roots or ROS's ament index) are served to the client's URDF layer through the
protocol's fetchAsset (the SDK's ``asset_handler``; :class:`MeshAssets`): only those URIs,
each a mesh file of at most robots.meshes.MAX_MESH_BYTES.

The server's problems with a client (a malformed frame, a subscription to an unknown
channel: the SDK logs them through Python ``logging``, under ``foxglove``) go to the node's
logger as warnings (:class:`ClientProblemLog`), throttled like every other warning of the
node, each cut to MAX_LOGGED_CHARS: the SDK's message quotes the client's frame. The front
bounds a client's message (live_view_front.MAX_CLIENT_MESSAGE, 64 KiB), far below the SDK's
own 16 MiB, which it does not let a caller lower.
"""
from __future__ import annotations

import logging
import os
import socket
import threading

from starleth_interface.ros_helpers import ThrottledLog

from ..robots import load_robot, package_dirs, robot_urdf, spec_text
from ..robots.meshes import MAX_MESH_BYTES, MESH_SUFFIXES, MeshError, mesh_filenames, resolve_mesh
from .live_view_front import LEGACY_SUBPROTOCOL, SUBPROTOCOL, SubprotocolFront
from .recording import message_definition, type_name

INSTALL_HINT = "pip install -r requirements-live.txt (or: pip install 'starleth_sim[live]')"


def viewer_urls(host: str, port: int) -> dict:
    """{viewer: the URL that opens the live view of a server at host:port in it}."""
    if host in ("0.0.0.0", "", "::", "127.0.0.1"):
        host = "localhost"
    ws = f"ws://{host}:{port}"
    return {"Foxglove": f"https://app.foxglove.dev/?ds=foxglove-websocket&ds.url={ws}",
            "Lichtblick": f"Open connection > Foxglove WebSocket > {ws}"}


def live_view_lines(host: str, port: int):
    """(the port is free to serve on, the lines to print: the URLs to open, or why there
    is no live view) for a live view about to start on host:port (starleth-demo --live)."""
    try:
        import foxglove  # noqa: F401  optional dependency: requirements-live.txt
    except ImportError:
        return False, [f"  live view: off (foxglove-sdk is not installed: {INSTALL_HINT})"]
    with socket.socket() as s:
        try:
            s.bind((host, port))
        except OSError as e:
            return False, [f"  live view: off (port {port}: {e.strerror}; the demo goes on "
                           "without it)"]
    return True, [f"  live view: open while it runs: {viewer}: {url}"
                  for viewer, url in viewer_urls(host, port).items()]


#: the characters of an SDK log message kept (it may quote a client's whole frame)
MAX_LOGGED_CHARS = 300
#: the Python logger the SDK logs through (its children: foxglove.websocket...)
SDK_LOGGER = "foxglove"


def cut(text: str, n: int = MAX_LOGGED_CHARS) -> str:
    """text cut to n characters, saying how long it was."""
    return text if len(text) <= n else f"{text[:n]}... ({len(text)} characters)"


class ClientProblemLog(logging.Handler):
    """The SDK's log records (from the server's threads) to `warn(message)`, the node's
    warning: throttled per SDK component (at most one line per `period` s each, the next
    one counting those suppressed), each cut to MAX_LOGGED_CHARS."""

    def __init__(self, warn, period: float):
        super().__init__(logging.WARNING)
        self.throttle = ThrottledLog(warn, period)
        self._lock = threading.Lock()

    def emit(self, record):
        try:
            text = cut(record.getMessage())
        except Exception:    # a record whose arguments do not format
            text = cut(str(record.msg))
        with self._lock:
            self.throttle("live_view", f"live_view: {text}", record.name)

    def install(self):
        """Take the SDK's log records (not also to the root logger's handlers)."""
        sdk = logging.getLogger(SDK_LOGGER)
        sdk.addHandler(self)
        sdk.propagate = False

    def remove(self):
        sdk = logging.getLogger(SDK_LOGGER)
        sdk.removeHandler(self)
        sdk.propagate = not any(isinstance(h, ClientProblemLog) for h in sdk.handlers)


class MeshAssets:
    """The asset handler of the live view (the SDK's ``asset_handler``: URI -> bytes or
    None): the mesh files a URDF names, each under its URI as the URDF writes it, read when
    asked; any other URI, a file grown over MAX_MESH_BYTES or gone: None."""

    def __init__(self, urdf_xml: str, roots=(), base_dir: str | None = None):
        #: URI -> file; the URIs whose files are not there (warned about once by open())
        self.files, self.missing = {}, []
        for uri in mesh_filenames(urdf_xml):
            try:
                path = resolve_mesh(uri, roots, base_dir)
            except MeshError:
                self.missing.append(uri)
                continue
            if path.lower().endswith(MESH_SUFFIXES):
                self.files[uri] = path

    @classmethod
    def of_robot(cls, robot: str, urdf_xml: str):
        """The assets of a `robot` value (a library name, a spec or URDF path): package://
        under its spec's roots, relative paths from its URDF's directory."""
        roots = package_dirs(load_robot(robot)) if spec_text(robot) is not None else []
        return cls(urdf_xml, roots, os.path.dirname(robot_urdf(robot)))

    def __call__(self, uri: str) -> bytes | None:
        path = self.files.get(uri)
        try:
            if path is None or os.path.getsize(path) > MAX_MESH_BYTES:
                return None
            with open(path, "rb") as f:
                return f.read(MAX_MESH_BYTES + 1)[:MAX_MESH_BYTES]
        except OSError:
            return None


class _Listener:
    """The SDK's ServerListener: which topics have subscribers, and the latched messages
    again for a new subscriber (called from the server's thread)."""

    def __init__(self, live):
        self.live = live

    def on_subscribe(self, _client, channel):
        self.live.subscribed_changed(channel.topic, +1)

    def on_unsubscribe(self, _client, channel):
        self.live.subscribed_changed(channel.topic, -1)


class LiveView:
    """A running Foxglove WebSocket server (made by :meth:`open`): one channel per topic,
    ``log`` sends CDR bytes to the clients that subscribe to the topic."""

    def __init__(self, foxglove, host, port, name, problems=None, assets=None):
        self._fox = foxglove
        #: the SDK's problems with clients to the node's log (ClientProblemLog), or None
        self.problems = problems
        if problems is not None:
            problems.install()
        self.context = foxglove.Context()
        self.channels = {}         # topic -> the SDK's channel
        self.latched = {}          # topic -> (bytes, stamp_ns) of the last latched message
        self._counts = {}          # topic -> subscriptions now
        self._lock = threading.Lock()
        #: the topics with at least one subscription now (replaced, never changed in place:
        #: read without a lock by the stepping thread)
        self.subscribed = frozenset()
        #: steps between two messages of a topic served (live_view_rate; the TF topics
        #: keep their own rate, tf_rate, and latched topics are always served)
        self.every = 1
        self.pending = []          # (channel, bytes, stamp) logged since the last flush
        # the SDK's server on a loopback port of its own, behind the front on host:port
        # (which lets in the clients offering the older subprotocol name too)
        self.server = foxglove.start_server(name=name, host="127.0.0.1", port=0,
                                            server_listener=_Listener(self),
                                            asset_handler=assets, context=self.context)
        try:
            self.front = SubprotocolFront(host, port, self.server.port)
        except OSError:
            self.server.stop()
            if problems is not None:
                problems.remove()
            raise
        self.host, self.port = host, self.front.port

    @classmethod
    def open(cls, host, port, topics, log, name="sim_node", every=1, throttle_period=2.0,
             assets: MeshAssets | None = None):
        """The live view serving `topics` ([(resolved topic, message type, latched)]) on
        host:port every `every` steps, and the robot's meshes `assets`, or None after one
        error line on `log` (foxglove-sdk not installed, the port in use, ...): the
        simulation goes on without it. Its problems with clients are warnings on `log`, at
        most one per `throttle_period` s and SDK component; meshes that are not there, one
        warning."""
        try:
            import foxglove  # optional dependency: requirements-live.txt
        except ImportError:
            log.error(f"live_view: foxglove-sdk is not installed; {INSTALL_HINT}. The "
                      "simulation goes on without the live view.")
            return None
        problems = ClientProblemLog(log.warning, throttle_period)
        try:
            live = cls(foxglove, host, port, name, problems, assets)
        except Exception as e:    # the SDK raises RuntimeError (FoxgloveError ...)
            problems.remove()
            log.error(f"live_view: cannot serve on {host}:{port}: {cut(str(e))}. The "
                      "simulation goes on without the live view (choose another "
                      "live_view_port).")
            return None
        if assets is not None and assets.missing:
            log.warning(f"live view: the URDF's mesh(es) {', '.join(assets.missing)} are not "
                        "on this machine; Foxglove draws those links without them")
        live.every = max(1, int(every))
        for topic, typ, latched in topics:
            live.add_topic(topic, typ, latched)
        urls = viewer_urls(host, live.port)
        log.info(f"live view: Foxglove WebSocket server on ws://{host}:{live.port} "
                 f"({len(live.channels)} topics; subprotocol {SUBPROTOCOL} or "
                 f"{LEGACY_SUBPROTOCOL}: Foxglove, Lichtblick of any release); open "
                 f"{urls['Foxglove']}")
        return live

    def add_topic(self, topic, typ, latched=False):
        """Advertise `topic` of message type `typ` (an rclpy class or 'pkg/msg/Type')."""
        from foxglove.channel import Channel  # deferred: foxglove is imported in open()
        name = type_name(typ)
        schema = self._fox.Schema(name=name, encoding="ros2msg",
                                  data=message_definition(name).encode("utf-8"))
        self.channels[topic] = Channel(topic, schema=schema, message_encoding="cdr",
                                       context=self.context).base
        if latched:
            self.latched.setdefault(topic, None)

    def subscribed_changed(self, topic, delta):
        with self._lock:
            n = self._counts[topic] = max(0, self._counts.get(topic, 0) + delta)
            self.subscribed = frozenset(t for t, c in self._counts.items() if c > 0)
            last = self.latched.get(topic) if delta > 0 and n else None
        if last is not None:      # a latched topic: its last message to the new subscriber
            self.channels[topic].log(last[0], log_time=last[1])

    def wants(self, topic) -> bool:
        """A client subscribes to `topic` (a latched one is always wanted: kept for later)."""
        return topic in self.subscribed or topic in self.latched

    def log(self, topic, data, stamp_ns):
        """CDR bytes (immutable: kept as they are) of `topic` at log time stamp_ns for its
        subscribers (if any): a latched topic's at once, the others at the next flush()."""
        if topic in self.latched:
            self.latched[topic] = (data, stamp_ns)
            if topic in self.subscribed:
                self.channels[topic].log(data, log_time=stamp_ns)
        elif topic in self.subscribed:
            self.pending.append((self.channels[topic], data, stamp_ns))

    def flush(self):
        """Hand the messages logged since the last flush to the server, one after another
        (called once the state of a step is out: a wake-up of the server's threads per step
        rather than per message, which on a busy machine costs the step tens of us each)."""
        pending = self.pending
        if pending:
            self.pending = []
            for channel, data, stamp_ns in pending:
                channel.log(data, log_time=stamp_ns)

    def stop(self):
        """Stop the front and the server (idempotent)."""
        if self.server is not None:
            self.front.stop()
            self.server.stop()
            self.server = None
        if self.problems is not None:
            self.problems.remove()
            self.problems = None
