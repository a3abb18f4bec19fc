"""Generates the ROS 2 interface packages of venv_interfaces/ into a venv whose ROS 2 comes from
the Jazzy PyPI wheels. There is no tf2_msgs wheel; without tf2_msgs sim_node records /tf and
/tf_static but cannot publish them on DDS. The rosidl generator chain is among the wheels, so
the package is generated here from its definition (venv_interfaces/tf2_msgs: TFMessage, the
definition of Jazzy's tf2_msgs, hence its type hash).

Run by `make venv` with the venv's python (``python venv_interfaces/generate.py``); per package:
1. nothing to do where the package is importable already: an installed ROS provides it, or an
   earlier run generated it from the same sources (their digest, kept in
   <venv>/share/<package>/venv_interfaces.digest); --force generates it again;
2. the generator wheels (requirements-interfaces.txt, pinned by constraints.txt) into the venv;
3. cmake configure, build and install with the venv as the install prefix, beside the wheels
   (the Python module in site-packages, the libraries in <venv>/lib); the build tree in
   <venv>/.venv_interfaces/<package>/ (removed once installed), every command's output in
   <venv>/.venv_interfaces/<package>.log;
4. a check that rclpy loads the package's type support; the type hashes are printed.
Each step prints a progress line. Where one fails, one line says why and that /tf and
/tf_static are recorded but not published; the exit status is then 1 (make venv goes on).
"""
from __future__ import annotations

import argparse
import hashlib
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
PREFIX = sys.prefix                         # the venv: where the wheels put share/ and lib/
BUILD_ROOT = os.path.join(PREFIX, ".venv_interfaces")
REQUIREMENTS = os.path.join(REPO, "requirements-interfaces.txt")
CONSTRAINTS = os.path.join(REPO, "constraints.txt")
#: the CMake file that points the wheels' imported targets at this interpreter's headers
INCLUDE_FIX = os.path.join(HERE, "wheel_include_dirs.cmake")
#: the packages generated, and what their absence costs (said where one cannot be generated)
PACKAGES = {"tf2_msgs": "/tf and /tf_static are recorded but not published"}
DIGEST_FILE = "venv_interfaces.digest"
# not this folder: its package sources would be found as namespace packages by their name
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != HERE]


class StepFailed(Exception):
    """A step that failed, with what to say (the log holds the details)."""


def say(pkg, text):
    print(f"venv: {pkg}: {text}", flush=True)


def source_digest(pkg) -> str:
    """sha256 of the package's definition files and of the CMake fix they are built with."""
    h = hashlib.sha256()
    src = os.path.join(HERE, pkg)
    files = sorted(os.path.relpath(os.path.join(d, f), HERE)
                   for d, _, names in os.walk(src) for f in names)
    for rel in files + [os.path.relpath(INCLUDE_FIX, HERE)]:
        h.update(rel.encode() + b"\0")
        with open(os.path.join(HERE, rel), "rb") as f:
            h.update(f.read() + b"\0")
    return h.hexdigest()


def importable(pkg):
    """The directory `pkg` is imported from (None: not importable)."""
    spec = importlib.util.find_spec(pkg)
    return None if spec is None or spec.origin is None else os.path.dirname(spec.origin)


def installed_state(pkg, digest) -> str | None:
    """Why nothing is to be done for `pkg` (None: generate it)."""
    marker = os.path.join(PREFIX, "share", pkg, DIGEST_FILE)
    if os.path.isfile(marker):
        with open(marker) as f:
            current = f.read().strip() == digest
        if current and importable(pkg):
            return "generated earlier from these sources, up to date"
        return None
    where = importable(pkg)
    return None if where is None else f"provided by the installed ROS ({where})"


def run(cmd, log, env=None):
    """Run `cmd` with its output appended to `log`; StepFailed with the line that says what
    went wrong if it fails."""
    with open(log, "a") as f:
        f.write(f"\n$ {' '.join(cmd)}\n")
        f.flush()
        try:
            proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env=env)
        except OSError as e:
            raise StepFailed(f"{cmd[0]}: {e.strerror}") from None
    if proc.returncode != 0:
        with open(log) as f:
            output = f.read().rsplit("\n$ ", 1)[-1].splitlines()[1:]    # this command's
        raise StepFailed(f"{os.path.basename(cmd[0])} exited with {proc.returncode}"
                         + (f": {first_error(output)[:200]}" if output else ""))


def first_error(lines) -> str:
    """The line of a command's output that says what went wrong: the first error line (with
    the message under CMake's "CMake Error at ...:"), else the last line."""
    lines = [ln.strip() for ln in lines if ln.strip()]
    for i, ln in enumerate(lines):
        if "error" in ln.lower():
            if ln.startswith("CMake Error at") and i + 1 < len(lines):
                return lines[i + 1]
            return ln
    return lines[-1] if lines else ""


def build_environment():
    """The environment of the CMake steps: only the venv's ament prefix (not a sourced ROS's),
    the venv's bin first on PATH."""
    env = dict(os.environ)
    env.pop("CMAKE_PREFIX_PATH", None)
    env["AMENT_PREFIX_PATH"] = PREFIX
    env["PATH"] = os.path.dirname(sys.executable) + os.pathsep + env.get("PATH", "")
    return env


