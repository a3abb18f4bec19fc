"""Issue #33, "Nothing a config value can do takes the simulator down": every configuration
value has a physical range checked on load (the file and the field named), duplicate YAML
keys and binary files are errors naming the file. ROS-free (the controller node's schema is
only imported)."""
import math

import pytest
import yaml

from starleth_interface import yaml_files
from starleth_interface.ros_helpers import ParameterSpec
from starleth_interface.yaml_files import load_yaml_file, load_yaml_text
from starleth_sim import ConfigError, Simulator, available_presets, load_preset
from starleth_sim.physics import config as config_mod
from starleth_sim.physics.config import PRESETS
from starleth_sim.ros.parameters import (
    SIM_NODE_PARAMETERS,
    Settings,
    load_default_parameters,
    render_yaml,
)
from starleth_sim.ros.state_io import read_state_spec
from starleth_sim.tools.sweep import sweep

BINARY = bytes(range(256)) * 4          # not UTF-8, NUL bytes: an image, a bag, ...


def preset_text(**top):
    """HmJ.yaml's text with top-level lines replaced (`key: value` as written)."""
    with open(config_mod.config_dir() + "/HmJ.yaml") as f:
        lines = f.read().splitlines()
    out = []
    for line in lines:
        key = line.split(":")[0]
        out.append(f"{key}: {top.pop(key)}" if key in top else line)
    assert not top, top
    return "\n".join(out) + "\n"


def preset_file(tmp_path, text, name="bad.yaml"):
    p = tmp_path / name
    p.write_bytes(text) if isinstance(text, bytes) else p.write_text(text)
    return str(p)


def with_change(change):
    data = load_preset("HmJ").to_dict()
    for k, v in change.items():
        if isinstance(v, dict):
            data[k].update(v)
        else:
            data[k] = v
    return data


# -----------------------------------------------------------------------------------------
# the physics presets
# -----------------------------------------------------------------------------------------
def test_all_presets_still_load_unchanged():
    assert set(PRESETS) <= set(available_presets())
    for name in PRESETS:
        cfg = load_preset(name)
        assert cfg.name == name and cfg.dt >= config_mod.MIN_DT


def test_steps_per_control_1e12_is_refused_naming_file_and_field(tmp_path):
    """Was accepted: sim_node grew to 23 GB; Simulator.from_preset(path).step() hung."""
    path = preset_file(tmp_path, preset_text(steps_per_control="1000000000000"))
    with pytest.raises(ConfigError, match=r"bad\.yaml: steps_per_control: must be <= 10000"):
        load_preset(path)
    with pytest.raises(ConfigError, match="steps_per_control"):
        Simulator.from_preset(path)


def test_control_rate_1e308_is_refused(tmp_path):
    """Was accepted: a period of 1e-308 s, sim time never advanced."""
    path = preset_file(tmp_path, preset_text(control_rate="1.0e+308"))
    with pytest.raises(ConfigError, match=r"bad\.yaml: control_rate: must be <= 100000"):
        load_preset(path)
    with pytest.raises(ConfigError, match="control_rate"):
        load_preset("HmJ").with_overrides(control_rate=1e308)


def test_physics_step_below_a_microsecond_is_refused(tmp_path):
    """Each value in range, the product not: Δt = 1/(control_rate · N) >= 1 µs."""
    path = preset_file(tmp_path, preset_text(control_rate="100000.0", steps_per_control="20"))
    with pytest.raises(ConfigError, match=r"bad\.yaml: steps_per_control: the physics step"
                                          r".*>= 1 us"):
        load_preset(path)
    ok = load_preset("HmJ").with_overrides(control_rate=1000.0, steps_per_control=1000)
    assert ok.dt == pytest.approx(1e-6)


