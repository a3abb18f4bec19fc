"""ROS 2 helpers of the node integration tests (test_sim_node, test_controller_node): a node
run as a child process on a ROS domain, and a test node in its own rclpy context. Every
wait is bounded; stop() always ends the process."""
import json
import os
import re
import signal
import subprocess
import sys
import time

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from starleth_interface.compile_notice import Deadline
from starleth_interface.ros_helpers import service_qos
from starleth_sim.tools.common.child_process import start_child_as_node
from starleth_sim.tools.common.discovery import keep_discovery_local, local_discovery_env

keep_discovery_local()     # the test nodes (this process) and every child: this host only


class NodeProcess:
    """`python -m module [pre_args] --ros-args [ros_args] -p k:=v ...` as a child process on
    domain_id (optionally renamed to `name`, under `namespace`; run by `wrapper`, a command
    prefix, with `preexec_fn` called in the child before it starts); its output in
    log_path."""

    def __init__(self, module, log_path, domain_id, name=None, namespace=None, pre_args=(),
                 preexec_fn=None, wrapper=(), ros_args=(), **params):
        cmd = [*wrapper, sys.executable, "-m", module, *pre_args, "--ros-args", *ros_args]
        if name:
            cmd += ["-r", f"__node:={name}"]
        if namespace:
            cmd += ["-r", f"__ns:={namespace}"]
        for k, v in params.items():
            val = f'"{v}"' if isinstance(v, str) else repr(v)
            cmd += ["-p", f"{k}:={val}"]
        env = dict(local_discovery_env(), ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED="1",
                   RCUTILS_LOGGING_BUFFERED_STREAM="0", RCUTILS_COLORIZED_OUTPUT="0")
        self.log_path = log_path
        self._log = open(log_path, "w")
        self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=self._log,
                                     stderr=subprocess.STDOUT, env=env,
                                     preexec_fn=start_child_as_node(preexec_fn))

    def alive(self):
        return self.proc.poll() is None

    def stop(self, sig=signal.SIGINT, timeout=30.0):
        """Send sig, wait up to timeout, then kill; returns the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self._log.close()
        return self.proc.returncode

    def log(self):
        with open(self.log_path) as f:
            return f.read()

    def summary(self):
        """The last `summary: {...}` JSON line a node logged (sim_node does on exit)."""
        m = re.findall(r"summary: (\{.*\})", self.log())
        return json.loads(m[-1]) if m else None


def run_lockstep(ros, ctl, log_path, domain_id, n_states, timeout, **params):
    """sim_node in lockstep as fast as `ctl` (an EchoController on `ros`'s node) answers,
    with `params`, until `ctl` has seen n_states states; then stopped (SIGINT) and `ctl`
    and `ros` closed. Asserts that it ran and exited with 0."""
    sim = NodeProcess("starleth_sim.ros.sim_node", log_path, domain_id, mode="lockstep",
                      real_time_factor=0.0, **params)
    try:
        ok = ros.spin_until(lambda: len(ctl.stamps) >= n_states or not sim.alive(), timeout)
        assert ok and sim.alive(), sim.log()[-3000:]
    finally:
        rc = sim.stop(signal.SIGINT)
        ctl.close()
        ros.close()
    assert rc == 0, sim.log()[-3000:]


class RosTestNode:
    """A test node `name` in its own context on domain_id; events=True spins it with
    rclpy's C++ EventsExecutor (much less overhead per callback) where available."""

    def __init__(self, domain_id, name, events=False):
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = Node(name, context=self.context)
        self.executor = None
        if events:
            try:
                from rclpy.experimental import EventsExecutor
                self.executor = EventsExecutor(context=self.context)
            except ImportError:
                pass
        if self.executor is None:
            self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, cond, timeout, procs=(), step=0.01):
        """Spin until cond() (True) or timeout (False); a dead process of procs fails. The
        timeout counts silence: a build line in the log of one of procs (a source checkout
        building its C kernels: compile_notice.shows_compiling) restarts it."""
        deadline = Deadline(timeout, [p.log_path for p in procs])
        while True:
            if cond():
                return True
            for p in procs:
                assert p.alive(), f"process died:\n{p.log()[-3000:]}"
            if deadline.expired():
                return False
            self.executor.spin_once(timeout_sec=step)

    def spin_for(self, seconds):
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            self.executor.spin_once(timeout_sec=0.01)

    def call_client(self, client, request, timeout=10.0):
        assert self.spin_until(client.service_is_ready, timeout), \
            f"{client.srv_name} not available"
        fut = client.call_async(request)
        assert self.spin_until(fut.done, timeout), f"{client.srv_name}: no response"
        return fut.result()

    def call(self, srv_type, name, request, timeout=10.0):
        client = self.node.create_client(srv_type, name, qos_profile=service_qos())
        try:
            return self.call_client(client, request, timeout)
        finally:
            self.node.destroy_client(client)

    def close(self):
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def nodes_on_domains(domain_ids, wait=1.5):
    """{domain id: the names of the nodes that another process runs there} (discovered within
    wait s, the domains side by side: a probe node on each, each in its own context): a
    leftover node of an earlier run there would answer or disturb a test's nodes."""
    probes = []
    try:
        for d in domain_ids:
            probes.append(RosTestNode(d, f"_domain_probe_{d}"))   # one logger each
        t_end = time.monotonic() + wait
        while time.monotonic() < t_end:
            for p in probes:
                p.executor.spin_once(timeout_sec=0.01 / len(probes))
        return {d: sorted(f"{ns.rstrip('/')}/{n}"
                          for n, ns in p.node.get_node_names_and_namespaces()
                          if not n.startswith("_domain_probe"))
                for d, p in zip(domain_ids, probes, strict=True)}
    finally:
        for p in probes:
            p.close()


def nodes_on_domain(domain_id, wait=1.5):
    """The names of the nodes that another process runs on domain_id (nodes_on_domains)."""
    return nodes_on_domains([domain_id], wait)[domain_id]


def domain_candidates(first, span):
    """The domain ids first..first+span-1, starting at one chosen by this process's pid (so
    that concurrent runs start apart)."""
    return [first + (os.getpid() + i) % span for i in range(span)]


def free_domain(candidates, wait=1.5):
    """The first domain id of candidates on which no other process runs a node; an occupied
    one is reported on stdout (pytest shows it with the test's output) and skipped."""
    candidates = list(candidates)
    for d in candidates:
        others = nodes_on_domain(d, wait)
        if not others:
            return d
        print(f"ROS domain {d} is taken by nodes of another process ({', '.join(others)}); "
              "trying the next one")
    raise RuntimeError(f"no free ROS domain among {candidates}")


def free_domains(candidate_lists, wait=1.5):
    """free_domain of each list of candidates, in one wait for them all: the first candidate
    of every list probed side by side (nodes_on_domains), the next ones of a list whose first
    is taken one by one. The domain ids, in the order of the lists."""
    firsts = sorted({c[0] for c in candidate_lists})
    others = nodes_on_domains(firsts, wait)
    chosen = []
    for c in candidate_lists:
        if not others[c[0]]:
            chosen.append(c[0])
            continue
        print(f"ROS domain {c[0]} is taken by nodes of another process "
              f"({', '.join(others[c[0]])}); trying the next one")
        try:
            chosen.append(free_domain(c[1:], wait))
        except RuntimeError:
            raise RuntimeError(f"no free ROS domain among {list(c)}") from None
    return chosen

