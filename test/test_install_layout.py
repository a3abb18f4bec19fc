"""colcon layout check: an install of the package into a prefix (what colcon's ament_python
build does: setup.py install --single-version-externally-managed with setup.cfg's
install_scripts=$base/lib/starleth_sim) has the executables where `ros2 run` looks and the
ament index marker, URDF and configs under share/. Where colcon is installed, the prefix is
colcon's own build of the package (`colcon build --packages-select starleth_sim`), else the
setup.py commands of that build.

No test here starts a ROS node (one runs the installed sim_node with a bad parameter, which
exits before it joins a ROS graph): the file runs beside the ROS node tests (conftest.py)."""
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
COLCON = os.path.join(os.path.dirname(sys.executable), "colcon")


@pytest.fixture(scope="module")
def prefix(tmp_path_factory):
    """The install prefix of starleth_sim: colcon's where colcon is installed (one build for
    every test here: the build is the slow part), else setup.py's."""
    tmp = tmp_path_factory.mktemp("install")
    if os.path.exists(COLCON):
        base = tmp / "ws"
        r = subprocess.run([COLCON, "--log-base", str(base / "log"), "build", "--base-paths",
                            ROOT, "--build-base", str(base / "build"), "--install-base",
                            str(base / "install"), "--packages-select", "starleth_sim"],
                           cwd=tmp, capture_output=True, text=True, timeout=600,
                           stdin=subprocess.DEVNULL)
        assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
        return base / "install" / "starleth_sim"
    prefix = tmp / "prefix"
    cmd = [sys.executable, "setup.py", "-q", "build", "--build-base", str(tmp / "build"),
           "egg_info", "--egg-base", str(tmp),
           "install", "--prefix", str(prefix), "--single-version-externally-managed",
           "--record", str(tmp / "record.txt")]
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300,
                       stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stdout + r.stderr
    return prefix


def test_colcon_build_installs_the_launch_file(prefix):
    """`colcon build` (the prefix fixture's build) installs the launch file and both nodes'
    executables where `ros2 launch` and `ros2 run` look."""
    if not os.path.exists(COLCON):
        pytest.skip("colcon not installed (pip install colcon-common-extensions)")
    assert (prefix / "share" / "colcon-core" / "packages" / "starleth_sim").is_file()
    share = prefix / "share" / "starleth_sim"
    assert (share / "launch" / "starleth.launch.xml").is_file()
    lib = prefix / "lib" / "starleth_sim"
    assert (lib / "controller_node").is_file() and (lib / "sim_node").is_file()


def _site_packages(prefix):
    for dirpath, dirnames, _ in os.walk(prefix / "lib"):
        if os.path.basename(dirpath) == "site-packages":
            return dirpath
    raise AssertionError("no site-packages under the install prefix")


def _run_installed(prefix, cwd, code):
    """`python -c code` with the installed package (from outside the source tree), which
    must succeed; its CompletedProcess."""
    env = dict(os.environ, PYTHONPATH=_site_packages(prefix), AMENT_PREFIX_PATH=str(prefix))
    r = subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return r


def test_executables_and_share(prefix):
    exe = prefix / "lib" / "starleth_sim" / "sim_node"
    assert exe.is_file() and os.access(exe, os.X_OK)
    assert "'console_scripts', 'sim_node'" in exe.read_text()
    index = prefix / "share" / "ament_index" / "resource_index"
    assert (index / "packages" / "starleth_sim").is_file()
    share = prefix / "share" / "starleth_sim"
    assert (share / "package.xml").is_file()
    assert (share / "urdf" / "starleth.urdf").is_file()
    assert (share / "launch" / "starleth.launch.xml").is_file()
    assert (share / "foxglove" / "starleth_layout.json").is_file()
    # the ros2_control path: its launch file finds the controllers in share/config
    assert (share / "launch" / "starleth_ros2_control.launch.xml").is_file()
    assert (share / "config" / "starleth_controllers.yaml").is_file()
    assert (share / "urdf" / "starleth_ros2_control.xml").is_file()
    for f in ("sim_node.yaml", "HmJ.yaml", "Cm.yaml", "HmS.yaml", "terrain/stairs.yaml",
              "terrain/rough.yaml"):
        assert (share / "msg_configs" / f).is_file(), f


def test_installed_package_finds_its_share_directory(prefix, tmp_path):
    """Run from outside the source tree: data comes from share/ via the ament index."""
    code = ("import starleth_sim, starleth_sim.physics.description as d;"
            "from starleth_sim.ros.parameters import load_default_parameters,"
            " default_settings_file;"
            "print(starleth_sim.__file__); print(d.package_share_dir());"
            "print(default_settings_file()); print(load_default_parameters()['physics'])")
    r = _run_installed(prefix, tmp_path, code)
    mod, share, yaml_path, physics = r.stdout.split()
    assert mod.startswith(str(prefix))
    # starleth-view's page template is package data
    assert os.path.isfile(os.path.join(os.path.dirname(mod), "tools", "view_page.html"))
    assert os.path.realpath(share) == os.path.realpath(prefix / "share" / "starleth_sim")
    assert yaml_path.startswith(share) and physics == "HmJ"


