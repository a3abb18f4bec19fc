"""Running independent tasks, for ``starleth-sweep`` and ``starleth-eval``: a local process
pool or Ray, the same tasks either way, results taken as they finish (a progress bar with
ETA on stderr) and returned in task order; :class:`SweepError`, the one-line error both
tools report.
"""
from __future__ import annotations

import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed


class SweepError(ValueError):
    """A sweep that cannot be run (a bad spec, --ray without Ray or a cluster to join):
    one line, exit status 1."""


def progress(done, total, t0, stream=sys.stderr, what="tasks"):
    """A progress bar with the elapsed time and an ETA, on one line."""
    width = 30
    fill = int(width * done / total) if total else width
    el = time.time() - t0
    eta = el / done * (total - done) if done else 0.0
    stream.write(f"\r[{'#' * fill}{'.' * (width - fill)}] {done}/{total} {what}, "
                 f"{el:5.0f} s elapsed, ~{eta:4.0f} s left")
    stream.flush()


def _call(fn, kwargs):
    return fn(**kwargs)


def _ray_init(address, init_kwargs):
    try:
        import ray
    except ImportError:
        raise SweepError("--ray needs Ray: pip install '.[ray]' (or make ray)") from None
    if not ray.is_initialized():
        kw = dict(init_kwargs or {})
        kw.setdefault("log_to_driver", False)
        kw.setdefault("include_dashboard", False)
        try:
            ray.init(address=None if address in (None, "local") else address, **kw)
        except ConnectionError as e:
            raise SweepError(f"--ray {address}: cannot connect: {e}") from None
    return ray


def execute(tasks, jobs=None, ray=None, ray_init=None, show_progress=True, what="tasks"):
    """Run tasks [(function, kwargs)] and return their results in task order. jobs: worker
    processes of the local pool (1: in this process); ray: 'auto', 'local' or an address
    to run each task as a Ray task instead (ray_init: extra ray.init arguments). Results are
    taken as they finish, with a progress bar and ETA on stderr."""
    n = len(tasks)
    results = [None] * n
    t0 = time.time()
    report = (lambda d: progress(d, n, t0, what=what)) if show_progress else (lambda _done: None)
    report(0)
    if ray is not None:
        rt = _ray_init(ray, ray_init)
        remote = rt.remote(num_cpus=1)(_call)
        refs = {remote.remote(fn, kw): i for i, (fn, kw) in enumerate(tasks)}
        pending = list(refs)
        done = 0
        while pending:
            ready, pending = rt.wait(pending, num_returns=1)
            for ref in ready:
                results[refs[ref]] = rt.get(ref)
                done += 1
                report(done)
    elif (jobs or os.cpu_count() or 1) == 1 or n <= 1:
        for i, (fn, kw) in enumerate(tasks):
            results[i] = fn(**kw)
            report(i + 1)
    else:
        with ProcessPoolExecutor(max_workers=min(jobs or os.cpu_count() or 1, n)) as ex:
            futs = {ex.submit(fn, **kw): i for i, (fn, kw) in enumerate(tasks)}
            for done, fut in enumerate(as_completed(futs), 1):
                results[futs[fut]] = fut.result()
                report(done)
    if show_progress:
        sys.stderr.write("\n")
    return results
