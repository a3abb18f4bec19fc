"""The one build recipe of the C extension modules: the flags, the compiler, the digest of
the sources kept beside a module and the locked in-place rebuild. It builds the small
modules itself, the controller's kernels (``starleth_controller._kernels``, sources in
starleth_controller/csrc) and sim_node's command parsers (``starleth_sim.ros._cdr``,
starleth_sim/ros/csrc), each one compiler call over its few sources; the physics kernels
(starleth_sim/physics/kernels/build.py: many sources compiled in parallel, a generated
header) take their flags, compiler and rebuild from here.

Flags: the results are pinned bit for bit (test/physics/test_bitexact.py, the controller's
pinned torques), so no flag may change a floating-point result: ``-ffp-contract=off`` (no
fused multiply-adds, which GCC forms by default where the CPU has them), no ``-ffast-math``
or any of its parts that reassociate or assume finite values. ``-fno-math-errno`` only lets
sqrt compile to one instruction (the same correctly rounded value). ``-O3`` and the
machine's own instruction set (`ARCH`) vectorize the loops over independent entries.

One build for every way the packages are installed: ``setup.py`` builds each `Extension`
(pip, colcon), and in a source checkout `load` (`ensure_built`) builds the module on first
use and again whenever its sources changed (their digest, with the flags, is kept beside the
module), so an edit never runs stale machine code. ``starleth_interface/csrc`` (`SHARED_INCLUDE`:
the headers both sides share) is on every build's include path.

Standard library only: setup.py imports it before anything is installed, and the controller
imports nothing of starleth_sim.
"""
from __future__ import annotations

import fcntl
import hashlib
import importlib
import importlib.util
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
#: the headers both sides share (py_args.h, py_minmax.h, quaternion.h, buffer_format.h)
SHARED_INCLUDE = os.path.join(HERE, "csrc")
SUFFIX = sysconfig.get_config_var("EXT_SUFFIX") or ".so"
DIGEST_SUFFIX = ".digest"
#: the target CPU: this machine's (``-march=native``), or what $STARLETH_KERNEL_ARCH names
#: (empty: the compiler's default target, for a build that runs on other machines than the
#: one it was built on). Vector instructions change no result: without reassociation only
#: independent entries are computed side by side.
ARCH = os.environ.get("STARLETH_KERNEL_ARCH", "native")
#: the extensions built here: module -> what it is (its sources: csrc/ in its package)
EXTENSIONS = {"starleth_controller._kernels": "the controller's kernels",
              "starleth_sim.ros._cdr": "sim_node's command parsers"}
#: the flags every C source compiles with (the module docstring)
FLAGS = ("-std=gnu11", "-O3", "-ffp-contract=off", "-fno-math-errno", "-fPIC",
         "-fvisibility=hidden", "-Wall", "-Wextra") + ((f"-march={ARCH}",) if ARCH else ())


class BuildError(RuntimeError):
    """The C compiler failed (its output is in the message) or was not found."""


