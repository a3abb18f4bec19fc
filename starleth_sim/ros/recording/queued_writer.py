"""A recorder written by a thread of its own: the in-process recorder of sim_node where no
writer process can be started."""
from __future__ import annotations

import collections
import threading
import time

from .interface import Recorder
from .mcap_sink import RecordingError


class QueuedRecorder(Recorder):
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
    thread), later writes return False and what was queued is dropped (:attr:`dropped`).
    Implements :class:`~.interface.Recorder`; the file's writer is :attr:`inner`."""

    POLL = 0.002   # s: the writer looks at the queue this often when it ran empty
    BATCH = 4      # messages written between two releases of the GIL

    def __init__(self, inner, on_failure=None):
        self.inner = inner             # the file's writer (McapRecorder or SplitRecorder)
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

    def _after_the_queue(self, method, *args):
        """Call a method of the file's writer once everything queued is written."""
        self.flush()
        if self.failure is not None:
            raise RecordingError(self.failure)
        try:
            return method(*args)
        except RecordingError as e:
            self._failed(e)
            raise

    def add_topic(self, topic: str, msg_type, qos=None, type_hash: str | None = None) -> int:
        return self._after_the_queue(self.inner.add_topic, topic, msg_type, qos, type_hash)

    def add_metadata(self, name: str, data: dict) -> None:
        self._after_the_queue(self.inner.add_metadata, name, data)

    def add_attachment(self, name: str, media_type: str, data, log_time_ns: int = 0) -> None:
        self._after_the_queue(self.inner.add_attachment, name, media_type, data, log_time_ns)

    def counts(self) -> dict:
        self.flush()
        return self.inner.counts()

    @property
    def topics(self) -> dict:
        return self.inner.topics

    @property
    def path(self):
        return self.inner.path

    @property
    def messages_on_disk(self) -> int:
        """Messages in the chunks that reached the file (the file's writer's count)."""
        return self.inner.messages_on_disk

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
        self.inner.close(metadata=metadata)
