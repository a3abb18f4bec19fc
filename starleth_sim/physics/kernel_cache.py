"""Keeps numba's on-disk cache of the physics kernels (``cache=True``) consistent.

numba keys a cached kernel by its own source file only: a kernel that calls, or inlines, a
kernel of another file keeps its compiled code after that other file changed (a documented
limitation of numba's cache), so a working tree could run stale machine code after an edit
(a fresh clone never does). The physics kernels call across files (tree_step -> step_kernels
-> prox, linalg, kinematics, rigid_body, coordinates/forest), so the package's sources are
hashed together at import, and when the hash differs from the one the cache was built with,
every cache file of the package is removed: the kernels compile again (≈1.5 min once).
"""
from __future__ import annotations

import hashlib
import os

STAMP_NAME = "kernel_sources.sha256"

#: the options of every physics kernel, ``numba.njit(**KERNEL)``: cached on disk (above),
#: and numpy's error model for division: x / 0 gives ±inf or NaN, which the kernels'
#: finiteness checks catch (status NONFINITE, TREE_STEP_NOT_PD, ...), instead of Python's
#: ZeroDivisionError. The results are the same for every nonzero divisor; numba's default
#: tests each divisor before dividing, which kept the small loops from being vectorized
#: (≈7 % of an HmJ step, measured side by side).
KERNEL = {"cache": True, "error_model": "numpy"}


def sources_digest(root: str) -> str:
    """SHA-256 over the .py files below root (paths and contents, in sorted order)."""
    h = hashlib.sha256()
    for folder, dirs, files in sorted(os.walk(root)):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__")
        for name in sorted(files):
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                h.update(os.path.relpath(path, root).encode())
                with open(path, "rb") as f:
                    h.update(f.read())
    return h.hexdigest()


def drop_stale_kernel_caches(root: str) -> bool:
    """Removes numba's cache files (.nbi, .nbc) below root when root's sources changed since
    they were built (the stamp in root/__pycache__); True if it removed any. Best effort: a
    read-only install or a concurrent process removing the same files is not an error
    (numba compiles whatever it cannot load)."""
    stamp = os.path.join(root, "__pycache__", STAMP_NAME)
    digest = sources_digest(root)
    try:
        with open(stamp) as f:
            if f.read().strip() == digest:
                return False
    except OSError:
        pass
    removed = False
    for folder, _, files in os.walk(root):
        if os.path.basename(folder) != "__pycache__":
            continue
        for name in files:
            if name.endswith((".nbi", ".nbc")):
                try:
                    os.remove(os.path.join(folder, name))
                    removed = True
                except OSError:
                    pass
    try:
        os.makedirs(os.path.dirname(stamp), exist_ok=True)
        tmp = f"{stamp}.{os.getpid()}"
        with open(tmp, "w") as f:
            f.write(digest + "\n")
        os.replace(tmp, stamp)
    except OSError:
        pass
    return removed