def test_nan_mu_is_refused(tmp_path):
    text = preset_text().replace("mu: 0.8", "mu: .nan")
    with pytest.raises(ConfigError, match=r"bad\.yaml: ground\.mu: must be finite"):
        load_preset(preset_file(tmp_path, text))
    with pytest.raises(ConfigError, match="ground.mu: must be finite"):
        load_preset("HmJ").with_overrides(mu=float("nan"))


def test_restitution_2_is_refused(tmp_path):
    path = preset_file(tmp_path, yaml.safe_dump(with_change({"contact": {
        "restitution_normal": 2}})))
    with pytest.raises(ConfigError, match=r"bad\.yaml: contact\.restitution_normal: must be "
                                          r"<= 1"):
        load_preset(path)
    with pytest.raises(ConfigError, match="restitution_tangential"):
        load_preset("HmJ").with_overrides(restitution_tangential=2.0)


def test_a_sane_override_is_still_accepted():
    cfg = load_preset("HmJ").with_overrides(mu=0.5)
    assert cfg.ground.mu == 0.5
    sim = Simulator.from_preset("HmJ", mu=0.5)
    sim.step()
    assert sim.t == pytest.approx(sim.control_period)


#: (override, value, words of the message): every number of the record out of its range
OUT_OF_RANGE = [
    ("control_rate", 0.5, "control_rate: must be >= 1"),
    ("control_rate", 2e5, "control_rate: must be <= 100000"),
    ("steps_per_control", 0, "steps_per_control: must be >= 1"),
    ("steps_per_control", 10 ** 400, "steps_per_control: must be <= 10000, got an integer"),
    ("ground.height", 1e4, "ground.height: must be <= 1000"),
    ("ground.height", -math.inf, "ground.height: must be finite"),
    ("ground.height", 10 ** 400, "ground.height: must be finite"),
    ("normal", [0.0, 0.0, -1.0], "ground.normal: must point up"),
    ("normal", [1.0, 0.0, 0.0], "ground.normal: must point up"),
    ("normal", [0.0, math.nan, 1.0], "ground.normal[1]: must be finite"),
    ("mu", 11.0, "ground.mu: must be <= 10"),
    ("mu", math.inf, "ground.mu: must be finite"),
    ("restitution_normal", -0.1, "contact.restitution_normal: must be >= 0"),
    ("restitution_overrides", {"LF_FOOT": [0.5, 1.5]}, "restitution_overrides.LF_FOOT[1]"),
    ("stiffness_normal", 1e10, "contact.stiffness_normal: must be <= 1000000000"),
    ("stiffness_tangential", math.nan, "contact.stiffness_tangential: must be finite"),
    ("damping_normal", 1e7, "contact.damping_normal: must be <= 1000000"),
    ("damping_tangential", -1.0, "contact.damping_tangential: must be >= 0"),
    ("slip_velocity", 2.0, "contact.slip_velocity: must be <= 1"),
    ("activation_gap", 1.0, "contact.activation_gap: must be <= 0.1"),
    ("opening_gap", 1.0, "contact.opening_gap: must be <= 0.1"),
    ("penetration_stabilization", math.nan, "contact.penetration_stabilization: must be "
                                            "finite"),
    ("alpha", math.inf, "solver.alpha: must be finite"),
    ("tol_rel", 2.0, "solver.tol_rel: must be <= 1"),
    ("tol_abs", 1e4, "solver.tol_abs: must be <= 1000"),
    ("tol_abs", math.nan, "solver.tol_abs: must be finite"),
    ("max_iterations", 10 ** 7, "solver.max_iterations: must be <= 1000000"),
    ("max_iterations", 0, "solver.max_iterations: must be >= 1"),
    ("fallback_alpha_factor", math.inf, "solver.fallback_alpha_factor: must be finite"),
    ("bilateral.stabilization", 1.5, "bilateral.stabilization: must be <= 1"),
]


@pytest.mark.parametrize("key,value,words", OUT_OF_RANGE,
                         ids=[f"{k}={v!r:.20}" for k, v, _ in OUT_OF_RANGE])
