"""``starleth-bench --terrain``: the cost of the terrain's contact query, beside the flat
ground, in one process with interleaved rounds.

The robot stands under the joint PD posture hold (HmJ by default) on three grounds: the
plane alone; 50 boxes (a 7 x 7 grid of 0.3 m tiles 1 cm high under and around the robot,
and a step 2 m away), so each foot is near several boxes; and a 256 x 256 heightfield of
2 cm cells, flat at 1 cm, under the robot. On the tiles and the heightfield the robot
stands as on the plane (flat surfaces 1 cm up): the contact query is the only new cost.
Rounds of `steps` control steps run in turn on the three; the figure per ground is the
median of its rounds' times per physics step, and the ratio to the plane's.
"""
from __future__ import annotations

import numpy as np

from ...physics.config import load_preset
from ...physics.posture import PostureHold
from ...physics.simulator import Simulator
from .timing import timed_steps

TILE = 0.3            # m
TILE_HEIGHT = 0.01    # m
GRID_POINTS = 256
GRID_CELL = 0.02      # m


def terrains():
    """{name: the terrain section} of the three grounds."""
    tiles = [{"centre": [(i - 3) * TILE, (j - 3) * TILE, 0.5 * TILE_HEIGHT],
              "size": [TILE, TILE, TILE_HEIGHT]} for i in range(7) for j in range(7)]
    tiles.append({"centre": [2.0, 0.0, 0.05], "size": [0.3, 1.0, 0.1]})
    half = 0.5 * (GRID_POINTS - 1) * GRID_CELL
    grid = {"origin": [-half, -half], "cell": GRID_CELL,
            "heights": np.full((GRID_POINTS, GRID_POINTS), TILE_HEIGHT)}
    return {"flat": {}, "50 boxes": {"boxes": tiles},
            f"{GRID_POINTS}x{GRID_POINTS} heightfield": {"heightfield": grid}}


def terrain_rounds(preset="HmJ", rounds=21, steps=200):
    """{ground: median µs per physics step over the rounds}, interleaved."""
    return {name: float(np.median(t))
            for name, t in terrain_times(preset, rounds, steps).items()}


def terrain_times(preset="HmJ", rounds=21, steps=200):
    """{ground: µs per physics step of each round}, the grounds' rounds interleaved."""
    sims = {}
    for name, terrain in terrains().items():
        cfg = load_preset(preset)
        cfg.terrain.boxes = terrain.get("boxes", [])
        cfg.terrain.heightfield = terrain.get("heightfield")
        sim = Simulator(cfg.validate(f"{preset} + {name}"))
        hold = PostureHold(sim.joint_positions())
        for _ in range(50):       # warm-up, and settled onto the surface
            sim.step(hold.torque(sim))
        sims[name] = (sim, hold)
    times = {name: [] for name in sims}
    for _ in range(rounds):
        for name, (sim, hold) in sims.items():
            wall, _ = timed_steps(sim, steps, hold)
            times[name].append(1e6 * wall / (steps * sim.config.steps_per_control))
    return times


def print_terrain_rounds(preset="HmJ", rounds=21, steps=200):
    times = terrain_times(preset, rounds, steps)
    median = {name: float(np.median(t)) for name, t in times.items()}
    fastest = {name: float(np.min(t)) for name, t in times.items()}
    print(f"{preset} standing, {rounds} interleaved rounds of {steps} control steps: time per "
          "physics step, the median round and the fastest (the least disturbed by other "
          "processes)")
    print(f"{'ground':24s} {'median':>8s} {'vs flat':>8s} {'fastest':>8s} {'vs flat':>8s}")
    for name in times:
        print(f"{name:24s} {median[name]:8.2f} {100 * (median[name] / median['flat'] - 1):+7.1f}%"
              f" {fastest[name]:8.2f} {100 * (fastest[name] / fastest['flat'] - 1):+7.1f}%")
    return 0
