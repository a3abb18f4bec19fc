"""A recorder in a child process of its own (:class:`ProcessRecorder`: sim_node's
recorder), the parent's side of the pipe to it; :mod:`.writer_child` is the child's."""
from __future__ import annotations

import collections
import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import time

from .interface import Recorder, StorageOptions
from .mcap_sink import RecordingError, repair
from .qos import qos_to_dict
from .schemas import registered_msg_text, type_name
from .split_writer import SplitRecorder

#: ``python -m WRITER_MODULE WRITER_FLAG`` runs the writer process
WRITER_MODULE, WRITER_FLAG = "starleth_sim.ros.recording", "--writer"
#: the frames to the writer process: kind (1 byte), payload size (4 bytes, little endian),
#: payload; MESSAGES: message records, each MESSAGE_HEAD and its CDR bytes; REQUEST: a
#: pickled (operation, *arguments) the writer answers with a pickled (ok, value) of its
#: own size-prefixed frame
MESSAGES, REQUEST = b"M", b"R"
MESSAGE_HEAD = struct.Struct("<HqI")          # topic index, log time, size
#: the directory holding the starleth_sim package (the writer process imports it from there)
_SOURCE_ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__)))))


def enlarge_pipe(fd, size) -> int:
    """Ask for a pipe buffer of `size` bytes (Linux F_SETPIPE_SZ, capped at
    /proc/sys/fs/pipe-max-size); returns the size in effect (0 where it cannot be read)."""
    try:
        import fcntl  # deferred: not on every platform (then the pipe keeps its size)
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


class ProcessRecorder(Recorder):
    """A recorder (:class:`~.mcap_writer.McapRecorder`, or :class:`SplitRecorder` when
    `max_duration_ns` or `max_size` is given) in a child process of its own (``python -m
    starleth_sim.ros.recording --writer``: :mod:`.writer_child`): the caller hands CDR
    bytes over through a pipe and the writing (~12 µs of Python per message) runs outside
    its interpreter, so it takes nothing from the caller's GIL. Messages are buffered and
    sent when 64 kB are buffered and on ``hand_over()`` (sim_node calls it every
    ``HAND_OVER_STEPS`` steps, after the state is out: one pipe write and one wake-up of
    the writer per 20 ms of sim time instead of one per step); ``add_topic``,
    ``add_metadata``, ``add_attachment`` and ``close`` are sent at once and wait for the
    child's answer (an error there is raised here). The child ignores SIGINT / SIGTERM
    (its parent closes it) and finalises the file when its input ends, so even a parent
    killed outright leaves a complete file. Implements :class:`~.interface.Recorder`
    (``write`` returns False after ``close``); the keyword arguments other than the split
    limits and `on_failure` (`file_settings`) are each file's McapRecorder's.

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
                 on_failure=None, **file_settings):
        self.path = str(path)
        #: the recording's storage options (what the writer process opens)
        self.options = StorageOptions(uri=self.path, max_bagfile_duration_ns=max_duration_ns,
                                      max_bagfile_size=max_size, **file_settings)
        self.split = self.options.split
        self._proc = subprocess.Popen(     # OSError: no process (the caller falls back)
            [sys.executable, "-m", WRITER_MODULE, WRITER_FLAG],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=None,
            env=dict(os.environ, PYTHONPATH=os.pathsep.join(
                p for p in (_SOURCE_ROOT, os.environ.get("PYTHONPATH", "")) if p)))
        self._fd = self._proc.stdin.fileno()
        self._in_fd = self._proc.stdout.fileno()
        os.set_blocking(self._fd, False)
        self.pipe_size = enlarge_pipe(self._fd, self.PIPE_SIZE)
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
            self._call("open", self.options)
        except BaseException:
            self._abandon()
            raise
        self._on_failure = on_failure

    # -- the pipe -------------------------------------------------------------------------------
    def _queue(self, kind: bytes, payload, messages=0) -> bool:
        frame = kind + len(payload).to_bytes(4, "little") + payload
        if kind == MESSAGES and self._pending_bytes + len(frame) > self.MAX_BACKLOG:
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
        while True:
            if len(self._answers) >= 4:
                size = int.from_bytes(self._answers[:4], "little")
                if len(self._answers) >= 4 + size:
                    data = bytes(self._answers[4:4 + size])
                    del self._answers[:4 + size]
                    return pickle.loads(data)
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
        self._queue(REQUEST, pickle.dumps(request))
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
            self._queue(MESSAGES, bytes(self._buf), self._buf_messages)
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
                             registered_msg_text(name))
            self._topics[topic] = (len(self._topics), cid, name)
        return self._topics[topic][1]

    @property
    def topics(self) -> dict:
        return {t: name for t, (_, _, name) in self._topics.items()}

    def add_metadata(self, name: str, data: dict) -> None:
        self._call("add_metadata", name, dict(data))

    def add_attachment(self, name: str, media_type: str, data, log_time_ns: int = 0) -> None:
        self._call("add_attachment", name, media_type, data, int(log_time_ns))

    def counts(self) -> dict:
        return self._call("counts")

    def write(self, topic: str, msg, log_time_ns: int,
              publish_time_ns: int | None = None) -> bool:  # noqa: ARG002 (Recorder's signature)
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
        self._buf += MESSAGE_HEAD.pack(self._topics[topic][0], log_time_ns, len(msg))
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
            records = {name: dict(data) for name, data in (metadata or {}).items()}
            self._queue(REQUEST, pickle.dumps(("close", records)))
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
