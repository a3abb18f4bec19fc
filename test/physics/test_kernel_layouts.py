"""The packed kernel models, their records and the kernels' named results are declared once
(starleth_sim.physics.kernel_layouts): the C side is generated from the declarations at build
time (kernel_build.c_header), and the Python side packs and names by them. These tests check
that both sides follow the declarations."""
import types

import numpy as np
import pytest

from starleth_sim import Simulator
from starleth_sim.physics import kernels
from starleth_sim.physics.contact import CompliantLaw
from starleth_sim.physics.kernels import build as kernel_build
from starleth_sim.physics.kernels import codegen as kernel_codegen
from starleth_sim.physics.kernels import layouts as kernel_layouts
from starleth_sim.physics.kernels.layouts import (
    CUT_MODEL,
    HEADER_KINDS,
    LAYOUTS,
    RECORDS,
    RESULTS,
    STEP_REPORT,
    TREE_STEP_MODEL,
    field_size,
    length,
    offsets,
)
from starleth_sim.physics.prox import ProxSettings
from starleth_sim.physics.step_kernels import StepSettings
from starleth_sim.physics.tree_step import buffer_views, report_size, report_views


def test_every_size_expression_reads_only_the_layouts_sizes():
    for layout in LAYOUTS:
        sizes = {f.name: 1 if f.kind == "flag" else 2 for f in layout.header()} | {
            n: 3 for n in layout.context}
        for b in layout.buffers:
            assert length(layout, b.name, sizes) >= 0
            for f in b.fields:
                for e in f.shape:
                    kernel_layouts.evaluate(e, sizes)
                if f.shape:     # a view's shape holds its entries
                    assert np.prod([kernel_layouts.evaluate(e, sizes) for e in f.shape]) == \
                        kernel_layouts.evaluate(field_size(f), sizes), (layout.name, f.name)
        assert all(f.kind not in HEADER_KINDS for b in layout.buffers if b.name != "ints"
                   for f in b.fields), "header entries live in the ints buffer"
        if layout.header():     # the header opens the ints buffer
            ints = layout.buffer("ints").fields
            assert ints[:len(layout.header())] == layout.header()
    with pytest.raises(ValueError):
        kernel_layouts.evaluate("__import__('os')", {})


def test_the_python_records_and_results_have_the_declared_fields():
    assert StepSettings._fields == tuple(f.name for f in kernel_layouts.STEP_SETTINGS.fields)
    assert ProxSettings._fields == tuple(f.name for f in kernel_layouts.PROX_SETTINGS.fields)
    assert CompliantLaw._fields == tuple(f.name for f in kernel_layouts.COMPLIANT_LAW.fields)
    assert ProxSettings(0, 0, 0.0, 0.0, 1, 0, False).alpha == 0.5
    for r in RESULTS:
        t = getattr(kernels, r.name)
        assert t._fields == tuple(f.name for f in r.fields)
        assert all(isinstance(getattr(t, f.name), types.MemberDescriptorType)
                   for f in r.fields)
    for r in RECORDS:
        assert f"#define {kernel_codegen.upper_snake(r.name)}_LENGTH {r.length}" in \
            kernel_build.c_header()


def test_the_kernel_reads_each_field_where_python_packs_it():
    """The generated unpacking reads the fields where pack (by the same declaration) put
    them: a ground raised through its packed offset lowers every reported gap by as much,
    zero packed effort limits saturate every torque to zero."""
    sim = Simulator.from_preset("HmJ")
    st, s = sim.stepper, sim.state
    nc, na = st.nc, sim.n_joints
    sizes = {"nj": st.coords.tree.parent.shape[0], "nc": nc, "na": na, "nv": st.nv,
             "nt": st.ground.terrain.shape[0], "drives": 0}

    def step(floats):
        report = np.empty(report_size(nc, na))
        r = kernels.tree_step_hard(0, True, (s.q, s.u, s.last_impulse.copy(),
                                             s.last_active.copy(), s.last_bilateral.copy(),
                                             s.prox_memory.copy()),
                                   np.full(na, 3.0), np.zeros(0),
                                   (report, np.empty(nc, dtype=bool), np.empty_like(s.q),
                                    np.empty_like(s.u)), (floats, *st._tree_model[1:]))
        assert r.outcome == kernels.TREE_STEP_OK
        return report_views(report, nc, na)
    floats = st._tree_model[0]
    _, gap, _, applied, _, _ = (a.copy() for a in step(floats.copy()))
    assert np.array_equal(applied, np.full(na, 3.0))
    changed = floats.copy()
    f = buffer_views(TREE_STEP_MODEL, "floats", changed, sizes)
    f["ground_offset"][0] += 0.01
    f["effort_limit"][:] = 0.0
    _, gap2, _, applied2, _, _ = step(changed)
    assert np.allclose(gap2, gap - 0.01, atol=1e-12)
    assert np.array_equal(applied2, np.zeros(na))
    header = kernel_build.c_header()
    assert "GENERATED" in header and header == kernel_build.c_header()   # deterministic
    for layout in LAYOUTS:      # every field is unpacked (into its target)
        for b in layout.buffers:
            for field in b.fields:
                assert f"out->{field.target} = " in header or \
                    f"&out->{field.target});" in header, (layout.name, field.name)