def test_every_number_of_the_physics_record_has_a_range(key, value, words):
    with pytest.raises(ConfigError, match=words.replace("[", r"\[").replace("(", r"\(")):
        load_preset("HmJ").with_overrides(**{key: value})


def test_paper_figures_are_finite_numbers_or_text(tmp_path):
    data = with_change({"paper": {"steps_per_second": float("inf")}})
    with pytest.raises(ConfigError, match=r"bad\.yaml: paper\.steps_per_second: must be finite"):
        load_preset(preset_file(tmp_path, yaml.safe_dump(data)))


# -----------------------------------------------------------------------------------------
# the YAML loader: duplicate keys, binary files
# -----------------------------------------------------------------------------------------
def test_duplicate_key_in_a_preset_is_refused_naming_key_and_line(tmp_path):
    text = preset_text().replace("  mu: 0.8", "  mu: 0.8\n  mu: 0.2")
    line = [k for k, t in enumerate(text.splitlines(), 1) if t.startswith("  mu: 0.2")][0]
    with pytest.raises(ConfigError, match=rf"bad\.yaml: duplicate key 'mu' at line {line} "
                                          rf"\(first at line {line - 1}\)"):
        load_preset(preset_file(tmp_path, text))
    # a top-level key twice, far apart
    with pytest.raises(ConfigError, match="bad.yaml: duplicate key 'control_rate'"):
        load_preset(preset_file(tmp_path, preset_text() + "control_rate: 800.0\n"))


def test_duplicate_keys_everywhere_yaml_configuration_is_read(tmp_path):
    # physics_overrides (sim_node's parameter)
    with pytest.raises(ConfigError, match="parameter physics_overrides: duplicate key 'mu'"):
        Settings(physics_overrides="{mu: 0.5, mu: 0.6}").physics_override_dict()
    # initial_state, as text and as a file
    with pytest.raises(ConfigError, match="parameter initial_state: duplicate key "
                                          "'base_position'"):
        read_state_spec("{base_position: [0, 0, 1], base_position: [0, 0, 2]}")
    state = tmp_path / "state.yaml"
    state.write_text("joint_positions: {LF_KFE: -1.0}\njoint_positions: {LF_KFE: 1.0}\n")
    with pytest.raises(ConfigError, match=r"state\.yaml: duplicate key 'joint_positions' at "
                                          r"line 2"):
        read_state_spec(str(state))
    # sim_node's parameter file
    params = tmp_path / "sim_node.yaml"
    params.write_text("/**:\n  ros__parameters:\n    mode: lockstep\n    mode: realtime\n")
    with pytest.raises(ConfigError, match=r"sim_node\.yaml: duplicate key 'mode' at line 4"):
        load_default_parameters(str(params))
    # nested mappings and flow mappings, and keys that are equal as values (1 and 1.0)
    for text in ("a: {b: 1, b: 2}", "a:\n  - {x: 1}\n  - {x: 1, x: 2}\n", "{1: a, 1.0: b}"):
        with pytest.raises(ConfigError, match="src: duplicate key"):
            load_yaml_text(text, "src")
    # a merge key may still be overridden, as YAML defines
    assert load_yaml_text("a: &A {b: 1}\nc:\n  <<: *A\n  b: 2\n", "src") == \
        {"a": {"b": 1}, "c": {"b": 2}}


