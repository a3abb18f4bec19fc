"""The controller examples as a user runs them: the python blocks of README.md's "Write your
own controller" section (test_sim_time: the torque PD) and of doc/controllers.md
(test_impedance_ros: the 50 Hz position controller; test_realtime_start: the controller on a
sim-time timer), each run as written, as a script with no arguments, beside sim_node, while
a test node records the base height."""
import os
import re
import subprocess
import sys

import numpy as np
from nav_msgs.msg import Odometry
from repo_root import ROOT
from ros_test_nodes import NodeProcess
from std_srvs.srv import SetBool

from starleth_sim.tools.common.discovery import local_discovery_env

START_TIMEOUT = 120.0          # of silence: a node's compile lines restart it (ros_test_nodes)


def python_blocks(text: str) -> list:
    return re.findall(r"```python\n(.*?)```", text, re.S)


def readme_controller_blocks() -> list:
    """The python code blocks of README.md's "Write your own controller" section, in order."""
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
        text = f.read()
    return python_blocks(text.split("## Write your own controller", 1)[1].split("\n## ", 1)[0])


def controllers_page_blocks() -> list:
    """The python code blocks of doc/controllers.md, in order."""
    with open(os.path.join(ROOT, "doc", "controllers.md"), encoding="utf-8") as f:
        return python_blocks(f.read())


def start_script(code, path, name, domain_id):
    """`code` run as a script with no arguments (as a user runs an example of the docs) on
    `domain_id`, its output in path/name.log; returns (process, log file)."""
    script = path / f"{name}.py"
    script.write_text(code)
    env = dict(local_discovery_env(), ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED="1")
    log = open(path / f"{name}.log", "w")
    return subprocess.Popen([sys.executable, str(script)], stdin=subprocess.DEVNULL,
                            stdout=log, stderr=subprocess.STDOUT, env=env), log


def stop_script(proc, log):
    """SIGINT, then SIGKILL after 10 s; the log closed."""
    proc.send_signal(2)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(10)
    log.close()


def run_beside_sim_node(ros, tmp_path, code, domain_id, until):
    """Run `code` as a script beside a lockstep sim_node on `domain_id` until the sim time
    reaches `until` [s]; then pause and stop both. Returns (t, z): the stamps [s] and base
    heights [m] of every state, and sim_node's exit summary. Fails if the script died or
    sim_node did not exit cleanly."""
    sim = NodeProcess("starleth_sim.ros.sim_node", str(tmp_path / "readme_sim.log"), domain_id,
                      mode="lockstep")
    log_path = tmp_path / "readme_controller.log"
    heights = []
    sub = ros.node.create_subscription(
        Odometry, "starleth/base_state",
        lambda m: heights.append((m.header.stamp.sec + m.header.stamp.nanosec * 1e-9,
                                  m.pose.pose.position.z)), 100)
    ctl = None
    try:
        # the controller only once this subscription sees sim_node's publisher (a lockstep
        # run goes at thousands of states per second: a late match would miss its start)
        assert ros.spin_until(lambda: ros.node.count_publishers("starleth/base_state") > 0,
                              START_TIMEOUT, procs=[sim]), sim.log()[-2000:]
        ros.spin_until(lambda: False, 0.5, procs=[sim])      # (and the match to take effect)
        ctl, log = start_script(code, tmp_path, "readme_controller", domain_id)
        assert ros.spin_until(lambda: heights and heights[-1][0] >= until, START_TIMEOUT,
                              procs=[sim]), (sim.log()[-2000:], heights[-3:])
        assert ctl.poll() is None, log_path.read_text()
        assert ros.call(SetBool, "/sim_node/pause", SetBool.Request(data=True)).success
    finally:
        ros.node.destroy_subscription(sub)
        if ctl is not None:
            stop_script(ctl, log)
        code_sim = sim.stop()
    assert code_sim == 0, sim.log()[-2000:]
    return (np.array([h[0] for h in heights]), np.array([h[1] for h in heights]),
            sim.summary())