def cmake_steps(pkg, build, log):
    """Configure, build and install `pkg` into the venv; yields each step's name when done."""
    cmake = shutil.which("cmake", path=os.path.dirname(sys.executable)) or shutil.which("cmake")
    if cmake is None:
        raise StepFailed("no cmake (requirements-interfaces.txt installs it)")
    try:
        import numpy
    except ImportError:
        raise StepFailed("numpy is not importable (requirements.txt)") from None
    env = build_environment()
    run([cmake, "-S", os.path.join(HERE, pkg), "-B", build,
         f"-DCMAKE_PREFIX_PATH={PREFIX}", f"-DCMAKE_INSTALL_PREFIX={PREFIX}",
         f"-DPython3_EXECUTABLE={sys.executable}", "-DCMAKE_BUILD_TYPE=Release",
         "-DBUILD_TESTING=OFF", f"-DCMAKE_PROJECT_INCLUDE={INCLUDE_FIX}",
         f"-DSTARLETH_PYTHON_INCLUDE={sysconfig.get_paths()['include']}",
         f"-DSTARLETH_NUMPY_INCLUDE={numpy.get_include()}"], log, env)
    yield "configured"
    run([cmake, "--build", build, "-j", str(os.cpu_count() or 2)], log, env)
    yield "built"
    run([cmake, "--install", build], log, env)
    yield "installed"


def check_and_hashes(pkg, log) -> list[str]:
    """rclpy loads each message's type support (in a fresh interpreter: the module was just
    installed); returns 'pkg/msg/Name RIHS01_...' of each message of the package."""
    names = sorted(os.path.splitext(f)[0] for f in os.listdir(os.path.join(HERE, pkg, "msg")))
    code = (f"from {pkg}.msg import {', '.join(names)}\n"
            "from rclpy.type_support import check_for_type_support\n"
            f"for t in ({', '.join(names)},):\n    check_for_type_support(t)\n")
    run([sys.executable, "-c", code], log)
    hashes = []
    for name in names:
        with open(os.path.join(PREFIX, "share", pkg, "msg", f"{name}.json")) as f:
            hashes.append("{type_name} {hash_string}".format(**json.load(f)["type_hashes"][0]))
    return hashes


def uninstall(build):
    """Remove the files the install step of `build` wrote (CMake's install_manifest.txt)."""
    manifest = os.path.join(build, "install_manifest.txt")
    if os.path.isfile(manifest):
        with open(manifest) as f:
            for path in f.read().splitlines():
                if os.path.isfile(path) or os.path.islink(path):
                    os.remove(path)


def generate(pkg, digest) -> None:
    """Steps 2 to 4 for `pkg`, with a progress line each; StepFailed where one fails."""
    if not os.path.isfile(os.path.join(PREFIX, "share", "geometry_msgs", "cmake",
                                       "geometry_msgsConfig.cmake")):
        raise StepFailed(f"the ROS 2 of {PREFIX} is not from the Jazzy wheels: install "
                         f"{pkg} with that ROS (ros-jazzy-{pkg.replace('_', '-')})")
    build = os.path.join(BUILD_ROOT, pkg)
    shutil.rmtree(build, ignore_errors=True)
    os.makedirs(build)
    log = os.path.join(BUILD_ROOT, f"{pkg}.log")
    open(log, "w").close()
    t0 = t = time.monotonic()
    say(pkg, f"generating it from venv_interfaces/{pkg} (log: {log})")
    run([sys.executable, "-m", "pip", "-qq", "--disable-pip-version-check", "--no-input",
         "install", "-c", CONSTRAINTS, "-r", REQUIREMENTS], log)
    say(pkg, f"generator wheels installed ({os.path.basename(REQUIREMENTS)}, "
             f"{time.monotonic() - t:.1f} s)")
    t = time.monotonic()
    for step in cmake_steps(pkg, build, log):
        say(pkg, f"{step} ({time.monotonic() - t:.1f} s)")
        t = time.monotonic()
    try:
        hashes = check_and_hashes(pkg, log)
    except (StepFailed, OSError, ValueError, KeyError):
        uninstall(build)      # not left importable: sim_node would try to publish with it
        raise
    for line in hashes:
        say(pkg, f"rclpy loads {line}")
    with open(os.path.join(PREFIX, "share", pkg, DIGEST_FILE), "w") as f:
        f.write(digest + "\n")
    shutil.rmtree(build, ignore_errors=True)
    say(pkg, f"done in {time.monotonic() - t0:.1f} s")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--force", action="store_true",
                    help="generate even where the package is installed and up to date")
    args = ap.parse_args(argv)
    status = 0
    for pkg, without in PACKAGES.items():
        digest = source_digest(pkg)
        why = None if args.force else installed_state(pkg, digest)
        if why is not None:
            say(pkg, why)
            continue
        try:
            generate(pkg, digest)
        except (StepFailed, OSError, ValueError, KeyError) as e:   # (a file, a JSON field)
            print(f"venv: {pkg} not generated ({e}): {without}", flush=True)
            status = 1
    return status


if __name__ == "__main__":
    sys.exit(main())
