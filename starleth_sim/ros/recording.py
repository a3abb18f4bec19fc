"""MCAP recording in the rosbag2 layout, without a running ROS graph.

``McapRecorder`` writes what ``ros2 bag record -s mcap`` writes, so that rosbag2, rosbags,
Foxglove and the ``mcap`` tools read the file as a ROS 2 bag:

* profile ``ros2``; one schema per message type, named ``pkg/msg/Type``, encoding ``ros2msg``,
  whose text is the type's ``.msg`` file followed by every type it depends on, each after a
  line of 80 ``=`` and a ``MSG: pkg/Type`` line (rosbag2's ``LocalMessageDefinitionSource``
  format);
* channels with message encoding ``cdr`` and the metadata ``offered_qos_profiles`` (YAML, the
  rosbag2 metadata version 9 spelling) and ``topic_type_hash`` when known;
* a metadata record ``rosbag2`` holding ``serialized_metadata`` (the ``BagMetadata`` YAML that
  ``ros2 bag info`` shows) and ``ROS_DISTRO``, written when the file is closed.

Messages are given either as rclpy message objects (serialised to CDR with
``rclpy.serialization.serialize_message``) or as CDR bytes already serialised, e.g. the bytes a
node has just published with ``Publisher.publish(bytes)``, so each message is serialised once.
The ``.msg`` texts come from the ``share/<pkg>/msg`` directories of the message packages (found
with ``AMENT_PREFIX_PATH`` or next to the Python packages of pip-installed ROS wheels); a type
without a ``.msg`` file gets a definition generated from its Python class.

The writer buffers at most one chunk (``chunk_size`` bytes); :meth:`McapRecorder.close`
writes the summary. A process that handles SIGINT/SIGTERM by calling ``close`` leaves a file
that is complete up to its last message.
"""
from __future__ import annotations

import importlib
import json
import os
import re
import sys
import threading
import time
from collections import OrderedDict

import yaml

from .mcap_sink import FileSink, RecordingError, close_damaged, repair

SEPARATOR = "=" * 80
RMW_DURATION_INFINITE = {"sec": 9223372036854775807, "nsec": 999999999}
ROSBAG2_METADATA_VERSION = 9
_PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
               "int32", "uint32", "int64", "uint64", "string", "wstring"}
# field types of a .msg file: "pkg/Type", "Type", "Type[]", "Type[3]", "string<=8" ...
_MSG_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:<=\d+)?(?:\[[^\]]*\])?\s+")


# -- message types ---------------------------------------------------------------------------
def type_name(msg_type) -> str:
    """'pkg/msg/Type' of an rclpy message class (or a 'pkg/msg/Type' / 'pkg/Type' string)."""
    if isinstance(msg_type, str):
        parts = msg_type.split("/")
        if len(parts) == 2:
            return f"{parts[0]}/msg/{parts[1]}"
        if len(parts) == 3:
            return msg_type
        raise ValueError(f"not a ROS type name: {msg_type!r}")
    module = msg_type.__module__.split(".")
    return f"{module[0]}/{module[1]}/{msg_type.__name__}"


def message_class(name: str):
    """The rclpy message class of 'pkg/msg/Type' or 'pkg/Type'."""
    pkg, sub, typ = type_name(name).split("/")
    return getattr(importlib.import_module(f"{pkg}.{sub}"), typ)


def _share_dirs(pkg: str):
    """Candidate share/<pkg> directories: AMENT_PREFIX_PATH, this interpreter's prefixes and
    the prefix of the installed Python package (pip wheels put share/ beside lib/)."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes += [sys.prefix, sys.base_prefix]
    try:
        spec = importlib.util.find_spec(pkg)
        if spec is not None and spec.origin:
            d = os.path.dirname(os.path.abspath(spec.origin))   # .../lib/pythonX/site-packages/pkg
            prefixes.append(os.path.abspath(os.path.join(d, "..", "..", "..", "..")))
    except (ImportError, ValueError):
        pass
    seen = set()
    for p in prefixes:
        d = os.path.join(p, "share", pkg)
        if d not in seen:
            seen.add(d)
            yield d


_IDL_TO_MSG = {"double": "float64", "float": "float32", "boolean": "bool", "octet": "byte",
               "long double": "float64"}


def _idl_field_to_msg(t: str) -> str:
    m = re.fullmatch(r"sequence<(.+?)(?:, (\d+))?>", t)
    if m:
        inner = _idl_field_to_msg(m.group(1))
        return f"{inner}[<={m.group(2)}]" if m.group(2) else f"{inner}[]"
    m = re.fullmatch(r"(.+)\[(\d+)\]", t)
    if m:
        return f"{_idl_field_to_msg(m.group(1))}[{m.group(2)}]"
    m = re.fullmatch(r"(w?string)<(\d+)>", t)
    if m:
        return f"{m.group(1)}<={m.group(2)}"
    return _IDL_TO_MSG.get(t, t)


def generated_msg_text(name: str) -> str:
    """A .msg text generated from the rclpy class: constants and fields, no comments.
    Used only when the package's .msg file cannot be found."""
    cls = message_class(name)
    meta = type(cls)
    consts = getattr(meta, f"_{meta.__name__}__constants", {}) or {}
    lines = []
    for cname, value in consts.items():
        if isinstance(value, bytes):
            lines.append(f"byte {cname}={value[0]}")
        elif isinstance(value, bool):
            lines.append(f"bool {cname}={str(value).lower()}")
        elif isinstance(value, int):
            lines.append(f"int64 {cname}={value}")
        elif isinstance(value, float):
            lines.append(f"float64 {cname}={value!r}")
        elif isinstance(value, str):
            lines.append(f"string {cname}={value}")
    for fname, ftype in cls.get_fields_and_field_types().items():
        lines.append(f"{_idl_field_to_msg(ftype)} {fname}")
    return "\n".join(lines) + "\n"


_MSG_TEXT_CACHE: dict = {}


def register_msg_text(name: str, text: str) -> None:
    """The .msg text of a type whose package is not installed (e.g. tf2_msgs outside a full
    ROS install), used when no .msg file is found; its dependencies must be findable."""
    _FALLBACK_MSG_TEXTS[type_name(name)] = text


_FALLBACK_MSG_TEXTS: dict = {}


