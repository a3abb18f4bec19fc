"""``starleth-bench``: simulation speed per configuration, beside the paper's Table 1.

The robot stands under the joint PD posture hold; only ``Simulator.step`` is timed. Figures
are physics steps per second (the paper's "evaluations per second") and the real-time factor
(simulated time / wall time). A second, profiled run breaks one step down like Fig. 7.
All configurations run in the same process, one after the other, so their ratios are
comparable on a shared machine.
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from ..physics.config import ConfigError, load_preset
from ..physics.posture import PostureHold
from ..physics.simulator import Simulator
from ..physics.stepper import PHASES

from ..physics.config import PRESETS as DEFAULT_PRESETS   # the paper's Table 1


def measure(preset: str, seconds: float, repeats: int = 3):
    """(steps/s samples, rtf samples, mean prox iterations per step) for `seconds` of
    simulated standing, repeated."""
    rates, rtfs, iters = [], [], []
    for _ in range(repeats):
        sim = Simulator.from_preset(preset)
        hold = PostureHold(sim.joint_positions())
        n = int(round(seconds / sim.control_period))
        sim.step(hold.torque(sim))  # warm-up (numba dispatch, caches)
        wall = 0.0
        it = 0
        for _ in range(n):
            tau = hold.torque(sim)
            t0 = time.perf_counter()
            d = sim.step(tau)
            wall += time.perf_counter() - t0
            it += d.iterations
        steps = n * sim.config.steps_per_control
        rates.append(steps / wall)
        rtfs.append(n * sim.control_period / wall)
        iters.append(it / steps)
    return np.array(rates), np.array(rtfs), float(np.mean(iters))


def breakdown(preset: str, seconds: float):
    """Mean time per physics step and phase [µs] (profiled run, includes timer overhead)."""
    from ..physics.stepper import StepperStats
    sim = Simulator.from_preset(preset, profile=True)
    hold = PostureHold(sim.joint_positions())
    for _ in range(20):  # warm-up: first calls of the profiled path load compiled code
        sim.step(hold.torque(sim))
    sim.reset()
    sim.stepper.stats = StepperStats()
    n = int(round(seconds / sim.control_period))
    for _ in range(n):
        sim.step(hold.torque(sim))
    steps = sim.stepper.stats.steps
    return {k: 1e6 * v / steps for k, v in zip(PHASES, sim.stepper.stats.timings)}


def main(argv=None):
    ap = argparse.ArgumentParser(prog="starleth-bench", description=__doc__.split("\n")[0])
    ap.add_argument("presets", nargs="*", default=list(DEFAULT_PRESETS),
                    help="configurations (default: %(default)s)")
    ap.add_argument("--seconds", type=float, default=5.0, help="simulated seconds per run")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    try:
        configs = {p: load_preset(p) for p in args.presets}
    except ConfigError as e:
        ap.error(str(e))

    print(f"StarlETH standing under a joint PD hold, {args.seconds:g} s simulated x "
          f"{args.repeats} runs per configuration; Python {sys.version.split()[0]}")
    print(f"{'config':7s} {'steps/s':>16s} {'paper':>7s} {'ratio':>6s} {'RTF':>7s} "
          f"{'paper':>6s} {'iter/step':>9s}")
    for p in args.presets:
        cfg = configs[p]
        rates, rtfs, it = measure(p, args.seconds, args.repeats)
        paper = cfg.paper.get("steps_per_second")
        prtf = cfg.paper.get("realtime_factor")
        ratio = rates.mean() / paper if paper else float("nan")
        print(f"{p:7s} {rates.mean():9.0f} ± {rates.std():4.0f} {paper or '-':>7} "
              f"{ratio:6.2f} {rtfs.mean():7.1f} {prtf or '-':>6} {it:9.2f}", flush=True)
    print("\nPer-step time by phase (Fig. 7), µs, profiled run:")
    print(f"{'config':7s} " + " ".join(f"{k:>9s}" for k in PHASES) + f" {'total':>9s}")
    for p in args.presets:
        b = breakdown(p, min(args.seconds, 2.0))
        print(f"{p:7s} " + " ".join(f"{b[k]:9.2f}" for k in PHASES) +
              f" {sum(b.values()):9.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
