"""One headless run with the controller in the loop (Simulator + StarlethController in one
process, no ROS): stand, or stand then trot, optionally pushed or perturbed, with the
measurements of starleth-eval's report. The one run of ``starleth-eval``'s tasks and of
``starleth-sweep``'s grid.
"""
from __future__ import annotations

import math
import time

import numpy as np

from starleth_controller import Command, RobotState, StarlethController
from starleth_controller.robot_params import trot_speed

from ...physics.simulator import Simulator
from ...physics.stepper import SimulationError
from ...ros.tf import base_link

STAND_BEFORE_TROT = 1.0  # s
GAIT_PERIOD = 0.8      # s (1.25 Hz)


def run_gait(preset, gait, seconds, profile=False, record_lf=False, push=None,
             stand_time=STAND_BEFORE_TROT, stop_on_nonconvergence=False, speed=None,
             perturb=None, robot="starleth", **overrides):
    """Stand (and trot at `speed` after `stand_time` s if gait == 'trot') for `seconds`;
    `robot` (a library name, a spec or URDF path) under the controller with its parameters
    scaled to it, speed default 0.3 m/s · √λ (robot_params.trot_speed);
    push = (time [s], force (world) [N], duration [s]) on the base; perturb(sim) may change
    the initial state. Returns per-step wall times of sim.step, iterations, and the
    measurements of the report. The one headless run of starleth-eval and starleth-sweep."""
    sim = Simulator.from_preset(preset, profile=profile, robot=robot, **overrides)
    if perturb is not None:
        perturb(sim)
    ctrl = StarlethController(robot=robot)
    speed = trot_speed(ctrl.model.scale) if speed is None else speed
    n = int(round(seconds / sim.control_period))
    run = _GaitMeasures(sim, n, record_lf, push is not None)
    for k in range(n):
        trot = gait == "trot" and k * sim.control_period >= stand_time
        cmd = Command(mode="trot" if trot else "stand", forward=speed if trot else 0.0)
        tau = ctrl.update(RobotState.from_simulator(sim), cmd)
        if push is not None and k == int(round(push[0] / sim.control_period)):
            sim.apply_wrench(base_link(sim.description.urdf_xml), push[1], duration=push[2])
        t0 = time.perf_counter()
        try:
            d = sim.step(tau)
        except SimulationError as e:  # reported, the run ends here
            run.error = str(e)
            break
        run.after_step(k, d, time.perf_counter() - t0)
        if stop_on_nonconvergence and not d.converged:
            break
    out = run.result(preset=preset, gait=gait, seconds=seconds, speed=speed, robot=robot)
    if profile:
        st = sim.stepper.stats
        out["phases_us"] = (1e6 * st.timings / max(st.steps, 1)).tolist()
    return out


class _GaitMeasures:
    """What run_gait measures after each control step of `sim` (n at most)."""

    def __init__(self, sim, n, record_lf, pushed):
        self.sim, self.record_lf, self.pushed = sim, record_lf, pushed
        self.feet = [sim.contact_names.index(f) for f in sim.description.foot_names]
        self.foot_names = set(sim.description.foot_names)
        self.x0 = float(sim.base_state()["position"][0])
        self.wall, self.iters = np.zeros(n), np.zeros(n, dtype=np.int64)
        self.lf_force, self.lf_t = [], []
        self.foot_gap, self.drift_t, self.drift_g = [], [], []
        self.foot_penetration = np.zeros(n)   # deepest foot below the ground after a step [m]
        self.min_height, self.max_tilt = 1.0, 0.0
        self.knee_trunk = set()
        self.error, self.k_done = None, 0

    def after_step(self, k, d, wall):
        sim, feet = self.sim, self.feet
        self.wall[k], self.iters[k], self.k_done = wall, d.iterations, k + 1
        gaps = sim.gaps()[feet]
        self.foot_penetration[k] = max(0.0, -float(gaps.min()))
        b = sim.base_state()
        self.min_height = min(self.min_height, float(b["position"][2]))
        x, y, z, w = b["orientation_xyzw"]
        self.max_tilt = max(self.max_tilt, math.acos(max(-1.0, min(1.0, 1 - 2 * (x * x + y * y)))))
        if self.record_lf:
            self.lf_t.append(sim.t)
            self.lf_force.append(float(sim.contacts[feet[0]].force[2]))
        if self.pushed:
            self.knee_trunk.update(c.name for c in sim.contacts
                                   if c.active and c.name not in self.foot_names)
        if k % 10 == 0:
            act = np.array([sim.contacts[i].active for i in feet])
            if act.any():
                self.foot_gap.append((sim.t, float(gaps[act].mean()), float(gaps[act].min())))
            if sim.coords.n_bilateral:
                self.drift_t.append(sim.t)
                self.drift_g.append(float(np.abs(sim.bilateral_violation()).max()))

    def result(self, **run):
        sim, k = self.sim, self.k_done
        out = dict(**run, steps=k, physics_steps=k * sim.config.steps_per_control,
                   error=self.error,
                   nonfinite=(self.error is not None and "non-finite" in self.error)
                   or not np.all(np.isfinite(sim.q)),
                   wall=self.wall[:k].tolist(), iterations=self.iters[:k].tolist(),
                   nonconverged=int(sim.diagnostics.nonconverged_steps),
                   min_height=self.min_height, max_tilt=self.max_tilt,
                   knee_trunk_contacts=sorted(self.knee_trunk),
                   distance=float(sim.base_state()["position"][0]) - self.x0,
                   control_period=sim.control_period,
                   steps_per_control=sim.config.steps_per_control,
                   foot_gap=self.foot_gap, drift_t=self.drift_t, drift_g=self.drift_g,
                   foot_penetration=self.foot_penetration[:k].tolist(),
                   loaded_contacts_opened=int(sim.diagnostics.loaded_contacts_opened_total),
                   projections=int(sim.stepper.stats.projections))
        if self.record_lf:
            out["lf_t"], out["lf_force"] = self.lf_t, self.lf_force
        return out