def test_pack_writes_the_drive_models_where_the_layout_says():
    """With the drive models the header's flag is 1 and their fields hold I_a, D, τ_c Δt and
    the lag's gain 1 − e^{−2π f Δt}; the workspace's lag_state is the stepper's."""
    sim = Simulator.from_preset("HmJ", armature=0.01, viscous_damping={"LF_HAA": 0.2},
                                coulomb_friction=0.5, torque_bandwidth=25.0)
    st = sim.stepper
    floats, ints, _, workspace = st._tree_model
    c = st.coords
    sizes = {"nj": c.tree.parent.shape[0], "nc": c.n_contacts, "na": c.joint_v.shape[0],
             "nv": c.nv, "nt": st.ground.terrain.shape[0], "nq": c.nq, "drives": 1}
    assert ints[6] == 1 and floats.shape[0] == length(TREE_STEP_MODEL, "floats", sizes)
    f = buffer_views(TREE_STEP_MODEL, "floats", floats, sizes)
    assert np.array_equal(f["armature"], np.full(12, 0.01))
    assert np.array_equal(f["viscous"], np.r_[0.2, np.zeros(11)])
    assert np.array_equal(f["friction_bound"], np.full(12, 0.5 * sim.dt))
    assert np.allclose(f["lag"], 1.0 - np.exp(-2 * np.pi * 25.0 * sim.dt), rtol=1e-15)
    w = buffer_views(TREE_STEP_MODEL, "workspace", workspace, sizes)
    assert np.shares_memory(w["lag_state"], st._lag_state)


@pytest.mark.parametrize("preset", ["HmJ", "Cm", "HEJD", "HMJD"])
def test_pack_writes_each_field_where_the_layout_says(preset):
    sim = Simulator.from_preset(preset)
    st = sim.stepper
    floats, ints, support, workspace = st._tree_model
    c = st.coords
    sizes = {"nj": c.tree.parent.shape[0], "nc": c.n_contacts, "na": c.joint_v.shape[0],
             "nv": c.nv, "nt": st.ground.terrain.shape[0], "nq": c.nq, "drives": 0}
    assert list(ints[:7]) == [sizes[k] for k in ("nj", "nc", "na", "nv", "nt", "nq",
                                                  "drives")]
    for name, array in (("floats", floats), ("ints", ints), ("support", support)):
        assert array.shape[0] == length(TREE_STEP_MODEL, name, sizes)
    f = buffer_views(TREE_STEP_MODEL, "floats", floats, sizes)
    assert list(f["settings"]) == kernel_layouts.STEP_SETTINGS.flatten(st.settings)
    assert tuple(f["law"]) == tuple(st.compliant_law)
    assert np.array_equal(f["eps"], st.eps)
    assert np.array_equal(f["ground_n"], st.ground.n) and f["ground_offset"][0] == \
        st.ground.offset
    i = buffer_views(TREE_STEP_MODEL, "ints", ints, sizes)
    assert np.array_equal(i["joint_v"], c.joint_v)
    assert np.array_equal(i["dof_parent"], c.tree.dof_parent)
    w = buffer_views(TREE_STEP_MODEL, "workspace", workspace, sizes)
    assert np.shares_memory(w["L"], st.L) and w["L"].shape == st.L.shape
    if st._forest:
        cf, ci, cw = st._cut_model
        constant = int(bool(c.constant_mass_matrix))
        csizes = {"ncut": c.n_cut, "constant": constant,
                  "nr": c.roots.shape[0] if constant else 0, "na": sizes["na"], "nv": c.nv}
        assert list(ci[:3]) == [csizes[k] for k in ("ncut", "constant", "nr")]
        for name, array in (("floats", cf), ("ints", ci), ("workspace", cw)):
            assert array.shape[0] == length(CUT_MODEL, name, csizes)
        v = buffer_views(CUT_MODEL, "floats", cf, csizes)
        assert np.array_equal(v["b1_C"], c.b1_C)
        if constant:
            assert np.array_equal(v["M"], c.M_const)
        assert np.array_equal(buffer_views(CUT_MODEL, "ints", ci, csizes)["joint_cut"],
                              c.joint_cut)


def test_the_report_follows_its_layout_and_the_kernel_writes_it_there():
    sim = Simulator.from_preset("HmJ")
    nc, na = sim.coords.n_contacts, sim.n_joints
    assert report_size(nc, na) == length(STEP_REPORT, "report", {"nc": nc, "na": na})
    report = np.full(report_size(nc, na), np.nan)
    active = np.zeros(nc, dtype=bool)
    tau = np.linspace(-1.0, 1.0, na)
    r = sim.stepper.step(sim.state, tau, report, active)
    assert isinstance(r, kernels.TreeStepResult) and r.outcome == kernels.TREE_STEP_OK
    impulse, gap, position, applied, explicit, damper = report_views(report, nc, na)
    assert np.isfinite(report).all()
    assert np.array_equal(applied, tau)     # (far below the limits: applied as asked)
    assert np.array_equal(explicit, tau) and not damper.any()   # (torques: no dampers)
    assert (gap < 0.0).sum() == r.n_active
    st = sim.stepper        # (g_N and the contact points at q^M, from its workspace)
    assert np.array_equal(gap, st.gap) and np.array_equal(position, st.position)
    assert (impulse[:, 0] >= 0.0).all() and impulse[:, 0].sum() > 0.0
    assert [f.name for f, _, _ in offsets(STEP_REPORT, "report", {"nc": nc, "na": na})] == \
        ["impulse", "gap", "position", "applied_torque", "explicit_torque", "damper"]
