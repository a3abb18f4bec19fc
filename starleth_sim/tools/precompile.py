"""``starleth-precompile``: fills numba's on-disk cache of the kernels, in parallel processes.

Every physics kernel is compiled with ``cache=True`` (``physics.kernel_cache``): the first
process that calls a kernel compiles it (a few minutes for all of them on a 2-core machine)
and writes the machine code next to its source; every later process loads it in well under a
second. Processes started side by side before the cache is filled (two pytest workers, the
sim and controller nodes of a first ``make demo``, the pool of a sweep) each compile the same
kernels at the same time. This tool compiles them once, spreading disjoint work over
``--jobs`` processes, so that those processes only load.

The work units are the public entry points that reach distinct kernels: the one-kernel step
of each family (tree hard contacts: HmJ; forest: HEJD and the other extended / maximal sets;
compliant: Cm), the phase-by-phase step that ``profile=True`` runs, the step prepared ahead
(``Simulator.prepare``, sim_node's path), the controller's kernels (one closed-loop control
period, and controller_node's reading of a state) and sim_node's command parsers. A unit
whose kernels are already cached takes a fraction of a second, so running the tool again is
cheap.
"""
from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
import time

from ..physics.config import PRESETS

#: the units that compile most, with their rough cold compile time on a 2-core machine [s]
_LONG_UNITS = (
    ("step:HmJ", 75.0),
    ("step:HEJD", 55.0),
    ("profile:HEJD", 40.0),
    ("profile:HmJ", 30.0),
    ("prepare:HmJ", 30.0),
    ("controller", 15.0),
    ("step:Cm", 7.0),
    ("profile:Cm", 5.0),
    ("ros-codec", 3.0),
)
#: every (unit, rough cold compile time [s]), the longest first, so that the processes
#: finish close together (longest processing time first); the step, profiled step and
#: prepared step of the other presets mostly load what the long units compiled (≈ 1 s)
UNITS = _LONG_UNITS + tuple(
    (unit, 1.0) for unit in (f"{kind}:{p}" for kind in ("step", "profile", "prepare")
                             for p in PRESETS)
    if unit not in dict(_LONG_UNITS))


def compile_unit(unit: str) -> None:
    """Runs the entry point of `unit` ("step:PRESET", "profile:PRESET", "prepare:PRESET",
    "controller" or "ros-codec") long enough to call each of its kernels once."""
    kind, _, preset = unit.partition(":")
    if kind == "controller":
        from .evaluation import run_gait
        run_gait("HmJ", "trot", 0.01, stand_time=0.0)
        _controller_node_state()
    elif kind == "ros-codec":
        from ..ros.cdr import CommandDecoder
        CommandDecoder(["joint"])          # compiles its parsers on construction
    elif kind in ("step", "profile", "prepare") and preset in PRESETS:
        from ..physics.posture import PostureHold
        from ..physics.simulator import Simulator
        sim = Simulator.from_preset(preset, profile=kind == "profile")
        hold = PostureHold(sim.joint_positions())
        for _ in range(2):
            if kind == "prepare":       # the torque-independent part ahead (sim_node's path)
                sim.prepare()
            sim.step(hold.torque(sim))
    else:
        raise ValueError(f"unknown unit {unit!r}: 'step:PRESET', 'profile:PRESET', "
                         "'prepare:PRESET', 'controller' or 'ros-codec'")


def _controller_node_state() -> None:
    """controller_node's reading of a state (kernels.node_state) with the argument types it
    passes (float64 views of one bundle, int64 permutation, bool contact flags): else the
    node compiles it on its first state."""
    import numpy as np
    from starleth_controller.kernels import node_state
    from starleth_interface import state_bundle as sb
    v = np.zeros(sb.SIZE)
    node_state(v[sb.SLICES["q"]], v[sb.SLICES["u"]], np.arange(12, dtype=np.int64),
               v[sb.BASE], v[sb.SLICES["force"]].reshape(4, 3), 5.0, np.empty(12),
               np.empty(12), np.empty(3), np.empty(4), np.empty(3), np.empty(3), np.eye(3),
               np.empty(4, dtype=bool))


def _try_unit(unit: str) -> tuple[str, float, str | None]:
    """compile_unit in a worker: (unit, wall seconds, None), or (unit, seconds, the error)
    when its entry point raised (the other units go on)."""
    t0 = time.perf_counter()
    error = None
    try:
        compile_unit(unit)
    except Exception as e:      # reported by precompile, which fails at the end
        error = f"{type(e).__name__}: {e}"
    return unit, time.perf_counter() - t0, error


def precompile(jobs: int | None = None, units=None, stream=None) -> tuple[float, list]:
    """Compiles (or loads) the kernels of `units` (default: all) in `jobs` processes (default:
    the CPU count, at most 4), printing each unit's time to `stream` (default stdout);
    returns (wall time [s], the [(unit, error)] of the units that failed)."""
    stream = sys.stdout if stream is None else stream
    units = [u for u, _ in UNITS] if units is None else list(units)
    jobs = max(1, min(jobs or min(os.cpu_count() or 1, 4), len(units)))
    t0 = time.perf_counter()
    failed = []

    def report(done):
        for unit, seconds, error in done:
            print(f"  {unit:<14} {seconds:6.1f} s" + (f"  FAILED: {error}" if error else ""),
                  file=stream, flush=True)
            if error:
                failed.append((unit, error))

    if jobs == 1:
        report(map(_try_unit, units))
    else:
        # spawn: a fresh interpreter per worker (no forked numba or threading state)
        with multiprocessing.get_context("spawn").Pool(jobs) as pool:
            report(pool.imap_unordered(_try_unit, units))
    return time.perf_counter() - t0, failed


def main(argv=None):
    ap = argparse.ArgumentParser(prog="starleth-precompile", description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=None,
                    help="processes (default: the CPU count, at most 4)")
    ap.add_argument("units", nargs="*",
                    help="units to compile (default: all): " + ", ".join(u for u, _ in UNITS))
    args = ap.parse_args(argv)
    known = {u for u, _ in UNITS}
    bad = [u for u in args.units if u not in known]
    if bad:
        ap.error(f"unknown unit(s) {', '.join(bad)}; known: {', '.join(sorted(known))}")
    if args.jobs is not None and args.jobs < 1:
        ap.error("--jobs must be at least 1")
    print("starleth-precompile: numba kernels into the on-disk cache", flush=True)
    wall, failed = precompile(args.jobs, args.units or None)
    if failed:
        print(f"{len(failed)} unit(s) failed in {wall:.1f} s: "
              f"{', '.join(u for u, _ in failed)}", file=sys.stderr, flush=True)
        return 1
    print(f"done in {wall:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