def msg_text(name: str) -> str:
    """The .msg file text of 'pkg/msg/Type' (generated from the class if no file is found,
    or taken from register_msg_text when there is no class either)."""
    full = type_name(name)
    if full in _MSG_TEXT_CACHE:
        return _MSG_TEXT_CACHE[full]
    pkg, sub, typ = full.split("/")
    text = None
    for d in _share_dirs(pkg):
        path = os.path.join(d, sub, typ + ".msg")
        if os.path.isfile(path):
            with open(path, encoding="utf-8") as f:
                text = f.read()
            break
    if text is None:
        try:
            text = generated_msg_text(full)
        except ImportError:
            if full not in _FALLBACK_MSG_TEXTS:
                raise
            text = _FALLBACK_MSG_TEXTS[full]
    _MSG_TEXT_CACHE[full] = text
    return text


def _dependencies(text: str, pkg: str):
    """Sorted 'pkg/Type' names of the non-primitive field types of a .msg text."""
    deps = set()
    for line in text.splitlines():
        m = _MSG_FIELD_TYPE.match(line.split("#", 1)[0] + " ")
        if not m or m.group(1) in _PRIMITIVES:
            continue
        t = m.group(1)
        deps.add(t if "/" in t else f"{pkg}/{t}")
    return sorted(deps)


def message_definition(msg_type) -> str:
    """Full ``ros2msg`` schema text of a message type: its .msg text followed by every
    dependency (depth first, each once), as rosbag2 writes it."""
    root = type_name(msg_type)
    seen = set()

    def append(name):
        pkg, _, typ = type_name(name).split("/")
        text = msg_text(name)
        out = text
        for dep in _dependencies(text, pkg):
            dep_pkg, dep_typ = dep.split("/")[0], dep.split("/")[-1]
            key = f"{dep_pkg}/{dep_typ}"
            if key in seen:
                continue
            seen.add(key)
            out += f"\n{SEPARATOR}\nMSG: {key}\n" + append(f"{dep_pkg}/msg/{dep_typ}")
        return out

    return append(root)


# -- QoS ----------------------------------------------------------------------------------
def _duration(d):
    """rclpy Duration / nanoseconds / {'sec','nsec'} -> {'sec', 'nsec'}; 0 = infinite."""
    if isinstance(d, dict):
        return {"sec": int(d["sec"]), "nsec": int(d["nsec"])}
    ns = getattr(d, "nanoseconds", d)
    ns = int(ns or 0)
    if ns <= 0 or ns >= RMW_DURATION_INFINITE["sec"]:
        return dict(RMW_DURATION_INFINITE)
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _policy(value, default):
    name = getattr(value, "name", value)
    if name is None:
        return default
    name = str(name).lower()
    return default if name in ("system_default", "unknown") else name


def qos_to_dict(qos) -> dict:
    """An rclpy QoSProfile (or a dict with the same keys) in rosbag2's metadata-v9 spelling."""
    if isinstance(qos, dict):
        g = qos.get
    else:
        def g(k, default=None):
            return getattr(qos, k, default)
    return {
        "history": _policy(g("history"), "keep_last"),
        "depth": int(g("depth", 0) or 0),
        "reliability": _policy(g("reliability"), "reliable"),
        "durability": _policy(g("durability"), "volatile"),
        "deadline": _duration(g("deadline", 0)),
        "lifespan": _duration(g("lifespan", 0)),
        "liveliness": _policy(g("liveliness"), "automatic"),
        "liveliness_lease_duration": _duration(g("liveliness_lease_duration", 0)),
        "avoid_ros_namespace_conventions": bool(g("avoid_ros_namespace_conventions", False)),
    }


def qos_profiles_yaml(profiles) -> str:
    """The ``offered_qos_profiles`` channel metadata string: a YAML list."""
    if profiles is None:
        profiles = [{}]
    elif not isinstance(profiles, (list, tuple)):
        profiles = [profiles]
    return yaml.safe_dump([qos_to_dict(p) for p in profiles], sort_keys=False).strip()


# -- recorder -----------------------------------------------------------------------------
class _Topic:
    __slots__ = ("name", "type", "channel_id", "qos_yaml", "type_hash", "count")

    def __init__(self, name, type_, channel_id, qos_yaml, type_hash):
        self.name, self.type, self.channel_id = name, type_, channel_id
        self.qos_yaml, self.type_hash, self.count = qos_yaml, type_hash, 0


def _cause(error) -> str:
    """An OSError as the cause of a failed recording: '[Errno 28] No space left on device'."""
    if isinstance(error, OSError) and error.errno is not None:
        return f"[Errno {error.errno}] {error.strerror}"
    return str(error) or type(error).__name__


