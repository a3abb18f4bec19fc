"""``starleth-demo --drop``: the headless drop test (no ROS). StarlETH (or ``--robot``)
falls from `height` onto flat ground under a joint PD posture hold (physics.posture.PostureHold),
settles, and a summary is printed: speed, trunk height, peak impact, per-foot normal force
(their sum against the weight), solver iterations. Exit status 0 when the feet carry the
weight to 1 % and every step converged."""
from __future__ import annotations

import time

import numpy as np

from ...physics.posture import PostureHold
from ...physics.simulator import Simulator


def drop_test(preset="HmJ", height=0.1, seconds=5.0, robot="starleth"):
    sim = Simulator.from_preset(preset, robot=robot)
    q = sim.q
    q[2] += height
    sim.reset(q)
    hold = PostureHold(sim.joint_positions())
    n = int(round(seconds / sim.control_period))
    iters, wall, peak = [], 0.0, 0.0
    for _ in range(n):
        tau = hold.torque(sim)
        t0 = time.perf_counter()
        d = sim.step(tau)
        wall += time.perf_counter() - t0
        iters.append(d.iterations / sim.config.steps_per_control)
        peak = max(peak, sum(sim.contact(f).force[2] for f in sim.description.foot_names))
    return sim, np.array(iters), wall, n, peak


def drop_main(args) -> int:
    sim, iters, wall, n, peak = drop_test(args.preset, args.height, args.seconds, args.robot)
    steps = n * sim.config.steps_per_control
    weight = sim.description.total_mass * 9.81
    label = "StarlETH" if args.robot == "starleth" else args.robot
    print(f"{label} drop test: {args.preset}, dropped from {args.height:g} m, "
          f"{args.seconds:g} s simulated, joint PD posture hold")
    print(f"  speed          {steps / wall:8.0f} physics steps/s, real-time factor "
          f"{n * sim.control_period / wall:.1f}")
    print(f"  trunk height   {sim.q[2]:.4f} m (nominal standing "
          f"{sim.description.standing_height} m)")
    print(f"  peak impact    {peak:8.1f} N total normal force ({peak / weight:.1f} x weight)")
    print("  foot normal forces at the end [N]:")
    total = 0.0
    for f in sim.description.foot_names:
        fz = sim.contact(f).force[2]
        total += fz
        print(f"    {f:8s} {fz:8.2f}")
    print(f"    {'sum':8s} {total:8.2f}   (weight {weight:.2f})")
    d = sim.diagnostics
    print(f"  prox iterations per step: mean {iters.mean():.2f}, max {iters.max():.0f}; "
          f"non-converged steps: {d.nonconverged_steps}")
    ok = abs(total - weight) < 0.01 * weight and d.nonconverged_steps == 0
    print("  result: settled, weight carried by the feet" if ok else
          "  result: NOT settled")
    return 0 if ok else 1
