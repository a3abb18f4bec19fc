"""What every recorder of this package is opened with and what it offers: the
:class:`StorageOptions` of a recording (rosbag2's ``StorageOptions``) and the
:class:`Recorder` protocol its writers implement (rosbag2's ``BaseWriterInterface``)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

#: the one storage this package writes (rosbag2's storage id of the MCAP plugin)
STORAGE_ID = "mcap"
#: bytes of messages an MCAP writer buffers before it writes a chunk
DEFAULT_CHUNK_SIZE = 256 * 1024


@dataclass(frozen=True)
class StorageOptions:
    """Where and how a recording is written (rosbag2's ``StorageOptions``; the chunk
    settings are those of its MCAP plugin's storage configuration).

    With ``max_bagfile_size`` or ``max_bagfile_duration_ns`` above 0 the recording is
    split like ``ros2 bag record --max-bag-size/--max-bag-duration``: `uri` then names a
    bag directory of numbered ``.mcap`` files (a trailing ``.mcap`` is dropped from its
    name) with a ``metadata.yaml``; else `uri` is the one ``.mcap`` file."""

    uri: str
    storage_id: str = STORAGE_ID
    #: bytes per file of a split recording; 0: no split by size
    max_bagfile_size: int = 0
    #: nanoseconds of message time per file of a split recording; 0: no split by duration
    max_bagfile_duration_ns: int = 0
    #: chunk compression: "none", "lz4" or "zstd"
    compression: str = "none"
    chunk_size: int = DEFAULT_CHUNK_SIZE
    #: the MCAP header's library field
    library: str = "starleth_sim"
    #: the bag's ROS_DISTRO (None: the environment's, else "jazzy")
    ros_distro: str | None = None
    #: the BagMetadata's custom_data (string keys and values)
    custom_data: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.storage_id != STORAGE_ID:
            raise ValueError(f"storage_id must be {STORAGE_ID!r}, got {self.storage_id!r}")
        object.__setattr__(self, "uri", str(self.uri))
        object.__setattr__(self, "max_bagfile_size", int(self.max_bagfile_size))
        object.__setattr__(self, "max_bagfile_duration_ns", int(self.max_bagfile_duration_ns))

    @property
    def split(self) -> bool:
        """Whether the recording is a bag directory of numbered files."""
        return self.max_bagfile_duration_ns > 0 or self.max_bagfile_size > 0

    def file_settings(self) -> dict:
        """The keyword arguments of one file's writer (:class:`~.mcap_writer.McapRecorder`)."""
        return {"chunk_size": self.chunk_size, "compression": self.compression,
                "library": self.library, "ros_distro": self.ros_distro,
                "custom_data": dict(self.custom_data)}

    def split_limits(self) -> dict:
        """The keyword arguments that split a recording (SplitRecorder, ProcessRecorder)."""
        return {"max_duration_ns": self.max_bagfile_duration_ns,
                "max_size": self.max_bagfile_size}


@runtime_checkable
class Recorder(Protocol):
    """A writer of a ROS 2 bag, open from its construction (rosbag2's ``open``) until
    :meth:`close`: :class:`~.mcap_writer.McapRecorder` (one file),
    :class:`~.split_writer.SplitRecorder` (a bag directory),
    :class:`~.queued_writer.QueuedRecorder` (either, written by a thread) and
    :class:`~.process_writer.ProcessRecorder` (either, written by a child process).

    A write that fails (disk full, file-size limit, I/O error, a writer process gone)
    leaves the file closed as a complete bag up to what reached the disk, sets
    :attr:`failure` and closes the recorder: the in-process writers raise
    :class:`~.mcap_sink.RecordingError` once, the queued and process writers tell their
    ``on_failure(message)`` callback once instead (nothing raises on the caller's hot
    path). Writing after ``close`` or a failure is ignored (returns False)."""

    #: the file (or the bag directory) written
    path: str
    #: why the recording stopped early (file, cause, how to read it), else None
    failure: str | None
    #: messages handed to :meth:`write` (and accepted)
    message_count: int
    #: of them, dropped before they reached the file (a writer too far behind, a failure)
    dropped: int
    #: what close had to leave undone (a time limit), "" if nothing
    close_note: str

    @property
    def closed(self) -> bool:
        """Closed, or failed: writes are ignored."""

    @property
    def topics(self) -> dict:
        """{topic: 'pkg/msg/Type'} of the registered topics."""

    def add_topic(self, topic: str, msg_type, qos=None, type_hash: str | None = None) -> int:
        """Register a topic (rosbag2's ``create_topic``; idempotent): msg_type an rclpy
        message class or 'pkg/msg/Type', qos an rclpy QoSProfile, a dict or a list of them
        (the offered QoS profiles). Returns the channel id."""

    def add_metadata(self, name: str, data: dict) -> None:
        """A metadata record (string keys; values not strings are JSON-encoded)."""

    def add_attachment(self, name: str, media_type: str, data, log_time_ns: int = 0) -> None:
        """An attachment (bytes or str) of every file of the bag."""

    def write(self, topic: str, msg, log_time_ns: int, publish_time_ns: int | None = None) -> bool:
        """Record one message (an rclpy message or its CDR bytes) on a registered topic;
        False if the recorder is closed."""

    def counts(self) -> dict:
        """{topic: messages written}."""

    def hand_over(self) -> None:
        """Pass the messages buffered in the caller on to the writer now, without waiting.
        This default does nothing: the in-process file writers take every write at once."""

    def close(self, timeout: float | None = None, metadata: dict | None = None) -> None:
        """Write what is still queued (within `timeout` s where the writing is queued),
        add the `metadata` records ({name: data}), finalise the file (idempotent)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