class McapRecorder:
    """Write ROS 2 messages to an MCAP file that rosbag2 and rosbags read as a bag.

        rec = McapRecorder("run.mcap")
        rec.add_topic("/joint_states", JointState, qos=QoSProfile(depth=10))
        rec.write("/joint_states", msg, log_time_ns)          # or CDR bytes
        rec.add_metadata("starleth_sim", {"physics_config": "..."})
        rec.add_attachment("starleth.urdf", "application/xml", urdf_bytes)
        rec.close()

    Thread-safe; ``close`` is idempotent and also called by ``__exit__``. Writing after
    ``close`` is ignored (returns False), so a signal handler may close the file while the
    owner still holds it.

    A write that fails (disk full, file-size limit, I/O error) raises
    :class:`~.mcap_sink.RecordingError` once: the file is then closed as a complete bag
    holding every message up to the last chunk that reached the disk
    (:func:`~.mcap_sink.close_damaged`), :attr:`failure` says why, and the recorder is
    closed (later writes return False)."""

    def __init__(self, path: str, *, chunk_size: int = 256 * 1024, compression: str = "none",
                 library: str = "starleth_sim", ros_distro: str | None = None,
                 custom_data: dict | None = None):
        from mcap.writer import Writer, CompressionType
        comp = {"none": CompressionType.NONE, "": CompressionType.NONE,
                "lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD}
        if compression not in comp:
            raise ValueError(f"compression must be one of {sorted(comp)}, got {compression!r}")
        self.path = str(path)
        d = os.path.dirname(os.path.abspath(self.path))
        os.makedirs(d, exist_ok=True)
        self.failure = None            # why the recording stopped early (RecordingError)
        self.messages_on_disk = 0      # messages in chunks that reached the file
        self._disk_counts = {}         # topic -> messages in chunks that reached the file
        self._file = FileSink(self.path)
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=comp[compression])
        try:
            self._writer.start(profile="ros2", library=library)
        except OSError as e:
            self._file.close()
            raise RecordingError(f"{self.path}: {_cause(e)}") from None
        self._compression = "" if compression == "none" else compression
        self._lock = threading.Lock()
        self._schemas: dict[str, int] = {}
        self._topics: "OrderedDict[str, _Topic]" = OrderedDict()
        self._closed = False
        self._start_ns = None
        self._end_ns = None
        self.message_count = 0
        self.ros_distro = ros_distro or os.environ.get("ROS_DISTRO", "jazzy")
        self.custom_data = dict(custom_data or {})
        self._bytes_since_flush = 0
        self._flushed_at = 0

    # -- setup ------------------------------------------------------------------------------
    def add_topic(self, topic: str, msg_type, qos=None, type_hash: str | None = None) -> int:
        """Register a topic (idempotent); qos: an rclpy QoSProfile, a dict or a list of
        them (the offered QoS profiles). Returns the channel id."""
        with self._lock:
            if topic in self._topics:
                return self._topics[topic].channel_id
            name = type_name(msg_type)
            self._check_open()
            qos_yaml = qos_profiles_yaml(qos)
            meta = {"offered_qos_profiles": qos_yaml}
            if type_hash:
                meta["topic_type_hash"] = type_hash
            try:
                if name not in self._schemas:
                    data = message_definition(name).encode("utf-8")
                    self._schemas[name] = self._writer.register_schema(
                        name=name, encoding="ros2msg", data=data)
                cid = self._writer.register_channel(topic=topic, message_encoding="cdr",
                                                    schema_id=self._schemas[name], metadata=meta)
            except OSError as e:
                self._fail(e)
            self._topics[topic] = _Topic(topic, name, cid, qos_yaml, type_hash or "")
            return cid

    @property
    def topics(self) -> dict:
        """{topic: 'pkg/msg/Type'}"""
        return {t.name: t.type for t in self._topics.values()}

    def counts(self) -> dict:
        return {t.name: t.count for t in self._topics.values()}

    def add_metadata(self, name: str, data: dict) -> None:
        """A metadata record (string keys and values; other values are JSON-encoded)."""
        md = {str(k): v if isinstance(v, str) else json.dumps(v) for k, v in data.items()}
        with self._lock:
            if not self._closed:
                try:
                    self._writer.add_metadata(name, md)
                except OSError as e:
                    self._fail(e)

    def add_attachment(self, name: str, media_type: str, data, log_time_ns: int = 0) -> None:
        if isinstance(data, str):
            data = data.encode("utf-8")
        with self._lock:
            if not self._closed:
                try:
                    self._writer.add_attachment(create_time=time.time_ns(),
                                                log_time=int(log_time_ns), name=name,
                                                media_type=media_type, data=bytes(data))
                except OSError as e:
                    self._fail(e)

    # -- messages ---------------------------------------------------------------------------
    def write(self, topic: str, msg, log_time_ns: int, publish_time_ns: int | None = None) -> bool:
        """Record one message (an rclpy message or its CDR bytes) on a registered topic."""
        if not isinstance(msg, (bytes, bytearray, memoryview)):
            from rclpy.serialization import serialize_message
            msg = serialize_message(msg)
        log_time_ns = int(log_time_ns)
        with self._lock:
            if self._closed:
                return False
            t = self._topics[topic]
            publish = log_time_ns if publish_time_ns is None else int(publish_time_ns)
            try:
                self._writer.add_message(t.channel_id, log_time_ns, bytes(msg), publish,
                                         t.count + 1)
            except OSError as e:
                self._fail(e)
            t.count += 1
            self.message_count += 1
            pos = self._file.pos
            if pos != self._flushed_at:          # a chunk went to the file (this message too)
                self._flushed_at, self._bytes_since_flush = pos, 0
                self.messages_on_disk = self.message_count
                self._disk_counts = {name: x.count for name, x in self._topics.items()}
            self._bytes_since_flush += len(msg)
            if self._start_ns is None or log_time_ns < self._start_ns:
                self._start_ns = log_time_ns
            if self._end_ns is None or log_time_ns > self._end_ns:
                self._end_ns = log_time_ns
        return True

    @property
    def size(self) -> int:
        """Bytes of the file so far: what is on disk plus the messages of the open chunk."""
        return self._flushed_at + self._bytes_since_flush

    @property
    def start_ns(self):
        return self._start_ns

    @property
    def end_ns(self):
        return self._end_ns

    # -- closing ------------------------------------------------------------------------------
    def bag_metadata(self) -> dict:
        """The rosbag2 BagMetadata (version 9) of what has been written so far (after a
        failure: of the messages in the file)."""
        start = self._start_ns or 0
        duration = (self._end_ns - start) if self._end_ns is not None else 0
        fname = os.path.basename(self.path)
        failed = self.failure is not None
        n = self.messages_on_disk if failed else self.message_count
        return {
            "version": ROSBAG2_METADATA_VERSION,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": n,
            "topics_with_message_count": [
                {"topic_metadata": {"name": t.name, "type": t.type, "serialization_format": "cdr",
                                    "offered_qos_profiles": yaml.safe_load(t.qos_yaml),
                                    "type_description_hash": t.type_hash},
                 "message_count": self._disk_counts.get(t.name, 0) if failed else t.count}
                for t in self._topics.values()],
            "compression_format": self._compression,
            "compression_mode": "",
            "relative_file_paths": [fname],
            "files": [{"path": fname, "starting_time": {"nanoseconds_since_epoch": start},
                       "duration": {"nanoseconds": duration}, "message_count": n}],
            "custom_data": self.custom_data,
            "ros_distro": self.ros_distro,
        }

    @property
    def closed(self) -> bool:
        return self._closed

    def _check_open(self):
        if self.failure is not None:
            raise RecordingError(self.failure)

    def _fail(self, error, data_end=None):
        """A write failed: close the file as a complete bag up to the last whole record
        (data_end: the end of the data section, when the failure came after it), mark the
        recorder failed and closed, raise RecordingError (the caller holds the lock)."""
        self._closed = True
        cause = _cause(error)
        end = self._file.good_end if data_end is None else data_end
        complete = close_damaged(self._file.fd, end, {"cause": cause,
                                                       "messages": str(self.messages_on_disk)})
        self._file.close()
        self.failure = (f"{self.path}: {cause}; " + (
            f"the file is closed, complete up to the last message written "
            f"({self.messages_on_disk} messages)" if complete else
            "the file is cut after the last message written: read it with --salvage"))
        raise RecordingError(self.failure) from None

    def close(self) -> None:
        """Write the rosbag2 metadata record and the summary, close the file (idempotent).
        A failure on the way closes the file as a complete bag up to its last whole chunk
        (raises RecordingError)."""
        with self._lock:
            if self._closed:
                return
            try:
                serialized = yaml.safe_dump(self.bag_metadata(), sort_keys=False)
                self._writer.add_metadata("rosbag2", {"serialized_metadata": serialized,
                                                      "ROS_DISTRO": self.ros_distro})
                self._writer.flush()            # the last chunk
            except OSError as e:
                self._fail(e)
            self.messages_on_disk = self.message_count
            data_end = self._file.pos
            try:
                self._writer.finish()           # DataEnd, the summary, the footer
            except OSError as e:
                self._fail(e, data_end)
            self._closed = True
            self._file.fsync()
            self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def __del__(self):  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass


