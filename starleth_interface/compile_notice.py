"""Telling a build from silence: a start-up timeout that counts only silence.

A source checkout builds its C extensions on first use (the physics kernels, the
controller's kernels, sim_node's command parsers: a few seconds, once per change of their
sources), and says so in the process's log (c_extension.ensure_built): "compiling ..." when
it starts, "... compiled in" when done. A tool that waits for a process to come up
(starleth-demo, the node tests) reads those lines from the process's log (`LogWatch`) and
counts its start-up timeout from the last of them (`Deadline`): a build is progress, not
silence.
"""
from __future__ import annotations

import re
import time

_MARK = re.compile(r"\b(still )?compiling\b|\bcompiled in\b")


def shows_compiling(text: str) -> bool:
    """Whether text holds a build line (the module docstring)."""
    return _MARK.search(text) is not None


class LogWatch:
    """Follows the log files of processes that start: `progress()` is True when a build
    line was written since the last call (the last such line in `last`)."""

    def __init__(self, paths):
        self.paths = list(paths)
        self._offsets = {p: 0 for p in self.paths}
        self.last = ""

    def progress(self) -> bool:
        seen = False
        for p in self.paths:
            try:
                with open(p, "rb") as f:
                    f.seek(self._offsets[p])
                    chunk = f.read()
            except OSError:
                continue
            if not chunk:
                continue
            # only whole lines: a line being written is read again next time
            end = chunk.rfind(b"\n") + 1
            self._offsets[p] += end
            for line in chunk[:end].decode("utf-8", "replace").splitlines():
                if shows_compiling(line):
                    seen = True
                    self.last = line.strip()
        return seen


class Deadline:
    """A start-up timeout that counts silence: it expires `timeout` seconds after it was made
    or after the last build line of the watched logs, whichever is later."""

    def __init__(self, timeout: float, log_paths=()):
        self.timeout = timeout
        self.watch = LogWatch(log_paths)
        self._end = time.monotonic() + timeout

    def expired(self) -> bool:
        if self.watch.progress():
            self._end = time.monotonic() + self.timeout
        return time.monotonic() > self._end
