"""``starleth-precompile``: makes every kernel ready before the first run needs it, and
measures what a fresh clone's first run costs (``--cold``).

Three units, the C extension modules, built side by side (``--jobs``, default 2):

* ``physics``: the physics kernels (``starleth_sim.physics.kernels``, kernel_build);
* ``controller``: the controller's kernels (``starleth_controller._kernels``);
* ``ros-codec``: sim_node's command parsers (``starleth_sim.ros._cdr``);

the last two built by starleth_interface.c_extension, whose recipe the physics uses too. A
source checkout builds a module when it is missing or its sources changed (a unit whose
module is current takes a fraction of a second); an installed package has them from its
build. ``--cold`` builds every unit again into a temporary directory, which times a full
build without touching the modules in use, and prints each unit's seconds and the total:
the figures of a first run on a fresh clone.

While units build, one line (rewritten in place on a terminal; a line per unit started and
finished otherwise) says which, for how long, and about how long they take.
"""
from __future__ import annotations

import argparse
import io
import os
import shutil
import sys
import tempfile
import time
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

from starleth_interface import c_extension

from ..physics import kernels
from ..physics.kernels import build as kernel_build

#: (unit, rough cold seconds on a 2-core machine), the longest first
UNITS = (("physics", 2.0), ("controller", 0.7), ("ros-codec", 0.3))
ESTIMATE = dict(UNITS)
#: the units of the C extensions outside the physics (c_extension.EXTENSIONS)
MODULES = {"controller": "starleth_controller._kernels", "ros-codec": "starleth_sim.ros._cdr"}


def compile_unit(unit: str, cold_dir: str | None = None) -> None:
    """Makes the module of `unit` ready (see the module docstring); cold_dir: build it there
    instead (--cold). Raises ValueError for an unknown unit, BuildError when the build
    fails."""
    if unit == "physics":
        if cold_dir is not None:
            kernel_build.build(kernel_build.inplace_path(cold_dir))
        else:
            kernels.ensure_built()      # (the import above built a stale checkout's module)
    elif unit in MODULES:
        module = MODULES[unit]
        csrc, path = c_extension.csrc_of(module), c_extension.module_path(module)
        if cold_dir is not None:
            c_extension.build(csrc, os.path.join(cold_dir, os.path.basename(path)))
        else:
            c_extension.ensure_built(csrc, path, c_extension.EXTENSIONS[module],
                                     stream=io.StringIO())
    else:
        raise ValueError(f"unknown unit {unit!r}: one of {', '.join(u for u, _ in UNITS)}")


def _try_unit(unit: str, cold_dir: str | None) -> tuple[str, float, str | None]:
    """compile_unit: (unit, wall seconds, None or the error)."""
    t0 = time.perf_counter()
    error = None
    try:
        compile_unit(unit, cold_dir)
    except Exception as e:      # reported by precompile, which fails at the end
        error = f"{type(e).__name__}: {e}"
    return unit, time.perf_counter() - t0, error