def test_duplicate_key_in_a_sweep_spec_is_refused(tmp_path, capsys):
    spec = tmp_path / "dup.yaml"
    spec.write_text("presets: [HmJ]\nscenarios: [{kind: stand}]\nseeds: [0]\nseeds: [1, 2]\n")
    with pytest.raises(sweep.SweepError, match=r"dup\.yaml: duplicate key 'seeds' at line 4"):
        sweep.load_spec(str(spec))
    assert sweep.main([str(spec)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "duplicate key 'seeds'" in err[0], err


def test_binary_file_is_refused_naming_the_file(tmp_path):
    path = preset_file(tmp_path, BINARY, "image.yaml")
    with pytest.raises(ConfigError, match=r"image\.yaml: not a YAML text file") as e:
        load_preset(path)
    assert path in str(e.value)
    with pytest.raises(sweep.SweepError, match=r"image\.yaml: not a YAML text file"):
        sweep.load_spec(path)
    # UTF-8 text with NUL bytes is binary too
    with pytest.raises(ConfigError, match=r"nul\.yaml: not a YAML text file \(binary"):
        load_yaml_file(preset_file(tmp_path, b"name: a\x00b\n", "nul.yaml"))


def test_other_unreadable_files_name_the_file(tmp_path):
    with pytest.raises(ConfigError, match="nothere.yaml: no such file"):
        load_preset(str(tmp_path / "nothere.yaml"))
    (tmp_path / "dir.yaml").mkdir()
    with pytest.raises(ConfigError, match=r"dir\.yaml: cannot read"):
        load_preset(str(tmp_path / "dir.yaml"))
    with pytest.raises(ConfigError, match=r"deep\.yaml: not valid YAML: nested too deeply"):
        load_preset(preset_file(tmp_path, "[" * 100_000, "deep.yaml"))
    big = tmp_path / "big.yaml"
    with open(big, "wb") as f:
        f.truncate(yaml_files.MAX_CONFIG_BYTES + 1)
    with pytest.raises(ConfigError, match=r"big\.yaml: larger than 16 MiB"):
        load_yaml_file(str(big))


# -----------------------------------------------------------------------------------------
# sweep specs
# -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("body,words", [
    ("scenarios: [{kind: stand, seconds: 1.0e+300}]\n", "scenarios[0].seconds: must be in"),
    ("scenarios: [{kind: push, magnitude: .inf}]\n", "scenarios[0].magnitude: expected finite"),
    ("scenarios: [{kind: trot, speed: 100}]\n", "scenarios[0].speed: must be in"),
    ("scenarios: [{kind: stand}]\nseeds: [-1]\n", "seeds: must be in"),
    ("scenarios: [{kind: stand}]\nperturbation: {joint_angles: 5}\n",
     "perturbation.joint_angles: must be in"),
    ("scenarios: [{kind: stand}]\nseeds: [" + ", ".join(map(str, range(2000))) + "]\n"
     "overrides: {mu: [" + ", ".join(["0.5"] * 60) + "]}\n", "more than 100000"),
])
def test_sweep_spec_numbers_have_ranges(tmp_path, body, words):
    spec = tmp_path / "spec.yaml"
    spec.write_text("presets: [HmJ]\n" + body)
    with pytest.raises(sweep.SweepError, match=words.replace("[", r"\[")):
        sweep.load_spec(str(spec))


# -----------------------------------------------------------------------------------------
# ROS parameters: sim_node and controller_node
# -----------------------------------------------------------------------------------------
def test_record_max_size_1_is_refused_and_0_means_no_split():
    with pytest.raises(ConfigError, match=r"parameter record_max_size: must be 0 \(no split\) "
                                          r"or >= 1048576 .*got 1$"):
        Settings(record_max_size=1).validate()
    Settings(record_max_size=0).validate()
    Settings(record_max_size=1024 ** 2).validate()


def test_record_max_duration_0_001_is_refused_and_0_means_no_split():
    with pytest.raises(ConfigError, match=r"parameter record_max_duration: must be 0 \(no "
                                          r"split\) or >= 1 "):
        Settings(record_max_duration=0.001).validate()
    Settings(record_max_duration=0.0).validate()
    Settings(record_max_duration=0).validate()
    Settings(record_max_duration=1.0).validate()
    with pytest.raises(ConfigError, match="record_max_duration"):
        Settings(record_max_duration=0.5).validate()
    with pytest.raises(ConfigError, match="record_max_duration"):
        Settings(record_max_duration=1e300).validate()


