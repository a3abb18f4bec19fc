"""The fall rule of the tools (starleth-sweep, starleth-eval, starleth-replay): a run fell
when the trunk tilted beyond a limit or sank below a height. The heights are StarlETH's
(tuned on its 0.415 m standing height) and scale with a robot's standing height (its spec's
``standing.height``), so that a Go1 standing at 0.27 m is not a fall from its first step."""
from __future__ import annotations

#: the standing height the tools' fall heights were chosen for: StarlETH's (robots/starleth.yaml)
REFERENCE_STANDING_HEIGHT = 0.415    # m


def fall_height(desc, starleth_height: float) -> float:
    """`starleth_height` [m] (a trunk height below which StarlETH has fallen) for the robot
    of the RobotDescription `desc`: in proportion to its standing height (unchanged for a
    robot without one, and exactly so for StarlETH)."""
    h = desc.standing_height
    return starleth_height if h is None else starleth_height * (h / REFERENCE_STANDING_HEIGHT)
