"""Builds the C physics kernels (``csrc/*.c``) into the extension module
``starleth_sim.physics._kernels``.

One build for every way the package is installed: ``setup.py`` (pip, colcon) calls `build`
for its extension, and in a source checkout `starleth_sim.physics.kernels` calls it when the
sources changed since the module was built (their digest, with the flags, is written beside
the module), so that an edit never runs stale machine code. The sources compile in parallel
processes, in a few seconds.

Flags: the kernels' results are pinned bit for bit (test/test_bitexact.py), so no flag may
change the floating-point results: ``-ffp-contract=off`` (no fused multiply-adds, which GCC
forms by default where the CPU has them), no ``-ffast-math`` or any of its parts that
reassociate or assume finite values. ``-fno-math-errno`` only lets sqrt compile to one
instruction (the same correctly rounded value). ``-O3`` and the machine's own instruction
set (`ARCH`) vectorize the loops over independent entries (the maximal coordinates' JOR
sweep: HMJP 6,100 -> 10,600 steps/s against -O2 for the default target, measured).

Standard library only: setup.py loads this file before anything is installed.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor

HERE = os.path.dirname(os.path.abspath(__file__))
CSRC = os.path.join(HERE, "csrc")
MODULE = "_kernels"
#: the file of the built module, and the digest of what it was built from, in the package
SUFFIX = sysconfig.get_config_var("EXT_SUFFIX") or ".so"
DIGEST_SUFFIX = ".digest"
#: a source checkout's object files (kernels.ensure_built), beside the module
OBJECTS = ".kernel_objects"

#: the target CPU: this machine's (``-march=native``, as numba's JIT targeted it), or what
#: $STARLETH_KERNEL_ARCH names (empty: the compiler's default target, for a build that runs
#: on other machines than the one it was built on). Vector instructions change no result:
#: without reassociation only independent entries are computed side by side.
ARCH = os.environ.get("STARLETH_KERNEL_ARCH", "native")
FLAGS = ("-std=gnu11", "-O3", "-ffp-contract=off", "-fno-math-errno", "-fPIC",
         "-fvisibility=hidden", "-Wall") + ((f"-march={ARCH}",) if ARCH else ())


class BuildError(RuntimeError):
    """The C compiler failed (its output is in the message) or was not found."""


def sources(csrc: str = CSRC) -> list[str]:
    """The C sources (.c) of the kernels, sorted."""
    return sorted(os.path.join(csrc, f) for f in os.listdir(csrc) if f.endswith(".c"))


def source_digest(csrc: str = CSRC) -> str:
    """SHA-256 over the kernels' sources and headers (names and contents), the flags and
    the Python ABI the module is built for."""
    h = hashlib.sha256()
    h.update(" ".join(FLAGS).encode())
    h.update(SUFFIX.encode())
    for name in sorted(os.listdir(csrc)):
        if name.endswith((".c", ".h")):
            h.update(name.encode() + b"\0")
            h.update(_read_bytes(os.path.join(csrc, name)))
    return h.hexdigest()


def compiler() -> list[str]:
    """The C compiler command: $CC, else Python's own (sysconfig), else cc."""
    cc = os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc"
    cmd = cc.split()
    if shutil.which(cmd[0]) is None:
        for alt in ("cc", "gcc", "clang"):
            if shutil.which(alt):
                return [alt]
        raise BuildError("no C compiler found (install gcc, e.g. `sudo apt install gcc`, or "
                         "set CC)")
    return cmd


def _python_include() -> str:
    inc = sysconfig.get_paths()["include"]
    if not os.path.exists(os.path.join(inc, "Python.h")):
        raise BuildError(f"Python.h not found in {inc}: install Python's headers (e.g. `sudo "
                         f"apt install python{sys.version_info[0]}.{sys.version_info[1]}-dev`)")
    return inc


def _run(cmd):
    p = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if p.returncode != 0:
        raise BuildError(f"{' '.join(cmd)}\n{p.stdout}")
    return p.stdout


