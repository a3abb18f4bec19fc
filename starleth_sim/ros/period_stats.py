"""The statistics of the realtime loop's period (:class:`PeriodStats`), ROS-free: kept by
:mod:`.sim_loops`, reported on /starleth/solver by :mod:`.solver_diagnostics` and in
sim_node's exit summary."""
from __future__ import annotations

import numpy as np


class PeriodStats:
    """Wall-clock tick intervals of the realtime loop: |interval - nominal| in a histogram
    of 1 us bins (O(1) per tick, percentiles in microseconds, cheap enough to run in the
    loop), plus count, mean and maximum."""

    BIN = 1e-6
    NBINS = 20000          # up to 20 ms; larger errors go to the last bin (max is exact)

    def __init__(self, nominal: float):
        self.nominal = nominal
        self.hist = np.zeros(self.NBINS, dtype=np.int64)
        self.n = 0
        self.total = 0.0
        self.max_err = 0.0
        self.last = None
        self.overruns = 0

    def tick(self, t: float):
        last = self.last
        self.last = t
        if last is None:
            return
        iv = t - last
        err = abs(iv - self.nominal)
        i = int(err / self.BIN)
        self.hist[i if i < self.NBINS else self.NBINS - 1] += 1
        self.n += 1
        self.total += iv
        if err > self.max_err:
            self.max_err = err

    def restart(self):
        self.last = None

    def percentile_ms(self, p: float) -> float:
        c = np.cumsum(self.hist)
        i = int(np.searchsorted(c, p / 100.0 * c[-1]))
        return (i + 1) * self.BIN * 1e3          # upper edge of the bin

    def summary(self) -> dict:
        if self.n == 0:
            return {"ticks": 0}
        return {"ticks": self.n, "period_mean_ms": self.total / self.n * 1e3,
                "period_error_p50_ms": self.percentile_ms(50),
                "period_error_p99_ms": self.percentile_ms(99),
                "period_error_max_ms": self.max_err * 1e3, "overruns": self.overruns}
