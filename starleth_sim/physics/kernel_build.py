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
instruction (the same correctly rounded value).

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

FLAGS = ("-std=gnu11", "-O2", "-ffp-contract=off", "-fno-math-errno", "-fPIC",
         "-fvisibility=hidden", "-Wall")


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
            with open(os.path.join(csrc, name), "rb") as f:
                h.update(f.read())
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


def build(out_path: str, csrc: str = CSRC, jobs: int | None = None, progress=None) -> float:
    """Compiles the kernels into the extension module file out_path (replaced atomically,
    with the digest beside it: out_path + DIGEST_SUFFIX); returns the wall time [s].
    progress(done, total) is called as the sources finish. Raises BuildError."""
    t0 = time.perf_counter()
    cc = compiler()
    digest = source_digest(csrc)
    include = ["-I" + csrc, "-I" + _python_include()]
    define = [f'-DKERNELS_SOURCE_DIGEST="{digest}"']
    srcs = sources(csrc)
    jobs = max(1, min(jobs or os.cpu_count() or 1, len(srcs)))
    out_dir = os.path.dirname(os.path.abspath(out_path))
    os.makedirs(out_dir, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="starleth-kernels-") as tmp:
        objects = [os.path.join(tmp, os.path.basename(s)[:-2] + ".o") for s in srcs]
        done = 0

        def compile_one(pair):
            src, obj = pair
            _run(cc + list(FLAGS) + include + define + ["-c", src, "-o", obj])

        with ThreadPoolExecutor(jobs) as pool:
            for _ in pool.map(compile_one, zip(srcs, objects)):
                done += 1
                if progress:
                    progress(done, len(srcs))
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
    with open(digest_file + ".tmp", "w") as f:
        f.write(digest + "\n")
    os.replace(digest_file + ".tmp", digest_file)
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
