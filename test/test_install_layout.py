"""colcon layout check: an install of the package into a prefix (what colcon's ament_python
build does: setup.py install --single-version-externally-managed with setup.cfg's
install_scripts=$base/lib/starleth_sim) has the executables where `ros2 run` looks and the
ament index marker, URDF and configs under share/."""
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def prefix(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("install")
    prefix = tmp / "prefix"
    cmd = [sys.executable, "setup.py", "-q", "build", "--build-base", str(tmp / "build"),
           "egg_info", "--egg-base", str(tmp),
           "install", "--prefix", str(prefix), "--single-version-externally-managed",
           "--record", str(tmp / "record.txt")]
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    return prefix


def _site_packages(prefix):
    for dirpath, dirnames, _ in os.walk(prefix / "lib"):
        if os.path.basename(dirpath) == "site-packages":
            return dirpath
    raise AssertionError("no site-packages under the install prefix")


def test_executables_and_share(prefix):
    exe = prefix / "lib" / "starleth_sim" / "sim_node"
    assert exe.is_file() and os.access(exe, os.X_OK)
    assert "'console_scripts', 'sim_node'" in exe.read_text()
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "starleth_sim").is_file()
    share = prefix / "share" / "starleth_sim"
    assert (share / "package.xml").is_file()
    assert (share / "urdf" / "starleth.urdf").is_file()
    assert (share / "launch" / "starleth.launch.xml").is_file()
    assert (share / "foxglove" / "starleth_layout.json").is_file()
    for f in ("sim_node.yaml", "HmJ.yaml", "Cm.yaml", "HmS.yaml"):
        assert (share / "msg_configs" / f).is_file(), f


def test_installed_package_finds_its_share_directory(prefix, tmp_path):
    """Run from outside the source tree: data comes from share/ via the ament index."""
    code = ("import starleth_sim, starleth_sim.physics.description as d;"
            "from starleth_sim.ros.parameters import load_default_parameters, default_settings_file;"
            "print(starleth_sim.__file__); print(d.package_share_dir());"
            "print(default_settings_file()); print(load_default_parameters()['physics'])")
    env = dict(os.environ, PYTHONPATH=_site_packages(prefix), AMENT_PREFIX_PATH=str(prefix))
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
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
               ROS_DOMAIN_ID=str(100 + os.getpid() % 2))
    r = subprocess.run([str(prefix / "lib" / "starleth_sim" / "sim_node"), "--ros-args",
                        "-p", "mode:=bogus"], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "parameter mode" in r.stderr


def test_readme_layout_lists_every_module():
    """The README's Layout table names every module of the packages (a newcomer's map)."""
    with open(os.path.join(ROOT, "README.md")) as f:
        text = f.read()
    layout = text[text.index("## Layout"):]
    layout = layout[:layout.index("\n## ", 3)]
    missing = []
    for pkg in ("starleth_sim", "starleth_controller", "starleth_interface"):
        for dirpath, _, files in os.walk(os.path.join(ROOT, pkg)):
            for name in files:
                if name.endswith((".py", ".html")) and name != "__init__.py" \
                        and f"{name}`" not in layout:
                    missing.append(os.path.relpath(os.path.join(dirpath, name), ROOT))
    assert not missing, f"README Layout does not list {missing}"


def test_stale_numba_caches_are_dropped_when_any_kernel_source_changes(tmp_path):
    """numba's cache only sees a kernel's own file: kernel_cache drops every cache file of
    the package when any of its sources changed (a caller in another file would otherwise
    keep stale machine code), and keeps them while nothing changed."""
    from starleth_sim.physics.kernel_cache import drop_stale_kernel_caches
    pkg = tmp_path / "pkg"
    (pkg / "sub" / "__pycache__").mkdir(parents=True)
    (pkg / "__pycache__").mkdir()
    (pkg / "a.py").write_text("A = 1\n")
    (pkg / "sub" / "b.py").write_text("B = 1\n")

    def caches():
        for p in (pkg / "__pycache__" / "a.f-1.py311.nbi", pkg / "sub" / "__pycache__" /
                  "b.g-3.py311.1.nbc", pkg / "__pycache__" / "a.cpython-311.pyc"):
            p.write_bytes(b"x")

    def left():
        return sorted(p.name for p in pkg.rglob("*") if p.suffix in (".nbi", ".nbc", ".pyc"))

    caches()
    drop_stale_kernel_caches(str(pkg))            # no stamp yet: built by unknown sources
    assert left() == ["a.cpython-311.pyc"]
    caches()
    assert not drop_stale_kernel_caches(str(pkg))     # nothing changed: kept
    assert len(left()) == 3
    (pkg / "sub" / "b.py").write_text("B = 2\n")      # a callee in another file changed
    assert drop_stale_kernel_caches(str(pkg))
    assert left() == ["a.cpython-311.pyc"]
