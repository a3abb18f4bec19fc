"""Who may talk to our nodes: ROS 2 discovery kept on this host unless the user chose
otherwise (ROS-free, for the processes the demo, the ROS benchmark and the tests start).

Jazzy's ``ROS_AUTOMATIC_DISCOVERY_RANGE`` (SUBNET by default) decides how far a node looks
for peers; with SUBNET, any machine on the LAN in the same ``ROS_DOMAIN_ID`` could publish
torques to a simulated robot. The helpers here default it to LOCALHOST for the child
processes they start; an explicit setting of the user (SUBNET, SYSTEM_DEFAULT, OFF, with
``ROS_STATIC_PEERS`` for chosen remote hosts) is kept.
"""
from __future__ import annotations

import os

DISCOVERY_RANGE = "ROS_AUTOMATIC_DISCOVERY_RANGE"


def local_discovery_env(environ=None) -> dict:
    """A copy of `environ` (default os.environ) with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
    unless it is set (non-empty) already."""
    env = dict(os.environ if environ is None else environ)
    if not env.get(DISCOVERY_RANGE, "").strip():
        env[DISCOVERY_RANGE] = "LOCALHOST"
    return env


def keep_discovery_local() -> str:
    """Apply local_discovery_env() to this process's environment (before rclpy.init);
    returns the range in effect."""
    os.environ.update(local_discovery_env())
    return os.environ[DISCOVERY_RANGE]
