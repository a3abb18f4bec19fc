"""No behaviour change across refactors: the states of 300 steps of every preset of Table 1
under a trotting joint PD law (diagonal leg pairs swing at 1.25 Hz, a push on the base at
0.2 s) are pinned bit for bit (test/physics/data/bitexact_reference.json). Cm, HmJ, HEJD and HMSD
carry digests recorded before the redesign of issue #15; when the kernels moved from numba
to C (issue #32) the new kernels gave the numba kernels' digests on all 11 presets, on one
machine, and those of the other 7 were added then. HMJP and HMSP were re-pinned for issue #49:
their bilateral prox rows are now swept Gauss-Seidel with ω_B = 1.5 (bilateral.relaxation),
the same fixed point in 2-4x fewer sweeps; their states moved by < 2e-5 up to step 50, where
the old pins and the new ones stand as close to a tightly solved HMJD (3e-4), and part
chaotically after the push. HEJD, HESD, HMJD and HMSD were re-pinned for issue #49 too: after
3 sweeps of a solve their direct bilateral method (Eqn. 20) applies the gain G_BB^{-1} [G_BU,
c_B], solved once for all its columns, instead of one solve with L_B per sweep: the same Λ_B
up to round-off (their states within 3e-13 of the old pins up to step 100, the same
iterations), parting after the push's contact events.

The torque law is a plain joint PD law on purpose: the physics alone is pinned here. The demo's
closed loop (sim_node + controller_node, below) is pinned with a tolerance, because its
stored states were recorded while the controller used ProxQP's AVX2 build, whose round-off
depends on the alignment of its buffers (~1e-10 N between processes); the controller now
uses proxsuite's portable build, which is reproducible (force_distribution).

Each step's (q, u, Λ of every contact) is hashed (SHA-256 of the float64 bytes, chained), and
the full state is stored every 50 steps so a failure says when and by how much it differs.
A change that is meant to alter the numbers regenerates the file on purpose:

    .venv/bin/python test/physics/test_bitexact.py --write

The demo's first 2 s (sim_node + controller_node over ROS, lockstep, standing) are pinned in
test/ros/test_controller_node.py against the states stored here every 50 steps (`demo_states`),
to 1e-7.
"""
import hashlib
import json
import os
import sys

import numpy as np
import pytest

REFERENCE = os.path.join(os.path.dirname(__file__), "data", "bitexact_reference.json")
PRESETS = ("Cm", "HmJ", "HmS", "HEJD", "HEJP", "HESD", "HESP", "HMJD", "HMJP", "HMSD", "HMSP")
STEPS = 300
SNAPSHOT_EVERY = 50
TROT_FROM = 0.25         # s
PUSH = (0.2, (40.0, 25.0, 0.0), 0.05)    # time [s], force [N], duration [s]


def trot_pd_torque(sim, q_stand, k):
    """Joint PD towards the standing posture, the hip flexion and knee of one diagonal pair
    (LF+RH, then RF+LH) lifting (knee +0.5 rad) at 1.25 Hz from TROT_FROM; public joint order."""
    t = k * sim.control_period
    target = q_stand.copy()
    if t >= TROT_FROM:
        s = np.sin(2 * np.pi * 1.25 * (t - TROT_FROM))
        lift = 0.5 * np.array([max(s, 0.0), max(-s, 0.0), max(-s, 0.0), max(s, 0.0)])
        target[1::3] -= 0.5 * lift * np.sign(q_stand[2::3])     # knee flexes, foot lifts
        target[2::3] += lift * np.sign(q_stand[2::3])
    return 120.0 * (target - sim.joint_positions()) - 3.0 * sim.joint_velocities()


def preset_trajectory(preset):
    """{"digest": hex, "snapshots": {step: [q..., u...]}} of the run above."""
    from starleth_sim import Simulator
    sim = Simulator.from_preset(preset)
    q_stand = sim.joint_positions().copy()
    h = hashlib.sha256()
    snapshots = {}
    for k in range(STEPS):
        tau = trot_pd_torque(sim, q_stand, k)
        if k == int(round(PUSH[0] / sim.control_period)):
            sim.apply_wrench("base", PUSH[1], duration=PUSH[2])
        sim.step(tau)
        forces = np.array([c.force for c in sim.contacts], dtype=np.float64)
        for a in (sim.q, sim.u, forces):
            h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
        if (k + 1) % SNAPSHOT_EVERY == 0:
            snapshots[str(k + 1)] = np.concatenate([sim.q, sim.u]).tolist()
    return {"digest": h.hexdigest(), "snapshots": snapshots}


DEMO_STEPS = 800         # the demo's 2 s of standing at 400 Hz


def demo_states(joint_states, base_states):
    """{step: values} every SNAPSHOT_EVERY steps of the first DEMO_STEPS of a demo bag:
    /joint_states (position, velocity, effort) and /starleth/base_state (pose, twist),
    both lists of deserialised messages in stamp order."""
    out = {}
    for k in range(SNAPSHOT_EVERY - 1, DEMO_STEPS, SNAPSHOT_EVERY):
        js, bs = joint_states[k], base_states[k]
        p, v = bs.pose.pose, bs.twist.twist
        out[str(k + 1)] = [*js.position, *js.velocity, *js.effort,
                           p.position.x, p.position.y, p.position.z,
                           p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w,
                           v.linear.x, v.linear.y, v.linear.z,
                           v.angular.x, v.angular.y, v.angular.z]
    return out


def platform_fingerprint():
    """What bit-for-bit results depend on besides our code: the architecture, the C library
    (libm's sin, cos, atan2 in the kernels) and the numeric libraries' versions. Not the
    CPU's vector instructions: the kernels are compiled without contraction or reassociation
    (kernels.build), so the same bits with SSE2, AVX2 or AVX-512 (the references recorded on
    an AVX2 machine match on an AVX-512 one)."""
    import platform

    import pinocchio
    return {"machine": platform.machine(), "libc": "-".join(platform.libc_ver()),
            "numpy": np.__version__, "pinocchio": pinocchio.__version__}


def load_reference():
    with open(REFERENCE) as f:
        return json.load(f)


@pytest.mark.parametrize("preset", PRESETS)
def test_closed_loop_states_are_unchanged_bit_for_bit(preset):
    reference = load_reference()
    ref = reference["presets"][preset]
    got = preset_trajectory(preset)
    diffs = {k: float(np.abs(np.array(got["snapshots"][k]) - np.array(want)).max())
             for k, want in ref["snapshots"].items()}
    report = "\n".join(f"step {k}: max |Δ(q, u)| = {d:.3e}" for k, d in diffs.items())
    here = platform_fingerprint()
    if here == reference["platform"]:
        assert got["digest"] == ref["digest"], \
            f"{preset}: the 300 steps differ from the pinned reference\n{report}"
    else:
        # another CPU or library version rounds differently: the same motion, not the same bits
        print(f"bit-for-bit check skipped: platform {here} != {reference['platform']}")
        assert max(diffs.values()) < 1e-6, f"{preset}: states differ\n{report}"


def main(argv):
    if argv != ["--write"]:
        print(__doc__)
        return 2
    ref = load_reference() if os.path.exists(REFERENCE) else {}
    ref["platform"] = platform_fingerprint()
    ref["presets"] = {p: preset_trajectory(p) for p in PRESETS}
    os.makedirs(os.path.dirname(REFERENCE), exist_ok=True)
    with open(REFERENCE, "w") as f:
        json.dump(ref, f, indent=1)
    print(f"wrote {REFERENCE}: " + ", ".join(f"{p} {v['digest'][:12]}"
                                             for p, v in ref["presets"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