def _read_bytes(path: str) -> bytes:
    with open(path, "rb") as f:
        return f.read()


def _object_key(src: str, cc, headers: bytes) -> str:
    """What an object file depends on: the compiler command, the flags, the Python headers'
    place, every header of the kernels and the source itself."""
    h = hashlib.sha256()
    h.update(" ".join(cc + list(FLAGS)).encode() + b"\0" + _python_include().encode())
    h.update(headers)
    h.update(_read_bytes(src))
    return h.hexdigest()[:32]


def build(out_path: str, csrc: str = CSRC, jobs: int | None = None, progress=None,
          object_cache: str | None = None) -> float:
    """Compiles the kernels into the extension module file out_path (replaced atomically,
    with the digest beside it: out_path + DIGEST_SUFFIX); returns the wall time [s].
    progress(done, total) is called as the sources finish. object_cache: a directory that
    keeps each source's object file under the digest of what it depends on (its own text,
    the headers, the flags), so that after an edit only the edited sources compile again
    (all of them after an edit of a header). Raises BuildError."""
    t0 = time.perf_counter()
    cc = compiler()
    digest = source_digest(csrc)
    include = ["-I" + csrc, "-I" + _python_include()]
    srcs = sources(csrc)
    jobs = max(1, min(jobs or os.cpu_count() or 1, len(srcs)))
    out_dir = os.path.dirname(os.path.abspath(out_path))
    os.makedirs(out_dir, exist_ok=True)
    headers = b"".join(_read_bytes(os.path.join(csrc, n))
                       for n in sorted(os.listdir(csrc)) if n.endswith(".h"))
    with tempfile.TemporaryDirectory(prefix="starleth-kernels-") as tmp:
        cache = object_cache or tmp
        os.makedirs(cache, exist_ok=True)
        objects = [os.path.join(cache, os.path.basename(s)[:-2] + "-"
                                + _object_key(s, cc, headers) + ".o") for s in srcs]
        done = 0

        def compile_one(pair):
            src, obj = pair
            if os.path.exists(obj):
                return
            part = obj + f".{os.getpid()}.tmp"
            _run(cc + list(FLAGS) + include + ["-c", src, "-o", part])
            os.replace(part, obj)

        with ThreadPoolExecutor(jobs) as pool:
            for _ in pool.map(compile_one, zip(srcs, objects)):
                done += 1
                if progress:
                    progress(done, len(srcs))
        if object_cache:    # the objects of other versions: removed
            keep = set(objects)
            for name in os.listdir(object_cache):
                path = os.path.join(object_cache, name)
                if name.endswith(".o") and path not in keep:
                    os.remove(path)
        fd, tmp_out = tempfile.mkstemp(prefix=".build-", suffix=SUFFIX, dir=out_dir)
        os.close(fd)
        try:
            _run(cc + ["-shared", "-fPIC"] + objects + ["-lm", "-o", tmp_out])
            os.chmod(tmp_out, 0o755)
            os.replace(tmp_out, out_path)
        finally:
            if os.path.exists(tmp_out):
                os.remove(tmp_out)
    digest_file = out_path + DIGEST_SUFFIX
    part = f"{digest_file}.{os.getpid()}.tmp"
    with open(part, "w") as f:
        f.write(digest + "\n")
    os.replace(part, digest_file)
    return time.perf_counter() - t0


def inplace_path(package_dir: str = HERE) -> str:
    """Where a source checkout keeps its built module: beside this file."""
    return os.path.join(package_dir, MODULE + SUFFIX)


def main(argv=None) -> int:
    """python -m starleth_sim.physics.kernel_build [OUT]: builds the module (in place by
    default), printing the time."""
    argv = sys.argv[1:] if argv is None else argv
    out = argv[0] if argv else inplace_path()
    try:
        seconds = build(out)
    except BuildError as e:
        print(f"kernel_build: FAILED: {e}", file=sys.stderr)
        return 1
    print(f"kernel_build: {out} in {seconds:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