def _widen_span(span, files_entry):
    """(start, end) ns of a bag's messages widened by one file's BagMetadata "files" entry
    (a file without messages leaves it as it is; span None: nothing yet)."""
    if not files_entry["message_count"]:
        return span
    start = files_entry["starting_time"]["nanoseconds_since_epoch"]
    end = start + files_entry["duration"]["nanoseconds"]
    return (start, end) if span is None else (min(span[0], start), max(span[1], end))


class SplitRecorder:
    """rosbag2's split recording (``ros2 bag record --max-bag-duration/--max-bag-size``): a
    bag directory holding ``<name>_0.mcap``, ``<name>_1.mcap``, ... and ``metadata.yaml``. A
    new file is started when the current one spans `max_duration_ns` of message time or
    holds `max_size` bytes (0: no limit); every file is a complete bag on its own (all
    topics, metadata records and attachments). ``metadata.yaml`` (rosbag2 BagMetadata)
    lists the files: it is written at close, and at the splits that bring the number of
    files to a power of two, so that writing it costs O(1) per split however many files
    there are (the tools of this package read a directory's .mcap files without it; a
    recording cut short has one listing at least half of its files). The memory of an
    all-day recording stays flat: each closed file's indexes leave memory with it.

    Same interface as :class:`McapRecorder`; `path` is the directory (a trailing ``.mcap``
    is dropped from the name). A failed write closes the current file as McapRecorder
    does, writes metadata.yaml and raises RecordingError (:attr:`failure`)."""

    def __init__(self, path: str, *, max_duration_ns: int = 0, max_size: int = 0, **kwargs):
        path = self.directory(path)
        if os.path.exists(path) and (not os.path.isdir(path) or os.listdir(path)):
            raise FileExistsError(f"{path}: the bag directory exists and is not empty")
        os.makedirs(path, exist_ok=True)
        self.path = path
        self.name = os.path.basename(os.path.normpath(path))
        self.max_duration_ns = int(max_duration_ns)
        self.max_size = int(max_size)
        self._kwargs = kwargs
        self._lock = threading.RLock()
        self._topics = []          # (topic, type, qos, type_hash)
        self._metadata = []        # (name, data)
        self._attachments = []     # (name, media_type, data, log_time_ns)
        self._done = []            # per closed file: its "files" entry of the metadata
        self._done_counts = {}     # topic -> messages in the closed files
        self._topic_meta = {}      # topic -> topic_metadata (name, type, QoS, hash)
        self._span = None          # (start, end) ns of the closed files' messages
        self._closed = False
        self.failure = None
        self.message_count = 0
        self.metadata_writes = 0   # how often metadata.yaml was written
        self._current = None
        self._open_next()

    # -- files ------------------------------------------------------------------------------
    @staticmethod
    def directory(path) -> str:
        """The bag directory of `record` path (a trailing .mcap dropped)."""
        path = str(path)
        return path[:-len(".mcap")] if path.endswith(".mcap") else path

    @staticmethod
    def file_path(directory: str, index: int) -> str:
        """The index-th file of a bag directory: <directory>/<its name>_<index>.mcap."""
        name = os.path.basename(os.path.normpath(directory))
        return os.path.join(directory, f"{name}_{index}.mcap")

    @property
    def files(self) -> list:
        """Paths of the files written so far (the current one last)."""
        names = [f["path"] for f in self._done]
        if self._current is not None and not self._current.closed:
            names.append(os.path.basename(self._current.path))
        return [os.path.join(self.path, n) for n in names]

    def _open_next(self):
        rec = McapRecorder(self.file_path(self.path, len(self._done)), **self._kwargs)
        self._current = rec
        for topic, typ, qos, type_hash in self._topics:
            rec.add_topic(topic, typ, qos, type_hash)
        for name, data in self._metadata:
            rec.add_metadata(name, data)
        for name, media_type, data, log_time in self._attachments:
            rec.add_attachment(name, media_type, data, log_time)

    def _retire(self):
        """Keep only the summary of the current file, closed (its indexes leave memory
        with it)."""
        cur, self._current = self._current, None
        if cur is None:
            return
        meta = cur.bag_metadata()
        entry = meta["files"][0]
        self._done.append(entry)
        self._span = _widen_span(self._span, entry)
        for t in meta["topics_with_message_count"]:
            name = t["topic_metadata"]["name"]
            self._topic_meta.setdefault(name, t["topic_metadata"])
            self._done_counts[name] = self._done_counts.get(name, 0) + t["message_count"]

    def _split(self):
        try:
            self._current.close()
        finally:
            self._retire()
        self._open_next()
        n = len(self._done)
        if n & (n - 1) == 0:        # 1, 2, 4, 8, ... files closed: O(1) per split
            self._write_metadata_yaml()

    def _full(self, log_time_ns) -> bool:
        cur = self._current
        if not cur.message_count:
            return False
        if self.max_duration_ns and log_time_ns - cur.start_ns >= self.max_duration_ns:
            return True
        return bool(self.max_size) and cur.size >= self.max_size

    def _fail(self, error):
        """The current file failed (McapRecorder closed it as far as it could): keep its
        summary, write metadata.yaml if possible, raise RecordingError."""
        self._closed = True
        self.failure = str(error)
        self._retire()
        try:
            self._write_metadata_yaml()
        except OSError:
            pass
        raise RecordingError(self.failure) from None

    # -- the McapRecorder interface -----------------------------------------------------------
    def add_topic(self, topic: str, msg_type, qos=None, type_hash: str | None = None) -> int:
        with self._lock:
            if topic not in (t[0] for t in self._topics):
                self._topics.append((topic, msg_type, qos, type_hash))
            try:
                return self._current.add_topic(topic, msg_type, qos, type_hash)
            except RecordingError as e:
                self._fail(e)

    @property
    def topics(self) -> dict:
        return {t[0]: type_name(t[1]) for t in self._topics}

    def counts(self) -> dict:
        total = dict(self._done_counts)
        if self._current is not None and not self._current.closed:
            for name, n in self._current.counts().items():
                total[name] = total.get(name, 0) + n
        return total

    def add_metadata(self, name: str, data: dict) -> None:
        with self._lock:
            self._metadata.append((name, dict(data)))
            if self._current is not None:
                try:
                    self._current.add_metadata(name, data)
                except RecordingError as e:
                    self._fail(e)

    def add_attachment(self, name: str, media_type: str, data, log_time_ns: int = 0) -> None:
        with self._lock:
            self._attachments.append((name, media_type, data, log_time_ns))
            if self._current is not None:
                try:
                    self._current.add_attachment(name, media_type, data, log_time_ns)
                except RecordingError as e:
                    self._fail(e)

    def write(self, topic: str, msg, log_time_ns: int, publish_time_ns: int | None = None) -> bool:
        with self._lock:
            if self._closed:
                return False
            try:
                if self._full(int(log_time_ns)):
                    self._split()
                ok = self._current.write(topic, msg, log_time_ns, publish_time_ns)
            except RecordingError as e:
                self._fail(e)
            self.message_count += ok
            return ok

    @property
    def closed(self) -> bool:
        return self._closed

    def bag_metadata(self) -> dict:
        """The rosbag2 BagMetadata of the whole bag (all files)."""
        files = list(self._done)
        topic_meta = dict(self._topic_meta)
        counts = dict(self._done_counts)
        span = self._span
        if self._current is not None and not self._current.closed:
            base = self._current.bag_metadata()
            entry = base["files"][0]
            files.append(entry)
            span = _widen_span(span, entry)
            for t in base["topics_with_message_count"]:
                name = t["topic_metadata"]["name"]
                topic_meta.setdefault(name, t["topic_metadata"])
                counts[name] = counts.get(name, 0) + t["message_count"]
        if span is None:
            first = files[0]["starting_time"]["nanoseconds_since_epoch"] if files else 0
            span = (first, first)
        compression = self._kwargs.get("compression", "none")
        return {
            "version": ROSBAG2_METADATA_VERSION,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": span[1] - span[0]},
            "starting_time": {"nanoseconds_since_epoch": span[0]},
            "message_count": sum(f["message_count"] for f in files),
            "topics_with_message_count": [{"topic_metadata": m, "message_count": counts.get(n, 0)}
                                          for n, m in topic_meta.items()],
            "compression_format": "" if compression == "none" else compression,
            "compression_mode": "",
            "relative_file_paths": [f["path"] for f in files],
            "files": files,
            "custom_data": dict(self._kwargs.get("custom_data") or {}),
            "ros_distro": self._kwargs.get("ros_distro") or os.environ.get("ROS_DISTRO",
                                                                             "jazzy"),
        }

    def _write_metadata_yaml(self):
        self.metadata_writes += 1
        data = {"rosbag2_bagfile_information": self.bag_metadata()}
        tmp = os.path.join(self.path, "metadata.yaml.tmp")
        with open(tmp, "w") as f:
            yaml.safe_dump(data, f, sort_keys=False)
        os.replace(tmp, os.path.join(self.path, "metadata.yaml"))

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                self._current.close()
            except RecordingError as e:
                self.failure = str(e)
                raise
            finally:
                self._retire()
                try:
                    self._write_metadata_yaml()
                except OSError:
                    if self.failure is None:
                        raise

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class QueuedRecorder:
    """A recorder (:class:`McapRecorder` or :class:`SplitRecorder`) written by a thread of
    its own, off the caller's critical path: ``write`` hands the CDR bytes over (a queue
    append; message objects are serialised first, in the caller, as they may change
    afterwards) and returns; the writer thread adds them to the file in the same order.
    ``add_topic``, ``add_metadata`` and ``add_attachment`` wait until the queue is empty
    and act at once, so every record keeps its place. ``close`` writes everything still
    queued, then finalises the file: a process that calls it on SIGINT / SIGTERM leaves a
    complete file holding every message written before. The writer releases the GIL after
    every BATCH messages (``time.sleep(0)``), so a caller waiting for it runs within a few
    messages' time.

    A failed write (the file closed as far as it could be: McapRecorder) stops the writer:
    :attr:`failure` says why, `on_failure(message)` is called once (from the writer
    thread), later writes return False and what was queued is dropped (:attr:`dropped`)."""

    POLL = 0.002   # s: the writer looks at the queue this often when it ran empty
    BATCH = 4      # messages written between two releases of the GIL

    def __init__(self, inner, on_failure=None):
        import collections
        self.inner = inner
        self._queue = collections.deque()
        self._wake = threading.Event()
        self._idle = threading.Event()
        self._idle.set()
        self._closing = False
        self._closed = False
        self._drop = False             # close ran out of time: drop what is queued
        self.message_count = 0         # messages handed over (written or queued)
        self.dropped = 0               # messages handed over and not written
        self.failure = None
        self.close_note = ""
        self._on_failure = on_failure
        self._thread = threading.Thread(target=self._run, name="mcap-writer", daemon=True)
        self._thread.start()

    # -- the writer thread --------------------------------------------------------------------
    def _run(self):
        q, inner = self._queue, self.inner
        while True:
            if not q:
                self._idle.set()
                if self._closing:
                    return
                self._wake.wait(self.POLL)
                self._wake.clear()
                continue
            self._idle.clear()
            if self._drop or self.failure is not None:
                self.dropped += len(q)
                q.clear()
                continue
            for _ in range(self.BATCH):
                if not q:
                    break
                item = q.popleft()
                try:
                    inner.write(*item)
                except Exception as e:   # RecordingError: the file is closed already
                    self._failed(e)
                    break
            time.sleep(0)              # let a waiting thread take the GIL

    def _failed(self, error):
        self.failure = str(error)
        self.dropped += 1 + len(self._queue)
        self._queue.clear()
        if self._on_failure is not None:
            self._on_failure(self.failure)

    def flush(self, timeout=None) -> bool:
        """Wait until every message handed over is in the writer's file buffers."""
        t_end = None if timeout is None else time.monotonic() + timeout
        while self._queue or not self._idle.is_set():
            if not self._thread.is_alive():
                return not self._queue
            self._wake.set()
            if t_end is not None and time.monotonic() > t_end:
                return False
            time.sleep(0.0005)
        return True

    # -- the recorder interface -----------------------------------------------------------------
    def write(self, topic: str, msg, log_time_ns: int, publish_time_ns: int | None = None) -> bool:
        if self._closing or self.failure is not None:
            return False
        if not isinstance(msg, (bytes, bytearray, memoryview)):
            from rclpy.serialization import serialize_message
            msg = serialize_message(msg)
        elif not isinstance(msg, bytes):
            msg = bytes(msg)
        if topic not in self.inner.topics:
            raise KeyError(topic)
        self._queue.append((topic, msg, log_time_ns, publish_time_ns))
        self.message_count += 1
        return True

    def _inner_call(self, op, *args):
        self.flush()
        if self.failure is not None:
            raise RecordingError(self.failure)
        try:
            return getattr(self.inner, op)(*args)
        except RecordingError as e:
            self._failed(e)
            raise

    def add_topic(self, topic: str, msg_type, qos=None, type_hash: str | None = None) -> int:
        return self._inner_call("add_topic", topic, msg_type, qos, type_hash)

    def add_metadata(self, name: str, data: dict) -> None:
        self._inner_call("add_metadata", name, data)

    def add_attachment(self, name: str, media_type: str, data, log_time_ns: int = 0) -> None:
        self._inner_call("add_attachment", name, media_type, data, log_time_ns)

    def counts(self) -> dict:
        self.flush()
        return self.inner.counts()

    @property
    def topics(self) -> dict:
        return self.inner.topics

    @property
    def path(self):
        return self.inner.path

    def __getattr__(self, name):      # files, size, start_ns, bag_metadata, ...
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    @property
    def closed(self) -> bool:
        return self._closing or self.failure is not None

    def close(self, timeout=None, metadata=None) -> None:
        """Write what is queued (within `timeout` s: what is left then is dropped, counted
        in :attr:`dropped` and :attr:`close_note`), add the `metadata` records ({name:
        data}), stop the writer, finalise the file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._closing = True
        self._wake.set()
        self._thread.join(timeout)
        if self._thread.is_alive():
            self._drop = True
            before = self.dropped
            self._thread.join()
            self.close_note = (f"dropped {self.dropped - before} queued messages at close "
                               f"(the writer was {timeout:g} s behind)")
        while self._queue and self.failure is None:   # the writer died: write the rest here
            self.inner.write(*self._queue.popleft())
        if self.failure is not None:
            return
        for name, data in (metadata or {}).items():
            self.inner.add_metadata(name, data)
        self.inner.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def _enlarge_pipe(fd, size) -> int:
    """Ask for a pipe buffer of `size` bytes (Linux F_SETPIPE_SZ, capped at
    /proc/sys/fs/pipe-max-size); returns the size in effect (0 where it cannot be read)."""
    try:
        import fcntl
        set_sz = getattr(fcntl, "F_SETPIPE_SZ", 1031)
        get_sz = getattr(fcntl, "F_GETPIPE_SZ", 1032)
        try:
            fcntl.fcntl(fd, set_sz, size)
        except OSError:
            try:
                with open("/proc/sys/fs/pipe-max-size") as f:
                    fcntl.fcntl(fd, set_sz, min(size, int(f.read())))
            except (OSError, ValueError):
                pass
        return int(fcntl.fcntl(fd, get_sz))
    except (ImportError, OSError):   # pragma: no cover - not Linux
        return 0


class ProcessRecorder:
    """A recorder (:class:`McapRecorder`, or :class:`SplitRecorder` when `max_duration_ns`
    or `max_size` is given) in a child process of its own (``python -m
    starleth_sim.ros.recording --writer``): the caller hands CDR bytes over through a pipe
    and the writing (~12 µs of Python per message) runs outside its interpreter, so it
    takes nothing from the caller's GIL. Messages are buffered and sent when 64 kB are
    buffered and on ``hand_over()`` (sim_node calls it every ``HAND_OVER_STEPS`` steps,
    after the state is out: one pipe write and one wake-up of the writer per 20 ms of sim
    time instead of one per step); ``add_topic``, ``add_metadata``, ``add_attachment`` and
    ``close`` are sent at once and wait for the child's answer (an error there is raised
    here). The child ignores SIGINT / SIGTERM (its parent closes it) and finalises the file
    when its input ends, so even a parent killed outright leaves a complete file.
    Same interface as :class:`McapRecorder` (``write`` returns False after ``close``).

    The caller never waits for the writer: the pipe is non-blocking, and what it does not
    take stays here (up to MAX_BACKLOG bytes; beyond, a hand-over's messages are dropped and
    counted in :attr:`dropped`). The writer can fail (disk full, file-size limit, I/O
    error; it then closes the file as a complete bag up to its last chunk, reports and
    exits) or be killed (its file is then repaired here: :func:`~.mcap_sink.repair`): the
    next hand-over finds out, sets :attr:`failure` (file, cause, how to read what was
    written), calls `on_failure(message)` once, and the recorder is closed; nothing raises
    on the caller's hot path."""

    FLUSH_BYTES = 64 * 1024
    #: bytes the pipe to the writer holds (Linux's default is 64 kB, about two hand-overs of
    #: sim_node)
    PIPE_SIZE = 1 << 20
    #: bytes handed over and held here while the writer is behind (about 40 s of sim_node's
    #: recording); more is dropped, counted
    MAX_BACKLOG = 64 << 20

    def __init__(self, path: str, *, max_duration_ns: int = 0, max_size: int = 0,
                 on_failure=None, **kwargs):
        import collections
        import pickle
        import struct
        import subprocess
        self._pickle = pickle
        self._head = struct.Struct("<HqI")          # topic index, log time, size
        self.path = str(path)
        self.split = max_duration_ns > 0 or max_size > 0
        self._proc = subprocess.Popen(     # OSError: no process (the caller falls back)
            [sys.executable, "-m", "starleth_sim.ros.recording", "--writer"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=None,
            env=dict(os.environ, PYTHONPATH=os.pathsep.join(
                p for p in (os.path.dirname(os.path.dirname(os.path.dirname(
                    os.path.abspath(__file__)))), os.environ.get("PYTHONPATH", "")) if p)))
        self._fd = self._proc.stdin.fileno()
        self._in_fd = self._proc.stdout.fileno()
        os.set_blocking(self._fd, False)
        self.pipe_size = _enlarge_pipe(self._fd, self.PIPE_SIZE)
        self._topics = {}
        self._buf = bytearray()
        self._buf_messages = 0
        self._pending = collections.deque()   # [frame, messages] not yet (all) in the pipe
        self._pending_bytes = 0
        self._sent = 0                        # bytes of the first pending frame in the pipe
        self._answers = bytearray()
        self._closed = False
        self._on_failure = None               # told of failures once the file is open
        self.failure = None
        self.close_note = ""
        self.message_count = 0                # messages handed over
        self.dropped = 0                      # of them, dropped: the writer was too far behind
        try:
            self._call("open", self.path, int(max_duration_ns), int(max_size), kwargs)
        except BaseException:
            self._abandon()
            raise
        self._on_failure = on_failure

    # -- the pipe -------------------------------------------------------------------------------
    def _queue(self, kind: bytes, payload, messages=0) -> bool:
        frame = kind + len(payload).to_bytes(4, "little") + payload
        if kind == b"M" and self._pending_bytes + len(frame) > self.MAX_BACKLOG:
            self.dropped += messages
            return False
        self._pending.append([frame, messages])
        self._pending_bytes += len(frame)
        return True

    def _drain(self) -> bool:
        """Put what the pipe takes into it without waiting; False if the writer is gone."""
        pending = self._pending
        while pending:
            frame = pending[0][0]
            try:
                n = os.write(self._fd, memoryview(frame)[self._sent:])
            except BlockingIOError:
                return True
            except OSError as e:                 # EPIPE: the writer process ended
                self._writer_gone(e)
                return False
            self._sent += n
            if self._sent == len(frame):
                pending.popleft()
                self._pending_bytes -= len(frame)
                self._sent = 0
        return True

    def _drain_until(self, deadline) -> bool:
        """Wait until everything pending is in the pipe (False at the deadline, or if the
        writer is gone)."""
        import select
        while self._pending:
            if not self._drain():
                return False
            if not self._pending:
                break
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return False
            select.select([], [self._fd], [], 0.1 if left is None else min(left, 0.1))
            if self._proc.poll() is not None:
                self._drain()
                if self._pending:
                    self._writer_gone(EOFError("the recording process ended"))
                    return False
        return True

    def _read_answer(self, deadline):
        """The child's next answer (ok, value); None at the deadline; EOFError if it ended."""
        import select
        while True:
            if len(self._answers) >= 4:
                size = int.from_bytes(self._answers[:4], "little")
                if len(self._answers) >= 4 + size:
                    data = bytes(self._answers[4:4 + size])
                    del self._answers[:4 + size]
                    return self._pickle.loads(data)
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return None
            r, _, _ = select.select([self._in_fd], [], [], 0.1 if left is None else min(left, 0.1))
            if r:
                chunk = os.read(self._in_fd, 1 << 16)
                if not chunk:
                    raise EOFError("the recording process ended")
                self._answers += chunk

    def _call(self, *request, timeout=None):
        """Send a request and wait for the child's answer (raises its error; RecordingError
        if the child failed or ended)."""
        if self.failure is not None:
            raise RecordingError(self.failure)
        deadline = None if timeout is None else time.monotonic() + timeout
        self.hand_over()
        self._queue(b"R", self._pickle.dumps(request))
        if not self._drain_until(deadline):
            if self.failure is not None:
                raise RecordingError(self.failure)
            raise TimeoutError(f"the recording process ({self.path}) is {timeout:g} s behind")
        try:
            answer = self._read_answer(deadline)
        except (OSError, EOFError, ValueError) as e:
            self._writer_gone(e)
            raise RecordingError(self.failure) from None
        if answer is None:
            raise TimeoutError(f"the recording process ({self.path}) is {timeout:g} s behind")
        ok, value = answer
        if not ok:
            if isinstance(value, RecordingError):     # the file failed: the child exits
                self._writer_gone(value)
            raise value
        return value

    def hand_over(self):
        """Send the buffered messages to the writer process (what the pipe does not take
        now waits here; never blocks)."""
        if self._closed:
            return
        if self._buf:
            self._queue(b"M", bytes(self._buf), self._buf_messages)
            self._buf.clear()
            self._buf_messages = 0
        if self._pending:
            self._drain()

    @property
    def backlog(self) -> int:
        """Bytes handed over that are not in the pipe yet (the writer is behind; at most
        MAX_BACKLOG)."""
        return self._pending_bytes - self._sent

    # -- failures ---------------------------------------------------------------------------
    def _writer_gone(self, error):
        """The writer failed or ended: find out why (its report, else its exit status),
        repair the file if it could not, close this recorder, tell on_failure once."""
        if self.failure is not None:
            return
        self._closed = True
        self.dropped += self._buf_messages + sum(m for _, m in self._pending)
        self._buf.clear()
        self._pending.clear()
        self._pending_bytes = self._sent = 0
        report = error if isinstance(error, RecordingError) else None
        try:
            self._proc.stdin.close()
        except OSError:
            pass
        try:
            self._proc.wait(5)
        except Exception:   # pragma: no cover - a writer that hangs
            self._proc.kill()
            self._proc.wait(5)
        if report is None:      # its own report, if it wrote one before it exited
            try:
                while True:
                    answer = self._read_answer(time.monotonic() + 1.0)
                    if answer is None:
                        break
                    if not answer[0] and isinstance(answer[1], RecordingError):
                        report = answer[1]
            except (OSError, EOFError, ValueError):
                pass
        if report is not None:
            self.failure = str(report)
        else:
            self.failure = self._repair_after(self._proc.returncode)
        if self._on_failure is not None:
            self._on_failure(self.failure)

    def _repair_after(self, returncode) -> str:
        """The writer ended without a report (killed): close its file here."""
        import signal
        if returncode is not None and returncode < 0:
            how = f"killed by {signal.Signals(-returncode).name}"
        else:
            how = f"exit status {returncode}"
        path = self.path
        if self.split:                    # the last file of the bag directory
            d = SplitRecorder.directory(path)
            index = 0
            while os.path.exists(SplitRecorder.file_path(d, index + 1)):
                index += 1
            path = SplitRecorder.file_path(d, index)
        try:
            result = repair(path, {"cause": f"the recording process ended ({how})"})
        except OSError as e:
            result = f"unreadable ({e})"
        state = {"complete": "the file is complete",
                 "repaired": "the file is closed, complete up to the last message written",
                 "cut": "the file is cut after the last message written: read it with "
                        "--salvage"}.get(result, f"the file is {result}")
        return f"{path}: the recording process ended ({how}); {state}"

    def _abandon(self):
        try:
            self._proc.kill()
            self._proc.wait(5)
        except Exception:   # pragma: no cover
            pass

    # -- the recorder interface ---------------------------------------------------------------
    def add_topic(self, topic: str, msg_type, qos=None, type_hash: str | None = None) -> int:
        if topic not in self._topics:
            qos_dict = None if qos is None else (
                [qos_to_dict(q) for q in qos] if isinstance(qos, (list, tuple))
                else qos_to_dict(qos))
            name = type_name(msg_type)
            cid = self._call("add_topic", topic, name, qos_dict, type_hash,
                             _FALLBACK_MSG_TEXTS.get(name))     # register_msg_text's
            self._topics[topic] = (len(self._topics), cid)
        return self._topics[topic][1]

    @property
    def topics(self) -> dict:
        return {t: i for t, (i, _) in self._topics.items()}

    def add_metadata(self, name: str, data: dict) -> None:
        self._call("add_metadata", name, dict(data))

    def add_attachment(self, name: str, media_type: str, data, log_time_ns: int = 0) -> None:
        self._call("add_attachment", name, media_type, data, int(log_time_ns))

    def counts(self) -> dict:
        return self._call("counts")

    def write(self, topic: str, msg, log_time_ns: int, publish_time_ns: int | None = None) -> bool:
        if self._closed:
            return False
        if not isinstance(msg, (bytes, bytearray, memoryview)):
            from rclpy.serialization import serialize_message
            msg = serialize_message(msg)
        log_time_ns = int(log_time_ns)
        if len(self._buf) > self.FLUSH_BYTES:
            self.hand_over()
            if self._closed:
                return False
        self._buf += self._head.pack(self._topics[topic][0], log_time_ns, len(msg))
        self._buf += msg
        self._buf_messages += 1
        self.message_count += 1
        return True

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self, timeout=None, metadata=None) -> None:
        """Send what is buffered, add the `metadata` records ({name: data}), let the child
        finalise the file and wait for it. With a `timeout` (s) nothing waits longer: what
        could not be sent by then is dropped, and a writer still busy with what it got
        finalises the file on its own after this process has gone (:attr:`close_note`
        says which). A failed writer raises RecordingError (the file is closed as far as
        it could be)."""
        if self._closed:
            if self.failure is not None:
                raise RecordingError(self.failure)
            return
        deadline = None if timeout is None else time.monotonic() + timeout
        self.hand_over()
        self._closed = True
        sent = self._drain_until(deadline)
        if self.failure is not None:
            raise RecordingError(self.failure)
        if not sent:
            # what has not gone into the pipe is dropped; a frame cut halfway ends the
            # child's input there (it finalises the file after the last whole batch)
            n = sum(m for _, m in self._pending)
            self.dropped += n
            self.close_note = (f"dropped {n} queued messages at close (the recording "
                               f"process was {timeout:g} s behind); ")
            self._pending.clear()
            self._proc.stdin.close()
            self.close_note += (f"the recording process (pid {self._proc.pid}) finalises "
                                f"{self.path} on its own")
            return
        try:
            request = [("add_metadata", name, dict(data)) for name, data in
                       (metadata or {}).items()]
            self._queue(b"R", self._pickle.dumps(("close", request)))
            if self._drain_until(deadline):
                answer = self._read_answer(deadline)
            else:
                answer = None
        except (OSError, EOFError, ValueError) as e:
            self._writer_gone(e)
            raise RecordingError(self.failure) from None
        if self.failure is not None:
            raise RecordingError(self.failure)
        if answer is None:
            self._proc.stdin.close()
            self.close_note = (f"the recording process (pid {self._proc.pid}) is still "
                               f"writing; it finalises {self.path} on its own")
            return
        ok, value = answer
        try:
            self._proc.stdin.close()
        except OSError:
            pass
        if not ok:
            self.failure = str(value)
            raise value
        try:
            self._proc.wait(5 if deadline is None else max(deadline - time.monotonic(), 0.1))
        except Exception:   # pragma: no cover - it has answered: it is ending
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def _background_scheduling():
    """The writer process under SCHED_BATCH (Linux; elsewhere nothing): woken by a hand-over,
    it does not preempt the simulator that wrote it (which then would wait for the whole
    batch to be written before it goes on: 1-1.5 ms every hand-over on a busy 2-CPU machine);
    it still gets its fair share of the CPU."""
    try:
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    except (AttributeError, OSError):   # pragma: no cover - not Linux
        pass