def test_installed_sim_node_runs(prefix, tmp_path):
    """The installed console script resolves to the node's main: a bad parameter is reported
    as a configuration error (exit 2) before any physics is set up."""
    env = dict(os.environ, PYTHONPATH=_site_packages(prefix), AMENT_PREFIX_PATH=str(prefix),
               ROS_DOMAIN_ID=str(220 + os.getpid() % 8))   # no test module's range
    r = subprocess.run([str(prefix / "lib" / "starleth_sim" / "sim_node"), "--ros-args",
                        "-p", "mode:=bogus"], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "parameter mode" in r.stderr


def test_architecture_lists_every_module():
    """doc/architecture.md's Modules table names every module of the packages, Python and C
    (a newcomer's map), and the README's Layout points to it."""
    with open(os.path.join(ROOT, "README.md")) as f:
        readme = f.read()
    assert "(doc/architecture.md)" in readme[readme.index("## Layout"):]
    with open(os.path.join(ROOT, "doc", "architecture.md")) as f:
        text = f.read()
    layout = text[text.index("## Modules"):]
    missing = []
    for pkg in ("starleth_sim", "starleth_controller", "starleth_interface"):
        for dirpath, _, files in os.walk(os.path.join(ROOT, pkg)):
            for name in files:
                if name.endswith((".py", ".html", ".c", ".h")) and name != "__init__.py" \
                        and not name.startswith("bind") \
                        and f"{name}`" not in layout:
                    missing.append(os.path.relpath(os.path.join(dirpath, name), ROOT))
    assert "`csrc/bind*.c`" in layout and "`csrc/bind.h`" in layout
    assert not missing, f"doc/architecture.md Modules does not list {missing}"


def test_the_kernels_are_rebuilt_when_and_only_when_their_sources_change(tmp_path):
    """A source checkout builds the C kernels on first use and again after any edit of their
    sources (their digest, with the flags, beside the module): an edit never runs stale
    machine code, and an unchanged checkout builds nothing."""
    import io
    import shutil
    from starleth_sim.physics import kernel_build
    from starleth_sim.physics.kernels import ensure_built
    csrc = tmp_path / "csrc"
    shutil.copytree(kernel_build.CSRC, csrc)
    module = str(tmp_path / ("_kernels" + kernel_build.SUFFIX))
    out = io.StringIO()
    assert ensure_built(out, str(csrc), module)                 # missing: built
    assert "physics kernels built in" in out.getvalue()
    assert not ensure_built(out, str(csrc), module)             # unchanged: kept
    stamp = os.stat(module).st_mtime_ns
    objects = tmp_path / kernel_build.OBJECTS

    def compiled():
        return {p.name.rsplit("-", 1)[0]: p.name for p in objects.glob("*.o")}
    first = compiled()
    assert sorted(first) == sorted(p[:-2] for p in os.listdir(csrc) if p.endswith(".c"))
    with open(csrc / "step.c", "a") as f:                       # an edit of one source:
        f.write("\n/* edited */\n")                            # it alone compiles again
    assert ensure_built(out, str(csrc), module)
    assert os.stat(module).st_mtime_ns != stamp
    second = compiled()
    assert [k for k in first if first[k] != second[k]] == ["step"]
    assert len(list(objects.glob("*.o"))) == len(first)         # the old object removed
    assert not ensure_built(out, str(csrc), module)
    with open(csrc / "core.h", "a") as f:                       # a header: every source
        f.write("\n/* edited */\n")
    assert ensure_built(out, str(csrc), module)
    third = compiled()
    assert all(third[k] != second[k] for k in second)
    with open(module + kernel_build.DIGEST_SUFFIX, "w") as f:   # built from other sources
        f.write("0" * 64 + "\n")
    assert ensure_built(out, str(csrc), module)
    assert not ensure_built(out, str(tmp_path / "no_csrc"), module)   # an installed package


def test_the_installed_package_steps_with_its_built_kernels(prefix, tmp_path):
    """setup.py (colcon's build) compiles the C kernels into the install; run from outside
    the source tree, the installed package loads them (no sources there) and steps."""
    code = ("import starleth_sim.physics.kernels as k, starleth_sim;"
            "from starleth_sim import Simulator;"
            "sim = Simulator.from_preset('HEJD'); sim.step(None);"
            "print(k._kernels.__file__); print(starleth_sim.__file__); print(sim.q[2])")
    r = _run_installed(prefix, tmp_path, code)
    kernels, pkg, z = r.stdout.split()
    assert kernels.startswith(str(prefix)) and pkg.startswith(str(prefix))
    assert not os.path.exists(os.path.join(os.path.dirname(kernels), "csrc"))
    assert 0.3 < float(z) < 0.5
    assert "building the physics kernels" not in r.stderr
