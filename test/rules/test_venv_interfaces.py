"""venv_interfaces/generate.py, the step of `make venv` that generates tf2_msgs where no ROS
install provides it: it does nothing where the package is up to date or provided by a ROS
install, it generates again when the definition changes, and where generation cannot be
done it says so in one line (what is lost: /tf not published) and fails without a traceback.
The generation itself is what test_tf_publishing checks (the type hash, a subscriber)."""
import importlib.util
import os
import shutil

import pytest
from repo_root import ROOT

SCRIPT = os.path.join(ROOT, "venv_interfaces", "generate.py")


@pytest.fixture()
def generate():
    """The script as a module (it is no package: loaded by path)."""
    spec = importlib.util.spec_from_file_location("_venv_interfaces_generate", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_digest_follows_the_definition(generate, tmp_path, monkeypatch):
    """The sources' digest changes with the message definition (a changed definition is
    generated again) and with nothing outside the package's folder and the CMake fix."""
    here = tmp_path / "venv_interfaces"
    shutil.copytree(os.path.dirname(SCRIPT), here)
    monkeypatch.setattr(generate, "HERE", str(here))
    monkeypatch.setattr(generate, "INCLUDE_FIX", str(here / "wheel_include_dirs.cmake"))
    before = generate.source_digest("tf2_msgs")
    assert before == generate.source_digest("tf2_msgs") and len(before) == 64
    (here / "generate.py").write_text("# another generator script\n")
    assert generate.source_digest("tf2_msgs") == before
    msg = here / "tf2_msgs" / "msg" / "TFMessage.msg"
    msg.write_text(msg.read_text() + "int32 extra\n")
    assert generate.source_digest("tf2_msgs") != before


def test_where_it_cannot_generate_one_line_says_what_is_lost(generate, tmp_path, monkeypatch,
                                                             capsys):
    """A prefix without the ROS 2 wheels (a venv on a system ROS lacking tf2_msgs): exit
    status 1 and one line naming the cause and that /tf is recorded but not published;
    nothing installed, no generator wheel asked for."""
    monkeypatch.setattr(generate, "PREFIX", str(tmp_path))
    monkeypatch.setattr(generate, "importable", lambda _pkg: None)
    ran = []
    monkeypatch.setattr(generate, "run", lambda *a, **k: ran.append(a))
    assert generate.main([]) == 1
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("venv: tf2_msgs not generated (the ROS 2 of ")
    assert "ros-jazzy-tf2-msgs" in lines[0]
    assert lines[0].endswith(": /tf and /tf_static are recorded but not published")
    assert ran == [] and os.listdir(tmp_path) == []


def test_nothing_to_do_where_a_ros_install_provides_it(generate, tmp_path, monkeypatch,
                                                       capsys):
    """tf2_msgs importable and not generated here (no digest file in the prefix): left
    alone, with a line saying where it comes from."""
    monkeypatch.setattr(generate, "PREFIX", str(tmp_path))
    monkeypatch.setattr(generate, "importable", lambda _pkg: "/opt/ros/jazzy/lib/tf2_msgs")
    monkeypatch.setattr(generate, "generate", lambda *a: pytest.fail("generated"))
    assert generate.main([]) == 0
    assert capsys.readouterr().out == \
        "venv: tf2_msgs: provided by the installed ROS (/opt/ros/jazzy/lib/tf2_msgs)\n"


def test_generated_earlier_is_up_to_date_until_its_sources_change(generate, tmp_path,
                                                                  monkeypatch, capsys):
    monkeypatch.setattr(generate, "PREFIX", str(tmp_path))
    monkeypatch.setattr(generate, "importable", lambda _pkg: str(tmp_path / "site-packages"))
    calls = []
    monkeypatch.setattr(generate, "generate", lambda _pkg, digest: calls.append(digest))
    marker = tmp_path / "share" / "tf2_msgs" / generate.DIGEST_FILE
    marker.parent.mkdir(parents=True)
    marker.write_text(generate.source_digest("tf2_msgs") + "\n")
    assert generate.main([]) == 0 and calls == []
    assert "up to date" in capsys.readouterr().out
    marker.write_text("0" * 64 + "\n")                  # generated from other sources
    assert generate.main([]) == 0 and calls == [generate.source_digest("tf2_msgs")]
    assert generate.main(["--force"]) == 0 and len(calls) == 2


def test_the_failure_line_names_the_cause(generate):
    """What a failed command's output is reduced to: CMake's message under "CMake Error
    at", a compiler's or pip's error line, else the last line."""
    cmake = ["-- The C compiler identification is unknown",
             "CMake Error at /x/CMakeDetermineCCompiler.cmake:48 (message):",
             "  Could not find the compiler specified in the environment variable CC:", "",
             "CMake Error: CMAKE_C_COMPILER not set, after EnableLanguage",
             "-- Configuring incomplete, errors occurred!"]
    assert generate.first_error(cmake) == \
        "Could not find the compiler specified in the environment variable CC:"
    pip = ["ERROR: Could not find a version that satisfies the requirement cmake==4.4.5",
           "ERROR: No matching distribution found for cmake==4.4.5"]
    assert generate.first_error(pip) == pip[0]
    assert generate.first_error(["gmake: *** [all] Killed", "  "]) == "gmake: *** [all] Killed"
    assert generate.first_error([]) == ""


def test_a_package_that_fails_its_check_is_removed_again(generate, tmp_path):
    """What the install step wrote (CMake's install_manifest.txt) is removed when rclpy
    cannot load it, so that sim_node does not find a broken tf2_msgs; nothing else is."""
    build, prefix = tmp_path / "build", tmp_path / "prefix"
    build.mkdir()
    (prefix / "lib").mkdir(parents=True)
    installed = [prefix / "lib" / "libtf2_msgs__rosidl_generator_c.so", prefix / "x.py"]
    for p in installed + [prefix / "lib" / "libgeometry_msgs.so"]:
        p.write_text("")
    (build / "install_manifest.txt").write_text(
        "\n".join(map(str, installed + [prefix / "gone.py"])))
    generate.uninstall(str(build))
    assert sorted(p.name for p in prefix.rglob("*") if p.is_file()) == ["libgeometry_msgs.so"]
