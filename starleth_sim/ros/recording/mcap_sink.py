"""The file under a recording, and what is left of it when writing fails.

A disk that fills up (ENOSPC), a file-size limit (EFBIG, ``ulimit -f``), an I/O error (EIO)
or a writer process killed outright leave an MCAP file cut somewhere in its data section.
This module makes such a file a complete MCAP file again, holding every message up to the
last whole record that reached the disk:

* :class:`FileSink` is the stream :class:`~.mcap_writer.McapRecorder` hands to the mcap
  ``Writer``: unbuffered ``os.write`` calls (a short write is continued, an error raised),
  so that the end of the last write that succeeded is always the end of a whole record
  (the ``Writer`` writes whole records per call) -- :attr:`FileSink.good_end`;
* :func:`close_damaged` cuts a file back to such a boundary and ends it with a Metadata
  record naming the fault, a DataEnd and a Footer without a summary (readers then scan
  the data section: ``mcap``, ``rosbags``, rosbag2's MCAP plugin and the tools of this
  package all do);
* :func:`repair` finds that boundary by walking the records of a file whose writer could
  not close it (a writer process killed), and closes the file the same way.

Where even the ~100 bytes of the ending do not fit, the file is left cut at the boundary:
the tools read it with ``--salvage``.
"""
from __future__ import annotations

import errno
import os
import resource
import struct

from mcap.opcode import Opcode

MCAP_MAGIC = b"\x89MCAP0\r\n"     # the MCAP file's first and last 8 bytes
OP_FOOTER, OP_METADATA, OP_DATA_END = Opcode.FOOTER, Opcode.METADATA, Opcode.DATA_END
_RECORD_HEAD = struct.Struct("<BQ")


class RecordingError(OSError):
    """A recording that could not go on (its file is closed as far as it could be); the
    message names the file, the cause and how to read what was written."""


def failure_cause(error, path: str | None = None) -> str:
    """An OSError as the cause of a failed recording, with what a user can do about it where
    it is known (`path`: the file or bag directory written): '[Errno 28] No space left on
    device: no space left where it is written (/data): free some or record elsewhere',
    '[Errno 17] File exists: /home/me/runs is a file, not a directory'."""
    if not (isinstance(error, OSError) and error.errno is not None):
        return str(error) or type(error).__name__
    cause = f"[Errno {error.errno}] {error.strerror}"
    hint = _hint(error.errno, path) if path else None
    return f"{cause}: {hint}" if hint else cause


def _hint(err: int, path: str) -> str | None:
    """What stops writing `path`, in a user's words, for the errno `err` (None: no more
    to say than its text)."""
    folder = os.path.dirname(os.path.abspath(path))
    if err in (errno.ENOTDIR, errno.EEXIST):
        blocker = _file_in_the_way(path)
        return None if blocker is None else f"{blocker} is a file, not a directory"
    if err in (errno.EACCES, errno.EPERM):
        missing = folder
        while not os.path.exists(missing) and os.path.dirname(missing) != missing:
            missing = os.path.dirname(missing)
        return f"{missing} is not writable"
    if err == errno.ENOENT:
        return f"no file can be made in {folder}" if os.path.isdir(folder) else \
            f"{folder} does not exist and cannot be made"
    return {errno.ENOSPC: f"no space left where it is written ({folder}): free some or "
                          "record elsewhere",
            errno.EDQUOT: f"the disk quota where it is written ({folder}) is used up",
            errno.EROFS: f"{folder} is on a read-only file system",
            errno.EFBIG: "the file reached the file-size limit of this process (ulimit -f: "
                         f"{_file_size_limit()})",
            errno.EISDIR: f"{path} is a directory",
            errno.EIO: "the disk reported an I/O error"}.get(err)


def _file_in_the_way(path: str) -> str | None:
    """The first of path's folders that is a file (makedirs then fails), or None."""
    parts = os.path.abspath(path).split(os.sep)
    for i in range(2, len(parts)):
        head = os.sep.join(parts[:i])
        if os.path.exists(head) and not os.path.isdir(head):
            return head
    return None


def _file_size_limit() -> str:
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    return "unlimited" if soft == resource.RLIM_INFINITY else f"{soft} bytes"