def _writer_main():
    """The child of :class:`ProcessRecorder`: requests and message batches on stdin,
    answers on stdout; finalises the file on 'close' or when stdin ends. A failed write
    (the recorder has closed the file as far as it could) is reported as an answer
    (False, RecordingError) that nobody asked for, and the child exits: the parent finds
    its pipe closed and reads the report."""
    import pickle
    import signal
    import struct
    signal.signal(signal.SIGINT, signal.SIG_IGN)      # the parent closes the recording
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _background_scheduling()
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    head = struct.Struct("<HqI")
    rec, names = None, []

    def answer(ok, value):
        data = pickle.dumps((ok, value))
        out.write(len(data).to_bytes(4, "little") + data)
        out.flush()

    while True:
        h = inp.read(5)
        if len(h) < 5:
            break
        kind, size = h[:1], int.from_bytes(h[1:], "little")
        payload = inp.read(size)
        if len(payload) < size:
            break
        if kind == b"M":
            o = 0
            try:
                while o < size:
                    i, t, n = head.unpack_from(payload, o)
                    o += head.size
                    rec.write(names[i], payload[o:o + n], t)
                    o += n
            except RecordingError as e:
                answer(False, e)
                return
            continue
        request = pickle.loads(payload)
        op, args = request[0], request[1:]
        try:
            if op == "open":
                path, max_duration_ns, max_size, kwargs = args
                rec = (SplitRecorder(path, max_duration_ns=max_duration_ns, max_size=max_size,
                                     **kwargs) if max_duration_ns > 0 or max_size > 0
                       else McapRecorder(path, **kwargs))
                value = None
            elif op == "add_topic":
                topic, typ, qos, type_hash, fallback_text = args
                if fallback_text is not None:
                    register_msg_text(typ, fallback_text)
                value = rec.add_topic(topic, typ, qos, type_hash)
                if topic not in names:
                    names.append(topic)
            elif op == "close":
                for _, name, data in (args[0] if args else ()):
                    rec.add_metadata(name, data)
                rec.close()
                answer(True, rec.message_count)
                return
            else:
                value = getattr(rec, op)(*args)
            answer(True, value)
        except RecordingError as e:
            answer(False, e)
            return
        except Exception as e:
            if op == "open" and isinstance(e, OSError):   # one line: file and cause
                e = RecordingError(f"{args[0]}: {_cause(e)}" if e.errno is not None
                                   else str(e))           # (a message naming the file)
            answer(False, e)
    if rec is not None:
        try:
            rec.close()
        except RecordingError:
            pass


if __name__ == "__main__" and sys.argv[1:] == ["--writer"]:
    _writer_main()
