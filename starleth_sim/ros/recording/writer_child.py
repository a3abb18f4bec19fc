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
    inp, out = sys.stdin.buffer, sys.stdout.buffer
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
        if kind == MESSAGES:
            o = 0
            try:
                while o < size:
                    i, t, n = MESSAGE_HEAD.unpack_from(payload, o)
                    o += MESSAGE_HEAD.size
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
                rec = open_file_recorder(args[0])
                value = None
            elif op == "add_topic":
                topic, typ, qos, type_hash, fallback_text = args
                if fallback_text is not None:
                    register_msg_text(typ, fallback_text)
                value = rec.add_topic(topic, typ, qos, type_hash)
                if topic not in names:
                    names.append(topic)
            elif op == "close":
                rec.close(metadata=args[0])
                answer(True, rec.message_count)
                return
            elif op == "add_metadata":
                value = rec.add_metadata(*args)
            elif op == "add_attachment":
                value = rec.add_attachment(*args)
            elif op == "counts":
                value = rec.counts()
            else:
                raise ValueError(f"the recording process has no request {op!r}")
            answer(True, value)
        except RecordingError as e:
            answer(False, e)
            return
        except Exception as e:
            if op == "open" and isinstance(e, OSError):   # one line: file and cause
                e = RecordingError(f"{args[0].uri}: {failure_cause(e, args[0].uri)}"
                                   if e.errno is not None
                                   else str(e))           # (a message naming the file)
            answer(False, e)
    if rec is not None:
        try:
            rec.close()
        except RecordingError:
            pass