class Progress:
    """The one line that says what compiles: rewritten on a terminal every half second;
    elsewhere one line per unit started and finished."""

    def __init__(self, stream, units, jobs):
        self.stream, self.tty = stream, hasattr(stream, "isatty") and stream.isatty()
        self.t0 = time.monotonic()
        self.pending = list(units)
        self.running: dict[str, float] = {}
        self.jobs = jobs
        self._shown = 0.0
        self.estimate = self._estimate(units, jobs)

    @staticmethod
    def _estimate(units, jobs):
        """Longest processing time first over `jobs` processes: the rough wall time."""
        load = [0.0] * max(1, jobs)
        for u in sorted(units, key=lambda u: -ESTIMATE.get(u, 1.0)):
            load[load.index(min(load))] += ESTIMATE.get(u, 1.0)
        return max(load)

    def _start_next(self, n):
        for _ in range(n):
            if self.pending:
                u = self.pending.pop(0)
                self.running[u] = time.monotonic()
                if not self.tty:
                    print(f"  compiling {u} ...", file=self.stream, flush=True)

    def begin(self):
        self._start_next(self.jobs)
        self.tick(force=True)

    def tick(self, force=False):
        if not self.tty:
            return
        now = time.monotonic()
        if not force and now - self._shown < 0.5:
            return
        self._shown = now
        parts = ", ".join(f"{u} {now - t:.0f} s" for u, t in self.running.items())
        self.stream.write(f"\r\033[Kcompiling kernels: {parts or 'done'} "
                          f"({now - self.t0:.0f} s of about {self.estimate:.0f} s)")
        self.stream.flush()

    def done(self, unit, seconds, error):
        self.running.pop(unit, None)
        if self.tty:
            self.stream.write("\r\033[K")
        print(f"  {unit:<11} {seconds:6.1f} s" + (f"  FAILED: {error}" if error else ""),
              file=self.stream, flush=True)
        self._start_next(1)
        self.tick(force=True)

    def end(self):
        if self.tty:
            self.stream.write("\r\033[K")
            self.stream.flush()


def precompile(jobs: int | None = None, units=None, stream=None, cold: bool = False
               ) -> tuple[float, list]:
    """Makes the modules of `units` (default: all) ready, `jobs` at a time (default 2; the
    builds run in compiler processes), printing each unit's time to `stream` (default
    stdout) and the progress line; cold: into a temporary directory (removed afterwards).
    Returns (wall time [s], the [(unit, error)] of the units that failed)."""
    stream = sys.stdout if stream is None else stream
    units = [u for u, _ in UNITS] if units is None else list(units)
    jobs = max(1, min(jobs or 2, len(units)))
    t0 = time.perf_counter()
    failed = []
    tmp = tempfile.mkdtemp(prefix="starleth-cold-") if cold else None
    try:
        progress = Progress(stream, units, jobs)
        progress.begin()
        with ThreadPoolExecutor(jobs) as pool:
            pending = {pool.submit(_try_unit, u, tmp) for u in units}
            while pending:
                finished, pending = wait(pending, timeout=0.25, return_when=FIRST_COMPLETED)
                if not finished:
                    progress.tick()
                for f in finished:
                    unit, seconds, error = f.result()
                    progress.done(unit, seconds, error)
                    if error:
                        failed.append((unit, error))
        progress.end()
    finally:
        if cold:
            shutil.rmtree(tmp, ignore_errors=True)
    return time.perf_counter() - t0, failed


def main(argv=None):
    ap = argparse.ArgumentParser(prog="starleth-precompile",
                                 description=__doc__.split("\n\n")[0].strip("`: "))
    ap.add_argument("--jobs", type=int, default=None, help="processes (default 2)")
    ap.add_argument("--cold", action="store_true",
                    help="measure a first run: build every unit into a temporary directory "
                         "(the modules in use are not touched) and print each unit's seconds "
                         "and the total")
    ap.add_argument("units", nargs="*",
                    help="units (default: all): " + ", ".join(u for u, _ in UNITS))
    args = ap.parse_args(argv)
    known = {u for u, _ in UNITS}
    bad = [u for u in args.units if u not in known]
    if bad:
        ap.error(f"unknown unit(s) {', '.join(bad)}; known: {', '.join(sorted(known))}")
    if args.jobs is not None and args.jobs < 1:
        ap.error("--jobs must be at least 1")
    what = "cold compilation (a fresh build)" if args.cold else "kernels ready"
    print(f"starleth-precompile: {what}, {args.jobs or 2} at a time", flush=True)
    wall, failed = precompile(args.jobs, args.units or None, cold=args.cold)
    if failed:
        print(f"{len(failed)} unit(s) failed in {wall:.1f} s: "
              f"{', '.join(u for u, _ in failed)}", file=sys.stderr, flush=True)
        return 1
    print(f"{'total' if args.cold else 'done in'} {wall:.1f} s wall", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