@pytest.mark.parametrize("name,value", [
    ("real_time_factor", 1e6), ("real_time_factor", 1e-9), ("lockstep_timeout", 1e9),
    ("warn_throttle_period", 1e9), ("contact_marker_scale", 10.0), ("tf_rate", 1e6),
    ("tf_rate", 1e-310), ("contact_markers_rate", 5000.0), ("max_wrench_force", 1e300),
    ("max_wrench_torque", math.inf), ("lockstep_timeout", math.nan),
])
def test_sim_node_numbers_have_caps(name, value):
    with pytest.raises(ConfigError, match=f"parameter {name}: "):
        Settings(mode="lockstep", **{name: value}).validate()


def test_sim_node_defaults_and_off_values_are_legal():
    Settings().validate()
    Settings(mode="lockstep", real_time_factor=0.0, tf_rate=0.0, contact_markers_rate=0.0,
             warn_throttle_period=0.0).validate()


def test_sim_node_parameter_file_values_are_checked_naming_the_file(tmp_path):
    params = tmp_path / "mine.yaml"
    params.write_text("/**:\n  ros__parameters:\n    record_max_size: 1\n")
    with pytest.raises(ConfigError, match=r"mine\.yaml: /\*\*: parameter record_max_size"):
        load_default_parameters(str(params))
    params.write_text("/**:\n  ros__parameters:\n    use_sim_time: true\n    recrod: x.mcap\n")
    with pytest.raises(ConfigError, match=r"^mine\.yaml: /\*\*: unknown parameter 'recrod' "
                       r"\(did you mean 'record'\?\)$"):
        load_default_parameters(str(params))
    params.write_bytes(BINARY)
    with pytest.raises(ConfigError, match=r"mine\.yaml: not a YAML text file"):
        load_default_parameters(str(params))
    assert load_default_parameters(str(tmp_path / "none.yaml"))["physics"] == "HmJ"


def test_off_value_is_rendered_in_the_parameter_file():
    spec = ParameterSpec("size", int, 0, "bytes", minimum=1024, off_value=0,
                         off_meaning="no split")
    assert spec.range_text() == "0 (no split) or >= 1024"
    spec.check(0)
    spec.check(2048)
    with pytest.raises(ValueError, match=r"parameter size: must be 0 \(no split\) or >= 1024, "
                                         "got 5"):
        spec.check(5)
    assert ParameterSpec("r", float, 1.0, "", minimum=0.0, minimum_exclusive=True,
                         maximum=10.0).range_text() == "> 0 and <= 10"
    text = render_yaml()
    assert "# Legal values: 0 (no split) or >= 1048576 and <= 1099511627776." in text
    assert "Legal values: 0 (off) or >= 0.1 and <= 1000." in text
    with_range = [p for p in SIM_NODE_PARAMETERS if p.kind in (int, float)]
    assert all(p.maximum is not None for p in with_range), \
        [p.name for p in with_range if p.maximum is None]


def test_controller_node_numbers_have_caps():
    pytest.importorskip("rclpy")
    from starleth_controller.node_parameters import PARAMETERS, PARAMETERS_BY_NAME
    numbers = [p for p in PARAMETERS if p.kind in (int, float)]
    assert numbers and all(p.maximum is not None for p in numbers)
    for name, bad in (("max_linear_speed", 1e9), ("max_yaw_rate", 100.0),
                      ("contact_force_threshold", 1e5), ("cmd_vel_timeout", 1e9),
                      ("warn_throttle_period", math.inf), ("max_linear_speed", math.nan)):
        with pytest.raises(ValueError, match=f"parameter {name}"):
            PARAMETERS_BY_NAME[name].check(bad)
    for p in numbers:
        p.check(p.coerce(p.default))