def compiler() -> list[str]:
    """The C compiler command: $CC, else Python's own (sysconfig), else cc."""
    cmd = (os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc").split()
    if shutil.which(cmd[0]) is None:
        for alt in ("cc", "gcc", "clang"):
            if shutil.which(alt):
                return [alt]
        raise BuildError("no C compiler found (install gcc, e.g. `sudo apt install gcc`, or "
                         "set CC)")
    return cmd


def python_include() -> str:
    """The directory of Python.h. Raises BuildError (how to install it) where it is missing."""
    inc = sysconfig.get_paths()["include"]
    if not os.path.exists(os.path.join(inc, "Python.h")):
        raise BuildError(f"Python.h not found in {inc}: install Python's headers (e.g. `sudo "
                         f"apt install python{sys.version_info[0]}.{sys.version_info[1]}-dev`)")
    return inc


def run(cmd: list[str]) -> str:
    """Runs a compiler command; its output. Raises BuildError with the output if it fails."""
    p = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if p.returncode != 0:
        raise BuildError(f"{' '.join(cmd)}\n{p.stdout}")
    return p.stdout


def csrc_of(module: str) -> str:
    """The sources' directory of the extension `module`: csrc/ in its package (found
    without importing the package)."""
    spec = importlib.util.find_spec(module.rpartition(".")[0])
    return os.path.join(spec.submodule_search_locations[0], "csrc")


def module_path(module: str) -> str:
    """Where a source checkout keeps the built `module`: in its package."""
    return os.path.join(os.path.dirname(csrc_of(module)),
                        module.rpartition(".")[2] + SUFFIX)


def sources(csrc: str) -> list[str]:
    """The C sources (.c) of a module's directory, sorted."""
    return sorted(os.path.join(csrc, f) for f in os.listdir(csrc) if f.endswith(".c"))


def headers(*dirs: str) -> list[str]:
    """The headers (.h) of the directories, each directory's sorted."""
    return [os.path.join(d, f) for d in dirs for f in sorted(os.listdir(d)) if f.endswith(".h")]


def source_digest(csrc: str, generated: bytes = b"") -> str:
    """SHA-256 over the module's sources and headers and the shared headers (names and
    contents), a generated header's text, the flags and the Python ABI."""
    h = hashlib.sha256()
    h.update(" ".join(FLAGS).encode() + SUFFIX.encode() + generated)
    for path in headers(SHARED_INCLUDE) + [os.path.join(csrc, n) for n in sorted(os.listdir(csrc))
                                           if n.endswith((".c", ".h"))]:
        with open(path, "rb") as f:
            h.update(os.path.basename(path).encode() + b"\0" + f.read())
    return h.hexdigest()


def write_output(cmd: list[str], out_path: str) -> None:
    """Runs the compiler command `cmd` with ``-o`` a temporary file beside out_path, then
    puts it at out_path (atomically: a process that loads the module meanwhile sees the old
    or the new one)."""
    out_dir = os.path.dirname(os.path.abspath(out_path))
    os.makedirs(out_dir, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".build-", suffix=SUFFIX, dir=out_dir)
    os.close(fd)
    try:
        run(cmd + ["-o", tmp])
        os.chmod(tmp, 0o755)
        os.replace(tmp, out_path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def write_digest(out_path: str, digest: str) -> None:
    """The digest of what the module out_path was built from, beside it (atomically)."""
    part = f"{out_path}{DIGEST_SUFFIX}.{os.getpid()}.tmp"
    with open(part, "w") as f:
        f.write(digest + "\n")
    os.replace(part, out_path + DIGEST_SUFFIX)


def build(csrc: str, out_path: str) -> float:
    """Compiles the sources of csrc into the extension module file out_path (replaced
    atomically, with its digest beside it); returns the wall time [s]. Raises BuildError."""
    t0 = time.perf_counter()
    digest = source_digest(csrc)
    write_output(compiler() + list(FLAGS) + ["-I" + csrc, "-I" + SHARED_INCLUDE,
                                             "-I" + python_include(), "-shared"]
                 + sources(csrc) + ["-lm"], out_path)
    write_digest(out_path, digest)
    return time.perf_counter() - t0


def _read(path: str) -> str | None:
    try:
        with open(path) as f:
            return f.read().strip()
    except OSError:
        return None


def ensure_built(csrc: str, path: str, what: str, stream=None, digest_of=source_digest,
                 build_module=build) -> bool:
    """In a source checkout (csrc exists), builds the module at `path` when it is missing or
    its sources changed (`digest_of(csrc)` is not the digest beside it), under a lock shared
    by concurrent processes, saying so on `stream` (default stderr; `what` names it); True
    if it built it. build_module(csrc, path) builds it (returns its seconds; default
    `build`). Raises BuildError."""
    if not os.path.isdir(csrc):
        return False        # an installed package: setup.py built the module
    digest = digest_of(csrc)
    if os.path.exists(path) and _read(path + DIGEST_SUFFIX) == digest:
        return False
    stream = sys.stderr if stream is None else stream
    try:
        lock = open(path + ".lock", "a")
    except OSError as e:
        raise BuildError(f"{what} in {os.path.dirname(path)} "
                         f"{'are out of date' if os.path.exists(path) else 'are not built'} "
                         f"and cannot be built there ({e.strerror}): build the package "
                         "again where it is writable") from None
    with lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if os.path.exists(path) and _read(path + DIGEST_SUFFIX) == digest:
                return False        # another process built it while this one waited
            print(f"compiling {what} (C, once per change of their sources)", file=stream,
                  flush=True)
            seconds = build_module(csrc, path)
            print(f"{what}: compiled in {seconds:.1f} s", file=stream, flush=True)
            return True
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def load(module: str, what: str | None = None, ensure=None):
    """The extension `module`, built first where its package is a source checkout's:
    ensure() (default: `ensure_built` of its csrc/, for a module of EXTENSIONS, which names
    it; `what` names another). Raises ImportError with the reason."""
    what = EXTENSIONS[module] if what is None else what
    try:
        if ensure is None:
            ensure_built(csrc_of(module), module_path(module), what)
        else:
            ensure()
    except BuildError as e:
        raise ImportError(f"{what} (C) could not be built: {e}") from None
    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise ImportError(f"{what} ({module}) are not built: {e}. In a source checkout they "
                          "build on first import (needs a C compiler and Python's headers); "
                          "an installed package builds them in setup.py") from e
