"""One MCAP file in the rosbag2 layout, written without a running ROS graph.

:class:`McapRecorder` writes what ``ros2 bag record -s mcap`` writes, so that rosbag2,
rosbags, Foxglove and the ``mcap`` tools read the file as a ROS 2 bag:

* profile ``ros2``; one schema per message type, named ``pkg/msg/Type``, encoding ``ros2msg``
  (:func:`~.schemas.message_definition`);
* channels with message encoding ``cdr`` and the metadata ``offered_qos_profiles`` (YAML, the
  rosbag2 metadata version 9 spelling: :mod:`.qos`) and ``topic_type_hash`` when known;
* a metadata record ``rosbag2`` holding ``serialized_metadata`` (the ``BagMetadata`` YAML that
  ``ros2 bag info`` shows) and ``ROS_DISTRO``, written when the file is closed.

Messages are given either as rclpy message objects (serialised to CDR with
``rclpy.serialization.serialize_message``) or as CDR bytes already serialised, e.g. the bytes a
node has just published with ``Publisher.publish(bytes)``, so each message is serialised once.

The writer buffers at most one chunk (``chunk_size`` bytes); :meth:`McapRecorder.close`
writes the summary. A process that handles SIGINT/SIGTERM by calling ``close`` leaves a file
that is complete up to its last message.
"""
from __future__ import annotations

import json
import os
import threading
import time
from collections import OrderedDict

import yaml
from mcap.writer import CompressionType, Writer

from .interface import DEFAULT_CHUNK_SIZE, Recorder
from .mcap_sink import FileSink, RecordingError, close_damaged, failure_cause
from .qos import qos_profiles_yaml
from .schemas import message_definition, type_name

#: the version of rosbag2's BagMetadata written (metadata.yaml, the ``rosbag2`` record)
ROSBAG2_METADATA_VERSION = 9


class _Topic:
    __slots__ = ("name", "type", "channel_id", "qos_yaml", "type_hash", "count")

    def __init__(self, name, type_, channel_id, qos_yaml, type_hash):
        self.name, self.type, self.channel_id = name, type_, channel_id
        self.qos_yaml, self.type_hash, self.count = qos_yaml, type_hash, 0


class McapRecorder(Recorder):
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
    closed (later writes return False). Implements :class:`~.interface.Recorder`."""

    def __init__(self, path: str, *, chunk_size: int = DEFAULT_CHUNK_SIZE,
                 compression: str = "none", library: str = "starleth_sim",
                 ros_distro: str | None = None, custom_data: dict | None = None):
        comp = {"none": CompressionType.NONE, "": CompressionType.NONE,
                "lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD}
        if compression not in comp:
            raise ValueError(f"compression must be one of {sorted(comp)}, got {compression!r}")
        self.path = str(path)
        try:
            os.makedirs(os.path.dirname(os.path.abspath(self.path)), exist_ok=True)
            self._file = FileSink(self.path)
        except OSError as e:
            raise RecordingError(f"{self.path}: {failure_cause(e, self.path)}") from None
        self.failure = None            # why the recording stopped early (RecordingError)
        self.messages_on_disk = 0      # messages in chunks that reached the file
        self.dropped = 0               # none: a write is in the file's buffers or raises
        self.close_note = ""
        self._disk_counts = {}         # topic -> messages in chunks that reached the file
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=comp[compression])
        try:
            self._writer.start(profile="ros2", library=library)
        except OSError as e:
            self._file.close()
            raise RecordingError(f"{self.path}: {failure_cause(e, self.path)}") from None
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
        cause = failure_cause(error, self.path)
        end = self._file.good_end if data_end is None else data_end
        complete = close_damaged(self._file.fd, end, {"cause": cause,
                                                       "messages": str(self.messages_on_disk)})
        self._file.close()
        self.failure = (f"{self.path}: {cause}; " + (
            f"the file is closed, complete up to the last message written "
            f"({self.messages_on_disk} messages)" if complete else
            "the file is cut after the last message written: read it with --salvage"))
        raise RecordingError(self.failure) from None

    def close(self, timeout=None, metadata=None) -> None:  # noqa: ARG002 (Recorder's signature)
        """Add the `metadata` records ({name: data}), write the rosbag2 metadata record and
        the summary, close the file (idempotent; `timeout` is not needed: nothing is
        queued). A failure on the way closes the file as a complete bag up to its last
        whole chunk (raises RecordingError)."""
        for name, data in (metadata or {}).items():
            self.add_metadata(name, data)
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

    def __del__(self):  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass
