"""The writer process of a :class:`~.process_writer.ProcessRecorder` (``python -m
starleth_sim.ros.recording --writer``): requests and message batches on stdin, answers on
stdout, the file written here."""
from __future__ import annotations

import os
import pickle
import signal
import sys

from .factory import open_file_recorder
from .mcap_sink import RecordingError, failure_cause
from .process_writer import MESSAGE_HEAD, MESSAGES
from .schemas import register_msg_text


def background_scheduling():
    """The writer process under SCHED_BATCH (Linux; elsewhere nothing): woken by a hand-over,
    it does not preempt the simulator that wrote it (which then would wait for the whole
    batch to be written before it goes on: 1-1.5 ms every hand-over on a busy 2-CPU machine);
    it still gets its fair share of the CPU."""
    try:
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    except (AttributeError, OSError):   # pragma: no cover - not Linux
        pass


def main():
    """Serve a ProcessRecorder on stdin / stdout; finalise the file on 'close' or when stdin
    ends. A failed write (the recorder has closed the file as far as it could) is reported
    as an answer (False, RecordingError) that nobody asked for, and the child exits: the
    parent finds its pipe closed and reads the report."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)      # the parent closes the recording
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    background_scheduling()
    server = _WriterServer(sys.stdin.buffer, sys.stdout.buffer)
    while server.serve_one():
        pass
    if server.rec is not None and not server.finished:
        try:
            server.rec.close()
        except RecordingError:
            pass


class _WriterServer:
    """One recording served over a pipe: `serve_one` reads and answers one request or
    message batch."""

    def __init__(self, inp, out):
        self.inp, self.out = inp, out
        #: finished: the file closed on request, or a failure answered (nothing to close)
        self.rec, self.names, self.finished = None, [], False

    def answer(self, ok, value):
        data = pickle.dumps((ok, value))
        self.out.write(len(data).to_bytes(4, "little") + data)
        self.out.flush()

    def serve_one(self) -> bool:
        """Reads one frame (kind byte, size, payload) and handles it; False once the input
        ended, the file was closed on request or a write failed (answered)."""
        h = self.inp.read(5)
        if len(h) < 5:
            return False
        kind, size = h[:1], int.from_bytes(h[1:], "little")
        payload = self.inp.read(size)
        if len(payload) < size:
            return False
        if kind == MESSAGES:
            return self.write_messages(payload)
        return self.handle(pickle.loads(payload))

    def write_messages(self, payload) -> bool:
        """A batch of (topic index, stamp, CDR bytes) messages into the file."""
        o = 0
        try:
            while o < len(payload):
                i, t, n = MESSAGE_HEAD.unpack_from(payload, o)
                o += MESSAGE_HEAD.size
                self.rec.write(self.names[i], payload[o:o + n], t)
                o += n
        except RecordingError as e:
            self.finished = True
            self.answer(False, e)
            return False
        return True

    def handle(self, request) -> bool:
        """One request (op, *args), answered (True, value) or (False, error)."""
        op, args = request[0], request[1:]
        try:
            if op == "close":
                self.rec.close(metadata=args[0])
                self.finished = True
                self.answer(True, self.rec.message_count)
                return False
            self.answer(True, self.request_value(op, args))
        except RecordingError as e:
            self.finished = True
            self.answer(False, e)
            return False
        except Exception as e:
            if op == "open" and isinstance(e, OSError):   # one line: file and cause
                e = RecordingError(f"{args[0].uri}: {failure_cause(e, args[0].uri)}"
                                   if e.errno is not None
                                   else str(e))           # (a message naming the file)
            self.answer(False, e)
        return True

    def request_value(self, op, args):
        """The answer's value of a request other than 'close'."""
        if op == "open":
            self.rec = open_file_recorder(args[0])
            return None
        if op == "add_topic":
            topic, typ, qos, type_hash, fallback_text = args
            if fallback_text is not None:
                register_msg_text(typ, fallback_text)
            value = self.rec.add_topic(topic, typ, qos, type_hash)
            if topic not in self.names:
                self.names.append(topic)
            return value
        if op == "add_metadata":
            return self.rec.add_metadata(*args)
        if op == "add_attachment":
            return self.rec.add_attachment(*args)
        if op == "counts":
            return self.rec.counts()
        raise ValueError(f"the recording process has no request {op!r}")
