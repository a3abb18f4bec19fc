"""A split recording: rosbag2's bag directory of numbered, complete MCAP files and its
``metadata.yaml`` (``ros2 bag record --max-bag-duration/--max-bag-size``)."""
from __future__ import annotations

import os
import threading

import yaml

from .interface import Recorder, StorageOptions
from .mcap_sink import RecordingError
from .mcap_writer import ROSBAG2_METADATA_VERSION, McapRecorder
from .schemas import type_name


def _widen_span(span, files_entry):
    """(start, end) ns of a bag's messages widened by one file's BagMetadata "files" entry
    (a file without messages leaves it as it is; span None: nothing yet)."""
    if not files_entry["message_count"]:
        return span
    start = files_entry["starting_time"]["nanoseconds_since_epoch"]
    end = start + files_entry["duration"]["nanoseconds"]
    return (start, end) if span is None else (min(span[0], start), max(span[1], end))


class SplitRecorder(Recorder):
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

    Implements :class:`~.interface.Recorder` as :class:`~.mcap_writer.McapRecorder` does;
    `path` is the directory (a trailing ``.mcap`` is dropped from the name), the other
    keyword arguments (`file_settings`) are each file's McapRecorder's. A failed write
    closes the current file as McapRecorder does, writes metadata.yaml and raises
    RecordingError (:attr:`failure`)."""

    def __init__(self, path: str, *, max_duration_ns: int = 0, max_size: int = 0,
                 **file_settings):
        path = self.directory(path)
        #: the recording's storage options (uri: the directory)
        self.options = StorageOptions(uri=path, max_bagfile_duration_ns=max_duration_ns,
                                      max_bagfile_size=max_size, **file_settings)
        if os.path.exists(path) and (not os.path.isdir(path) or os.listdir(path)):
            raise FileExistsError(f"{path}: the bag directory exists and is not empty")
        os.makedirs(path, exist_ok=True)
        self.path = path
        self.name = os.path.basename(os.path.normpath(path))
        self.max_duration_ns = int(max_duration_ns)
        self.max_size = int(max_size)
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
        self.dropped = 0           # none: a write is in the file's buffers or raises
        self.close_note = ""
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
        rec = McapRecorder(self.file_path(self.path, len(self._done)),
                           **self.options.file_settings())
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

    # -- the recorder interface -------------------------------------------------------------
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

    @property
    def messages_on_disk(self) -> int:
        """Messages in the closed files and in the chunks of the current one that reached
        its file."""
        n = sum(f["message_count"] for f in self._done)
        if self._current is not None and not self._current.closed:
            n += self._current.messages_on_disk
        return n

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
        compression = self.options.compression
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
            "custom_data": dict(self.options.custom_data),
            "ros_distro": self.options.ros_distro or os.environ.get("ROS_DISTRO", "jazzy"),
        }

    def _write_metadata_yaml(self):
        self.metadata_writes += 1
        data = {"rosbag2_bagfile_information": self.bag_metadata()}
        tmp = os.path.join(self.path, "metadata.yaml.tmp")
        with open(tmp, "w") as f:
            yaml.safe_dump(data, f, sort_keys=False)
        os.replace(tmp, os.path.join(self.path, "metadata.yaml"))

    def close(self, timeout=None, metadata=None) -> None:  # noqa: ARG002 (Recorder's signature)
        """Add the `metadata` records ({name: data}) to the current file, close it, write
        metadata.yaml (idempotent; `timeout` is not needed: nothing is queued)."""
        with self._lock:
            if self._closed:
                return
            for name, data in (metadata or {}).items():
                self.add_metadata(name, data)
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