class FileSink:
    """A binary file written with unbuffered ``os.write`` calls (the stream of an mcap
    ``Writer``): :attr:`pos` is exact, and :attr:`good_end` is the end of the last write
    that went through whole (a record boundary, as the ``Writer`` writes whole records)."""

    def __init__(self, path: str):
        self.path = path
        self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self.pos = 0
        self.good_end = 0

    def write(self, data) -> int:
        view = memoryview(data)
        n = len(view)
        while view:
            w = os.write(self.fd, view)      # OSError (ENOSPC, EFBIG, EIO) propagates
            self.pos += w
            view = view[w:]
        self.good_end = self.pos
        return n

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        pass

    def fsync(self) -> None:
        try:
            os.fsync(self.fd)
        except OSError:
            pass

    @property
    def closed(self) -> bool:
        return self.fd < 0

    def close(self) -> None:
        if self.fd >= 0:
            fd, self.fd = self.fd, -1
            os.close(fd)


def _record(opcode: int, body: bytes) -> bytes:
    return _RECORD_HEAD.pack(opcode, len(body)) + body


def _string(s: str) -> bytes:
    b = s.encode("utf-8")
    return struct.pack("<I", len(b)) + b


def ending(note: dict | None = None) -> bytes:
    """The bytes that end a data section: a Metadata record ``starleth_recording_fault``
    (note: str -> str) if given, DataEnd (no CRC), a Footer without a summary, the magic."""
    out = b""
    if note:
        pairs = b"".join(_string(str(k)) + _string(str(v)) for k, v in note.items())
        out += _record(OP_METADATA, _string("starleth_recording_fault")
                       + struct.pack("<I", len(pairs)) + pairs)
    out += _record(OP_DATA_END, struct.pack("<I", 0))
    out += _record(OP_FOOTER, struct.pack("<QQI", 0, 0, 0))
    return out + MCAP_MAGIC


def close_damaged(fd: int, good_end: int, note: dict | None = None) -> bool:
    """Cut the file open as `fd` at `good_end` (a record boundary of its data section) and
    end it (:func:`ending`): True if the file is a complete MCAP file now, False if the
    ending did not fit (the file is then cut at good_end: readable with --salvage)."""
    for extra in (note, None):        # with the note, else without it (fewer bytes)
        try:
            os.ftruncate(fd, good_end)
            data = ending(extra)
            written = 0
            while written < len(data):
                written += os.pwrite(fd, data[written:], good_end + written)
            try:
                os.fsync(fd)
            except OSError:
                pass
            return True
        except OSError:
            continue
    try:
        os.ftruncate(fd, good_end)
    except OSError:
        pass
    return False


def last_boundary(path: str) -> tuple:
    """(offset, complete): the end of the last whole record of an MCAP file's data section
    (the start of its DataEnd if it has one), and whether the file already ends with a Footer and
    the magic (nothing to repair). (0, False) if it does not even start with the magic."""
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            return 0, False
        if size >= 2 * len(MCAP_MAGIC) + _RECORD_HEAD.size + 20:
            f.seek(size - len(MCAP_MAGIC))
            if f.read(len(MCAP_MAGIC)) == MCAP_MAGIC:
                f.seek(size - len(MCAP_MAGIC) - 20 - _RECORD_HEAD.size)
                op, length = _RECORD_HEAD.unpack(f.read(_RECORD_HEAD.size))
                if op == OP_FOOTER and length == 20:
                    return size, True
        pos = len(MCAP_MAGIC)
        while pos + _RECORD_HEAD.size <= size:
            f.seek(pos)
            op, length = _RECORD_HEAD.unpack(f.read(_RECORD_HEAD.size))
            end = pos + _RECORD_HEAD.size + length
            if op == 0 or op == OP_DATA_END or end > size:
                break
            pos = end
        return pos, False


def repair(path: str, note: dict | None = None) -> str:
    """Close an MCAP file its writer left cut (a writer process killed, a failed write):
    'complete' (it needed nothing), 'repaired' (cut at its last whole record and ended:
    a complete file), 'cut' (cut there, the ending did not fit: --salvage reads it) or
    'unreadable' (not even the MCAP magic)."""
    end, complete = last_boundary(path)
    if complete:
        return "complete"
    if end == 0:
        return "unreadable"
    fd = os.open(path, os.O_WRONLY)
    try:
        return "repaired" if close_damaged(fd, end, note) else "cut"
    finally:
        os.close(fd)
