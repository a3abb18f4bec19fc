"""The solver figures of a control step (`Diagnostics`): made from the figures of its physics
steps (the kernels' TreeStepResults), continuing the cumulative counts of the last control
step. No ROS anywhere in here."""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from types import MappingProxyType
from typing import Mapping

from . import prox

#: Diagnostics.timings when not profiling (one shared, read-only, empty mapping)
NO_TIMINGS = MappingProxyType({})
#: Diagnostics.status of each prox.STATUS_*
STATUS_NAMES = {prox.STATUS_CONVERGED: "converged", prox.STATUS_MAX_ITER: "max_iterations",
                prox.STATUS_NONFINITE: "non_finite", prox.STATUS_STALLED: "stalled"}
_CONVERGED = prox.STATUS_CONVERGED
#: the cumulative counts before the first step: (physics_steps, nonconverged_steps,
#: loaded_contacts_opened_total)
NO_TOTALS = (0, 0, 0)


@dataclass(slots=True)
class Diagnostics:
    """Solver figures of the last control step (summed / worst over its physics steps).

    One made by kernels.ControlPeriod (a Simulator's record of its last period) holds its
    physics steps' figures in `_pending` (totals before, figures, step_time, timings) and
    works its fields out when one is first read: a simulation loop that never reads them
    does not pay for them (made on every step: figures in doc/performance.md)."""

    iterations: int = 0            # prox iterations, summed over the physics steps
    max_iterations_step: int = 0   # worst physics step
    converged: bool = True         # every physics step converged
    status: str = "converged"
    residual: float = 0.0          # max |Λ^{k+1} − Λ^k| of the final iterations [N s]
    active_contacts: int = 0
    retried: bool = False          # a step needed the fallback α
    #: contacts that carried Λ_N > 0 in the previous physics step and left the active set by
    #: the activation test alone (with contact.activation "hysteresis" only beyond
    #: opening_gap), summed over the physics steps
    loaded_contacts_opened: int = 0
    projection_iterations: int = 0  # post-step projection, summed over the physics steps
    projections: int = 0           # physics steps that needed the post-step projection
    step_time: float = 0.0         # wall time of the control step [s]
    physics_steps: int = 0         # cumulative
    nonconverged_steps: int = 0    # cumulative
    loaded_contacts_opened_total: int = 0  # cumulative
    #: cumulative per phase (profile=True) [s]; empty and read-only when not profiling
    timings: Mapping[str, float] = field(default_factory=lambda: NO_TIMINGS)
    #: (totals before, figures, step_time, timings) until the fields are worked out
    _pending: tuple | None = field(default=None, repr=False, compare=False)

    def __getattr__(self, name):
        """A field not set yet: those of the pending figures, worked out now."""
        try:
            pending = object.__getattribute__(self, "_pending")
        except AttributeError:
            pending = None
        if pending is None or name not in FIELD_NAMES:
            raise AttributeError(f"'Diagnostics' object has no attribute '{name}'")
        self._pending = None
        for n, v in zip(FIELD_NAMES, figures_of(*pending), strict=True):
            object.__setattr__(self, n, v)
        return object.__getattribute__(self, name)

    def __getstate__(self):
        """(copy and pickle: the fields worked out first; NO_TIMINGS, a read-only mapping,
        as None)"""
        values = [getattr(self, n) for n in FIELD_NAMES]
        values[-1] = dict(values[-1]) if values[-1] else None
        return tuple(values)

    def __setstate__(self, state):
        for n, v in zip(FIELD_NAMES, state, strict=True):
            object.__setattr__(self, n, v)
        if state[-1] is None:
            self.timings = NO_TIMINGS
        self._pending = None


#: Diagnostics' fields in order (its _pending aside)
FIELD_NAMES = tuple(f.name for f in fields(Diagnostics) if f.name != "_pending")


def figures_of(totals, figures, step_time: float, timings) -> tuple:
    """The values of Diagnostics' fields (FIELD_NAMES order) of a control step: its physics
    steps' figures (a TreeStepResult, or a list of them: sums and worst cases) after the
    cumulative `totals`."""
    if type(figures) is not list:
        figures = [figures]
    iterations = worst = projection_iterations = projections = opened = nonconverged = 0
    residual = 0.0
    retried = False
    status = _CONVERGED
    for f in figures:
        iterations += f.iterations
        worst = max(worst, f.iterations)
        residual = max(residual, f.residual)
        retried |= bool(f.retried)
        opened += f.opened
        projection_iterations += f.projection_iterations
        projections += f.projection_status >= 0
        if f.status != _CONVERGED:
            status = f.status
            nonconverged += 1
    return (iterations, worst, nonconverged == 0, STATUS_NAMES[status], residual,
            figures[-1].n_active, retried, opened, projection_iterations, projections,
            step_time, totals[0] + len(figures), totals[1] + nonconverged,
            totals[2] + opened, timings)


class StepWarnings:
    """Warns through `log` (the first time, then every 1000th) of a control step that did not
    converge or that opened loaded contacts by the gap test alone (contact.activation
    `activation`). Call it with a step's Diagnostics and its end time; returns them."""

    def __init__(self, log, activation: str):
        self.log = log
        self.activation = activation
        self.nonconverged = 0
        self.opened = 0

    def __call__(self, d: "Diagnostics", t: float) -> "Diagnostics":
        if not d.converged:
            self.nonconverged += 1
            if self.nonconverged == 1 or self.nonconverged % 1000 == 0:
                self.log.warning("t=%.4f s: prox iteration did not converge (%s, %d "
                                 "iterations, residual %.3g N s); %d such steps so far", t,
                                 d.status, d.max_iterations_step, d.residual,
                                 d.nonconverged_steps)
        if d.loaded_contacts_opened:
            self.opened += 1
            if self.opened == 1 or self.opened % 1000 == 0:
                self.log.warning("t=%.4f s: %d loaded contact(s) left the active set by the "
                                 "gap test alone (contact.activation '%s'); %d so far", t,
                                 d.loaded_contacts_opened, self.activation,
                                 d.loaded_contacts_opened_total)
        return d
