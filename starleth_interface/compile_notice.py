"""Saying that kernels compile, and telling compilation from silence.

A first run after an install (or after an edit) compiles numba kernels for seconds, in which a
process prints nothing of its own. `CompileNotice` wraps such a block: once numba compiles
in it (numba's "numba:compile" events; loading from numba's cache is no compilation) and the
block has run for `after` seconds, it logs that it is compiling (what, and a rough
estimate), then a line every `every` seconds with the time so far, and at the end how long
it took; a block that only loads the cache says nothing. A tool that waits for a process
to come up (starleth-demo, the node tests) reads those lines from the process's log
(`LogWatch`) and counts its start-up timeout from the last of them: compilation is progress,
not silence.

``STARLETH_TEST_SLOW_COMPILE=<seconds>`` makes every CompileNotice block last that much longer
(a stand-in for a slow first compile, for the tests of the above).
"""
from __future__ import annotations

import os
import re
import threading
import time

#: what a compile line says (the tools match it in a process's log)
COMPILE_MARK = "compiling"
_MARK = re.compile(r"\b(still )?compiling\b|\bcompiled in\b")
SLOW_COMPILE_ENV = "STARLETH_TEST_SLOW_COMPILE"


class CompileNotice:
    """with CompileNotice("the controller's kernels", log.info, estimate=10): warm_up()"""

    def __init__(self, what: str, log=print, estimate: float | None = None,
                 after: float = 0.5, every: float = 5.0):
        self.what, self.log, self.estimate = what, log, estimate
        self.after, self.every = after, every
        self.announced = False
        self.seconds = 0.0
        self._done = threading.Event()
        self._compiling = threading.Event()
        self._thread = None
        self._listener = None
        self._unregister = None
        self._t0 = 0.0

    def _listen(self):
        """Sets _compiling at numba's first compile event (none without numba)."""
        try:
            from numba.core import event  # deferred: numba (0.6 s) only once a block runs
        except ImportError:     # pragma: no cover - numba is a dependency
            return
        compiling = self._compiling

        class Listener(event.Listener):
            def on_start(self, _event):
                compiling.set()

            def on_end(self, ev):
                pass
        self._listener = Listener()
        event.register("numba:compile", self._listener)
        self._unregister = lambda: event.unregister("numba:compile", self._listener)

    def _unlisten(self):
        if self._listener is not None:
            self._unregister()
            self._listener = None

    def _about(self) -> str:
        return f", about {self.estimate:.0f} s" if self.estimate else ""

    def _watch(self):
        if self._done.wait(self.after):
            return
        while not self._compiling.is_set():     # (loading from the cache: nothing to say)
            if self._done.wait(0.05):
                return
        self.announced = True
        self.log(f"{COMPILE_MARK} {self.what} (numba: the first run after an install or an "
                 f"edit compiles, later runs load the cache{self._about()})")
        while not self._done.wait(self.every):
            self.log(f"still {COMPILE_MARK} {self.what}: "
                     f"{time.monotonic() - self._t0:.0f} s{self._about()}")

    def __enter__(self):
        self._t0 = time.monotonic()
        self._listen()
        self._thread = threading.Thread(target=self._watch, name="compile-notice",
                                        daemon=True)
        self._thread.start()
        slow = os.environ.get(SLOW_COMPILE_ENV)
        if slow:                # the stand-in compiles
            self._compiling.set()
            time.sleep(float(slow))
        return self

    def compiling(self):
        """Marks the block as compiling (code that compiles without numba's events)."""
        self._compiling.set()

    def __exit__(self, *exc):
        self._done.set()
        self._thread.join()
        self._unlisten()
        self.seconds = time.monotonic() - self._t0
        if self.announced:
            self.log(f"{self.what}: compiled in {self.seconds:.1f} s"
                     + (" (failed)" if exc[0] is not None else ""))
        return False


def shows_compiling(text: str) -> bool:
    """Whether text holds a CompileNotice line."""
    return _MARK.search(text) is not None


class LogWatch:
    """Follows the log files of processes that start: `progress()` is True when a compile
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
    or after the last compile line of the watched logs, whichever is later."""

    def __init__(self, timeout: float, log_paths=()):
        self.timeout = timeout
        self.watch = LogWatch(log_paths)
        self._end = time.monotonic() + timeout

    def expired(self) -> bool:
        if self.watch.progress():
            self._end = time.monotonic() + self.timeout
        return time.monotonic() > self._end
