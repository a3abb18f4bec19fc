"""The physics kernels: the C extension module ``starleth_sim.physics.kernels._kernels``
(sources in ``starleth_sim/physics/csrc/``), loaded here; the build (`build`), the declared
layouts of the packed buffers (`layouts`) and the C header generated from them (`codegen`)
are this package's modules.

An installed package (pip, colcon) holds the module its ``setup.py`` built. A source checkout
builds it on first use, and again whenever the sources changed since it was built (their
digest is kept beside the module: starleth_interface.c_extension, the build recipe of every C
extension), so an edit never runs stale machine code; the build takes a few seconds and says
so on stderr. Processes that start together (two nodes, test workers) build it once: the
first takes a lock, the others wait for it and load its result.

The modules of :mod:`starleth_sim.physics` import the kernels from here under the names of
the Python functions that describe them (linalg, kinematics, rigid_body, contact, prox,
step_kernels, tree_step, coordinates.forest).
"""
from __future__ import annotations

import importlib
import importlib.util
import os
import sys
import time

from starleth_interface import c_extension

from . import build as kernel_build


def _progress_line(stream):
    """A progress(done, total) callback that rewrites one line of stream (a terminal) or
    stays silent until the end (a log)."""
    t0 = time.monotonic()
    tty = hasattr(stream, "isatty") and stream.isatty()

    def progress(done, total):
        if tty:
            stream.write(f"\rcompiling the physics kernels (C): {done}/{total} sources, "
                         f"{time.monotonic() - t0:.0f} s ")
            stream.flush()
    return progress


def ensure_built(stream=None, csrc: str = kernel_build.CSRC, path: str | None = None) -> bool:
    """In a source checkout (csrc exists), builds the module (at `path`, default in the
    package) when it is missing or its sources changed (c_extension.ensure_built: under a
    lock shared by concurrent processes, saying so on stream, default stderr); True if it
    built it. Raises c_extension.BuildError when it cannot."""
    stream = sys.stderr if stream is None else stream
    path = kernel_build.inplace_path() if path is None else path

    def build(csrc, path):
        seconds = kernel_build.build(path, csrc, progress=_progress_line(stream),
                                     object_cache=os.path.join(os.path.dirname(path),
                                                               kernel_build.OBJECTS))
        if hasattr(stream, "isatty") and stream.isatty():
            stream.write("\r\033[K")
        return seconds
    return c_extension.ensure_built(csrc, path, "the physics kernels", stream,
                                    digest_of=kernel_build.source_digest, build_module=build)


#: names a module built with the sanitizers to load instead (`make sanitize`: built there by
#: ``kernels/build.py --sanitize``, run with the sanitizers' runtime preloaded)
SANITIZED = "STARLETH_KERNELS_SANITIZED"


def _load_sanitized(path: str):
    """The module at `path` (a sanitizer build), as this package's _kernels."""
    if not os.path.exists(path):
        raise ImportError(f"${SANITIZED}: no module {path} (make sanitize builds it)")
    name = __package__ + "." + kernel_build.MODULE
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    sys.modules[name] = module
    return module


def _load():
    if os.environ.get(SANITIZED):
        return _load_sanitized(os.environ[SANITIZED])
    return c_extension.load(__package__ + "." + kernel_build.MODULE, "the physics kernels",
                            ensure_built)


_kernels = _load()
globals().update({name: getattr(_kernels, name) for name in dir(_kernels)
                  if not name.startswith("__")})
