"""``starleth-demo`` (``make demo``): the main job.

Default: the trotting demo over ROS 2. Two processes on an isolated ROS_DOMAIN_ID (the
environment's ROS_DOMAIN_ID if set, else one chosen from the pid), discovering peers on this
host only (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST unless the environment sets it):

* ``sim_node`` (lockstep, as fast as the controller answers, physics HmJ, recording to
  ``runs/demo.mcap``; started paused, set going once both nodes are up), and
* ``controller_node`` (starleth_controller), started right after it: sim_node re-sends its
  first state until the controller answers, so the start order does not matter.

First the kernels are made ready (``starleth-precompile``: a source checkout builds its C
extensions when they are missing or out of date, a few seconds, with a progress line), so
that the nodes start with them built; a node that builds one anyway says so in its log,
and the start-up time-out counts only silence.

This process drives the run over ROS: it publishes /cmd_vel (0.3 m/s forward for StarlETH,
0.3 m/s · √λ for a robot of λ times its leg length: starleth_controller.robot_params;
ignored while standing), watches /clock, calls ``/controller_node/trot`` (true) at t = 2 s
of sim time, and after 18 s of trotting pauses the simulation (``/sim_node/pause``) and stops
both nodes with SIGINT, so that the recording is finalised. It then reads the bag
(tools/common/bag.py) and prints a summary: distance travelled, mean speed while trotting, falls
(base height > 0.3 m throughout for StarlETH, scaled to another robot's standing height),
real-time factor (sim time / wall time), solver iterations, messages, file. Exit status 0
when the run is complete and the robot trotted without falling (at least 0.8x the commanded
distance), non-zero with a message otherwise.

``--robot NAME``: the robot (a library name, a robot spec or URDF path), given to both nodes.

``--terrain step|stairs|ledge|slope|rough``: the same on a terrain course (tools/demo/terrain.py,
recorded to ``runs/demo_<name>.mcap``); the trunk must also cross the course.
``--live [PORT]``: sim_node also serves the live view (port 8765), whose URLs are printed.
``starleth-demo --drop``: the headless drop test (no ROS): StarlETH (or ``--robot``) falls
from 0.1 m onto flat ground under a joint PD posture hold, settles, and a summary is printed
(speed, final trunk height, per-foot normal force, solver iterations).
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass

from starleth_controller.robot_params import trot_speed
from starleth_interface.compile_notice import Deadline
from starleth_interface.robot.scaling import robot_scale
from starleth_interface.ros_helpers import service_qos

from ...physics.config import ConfigError
from ...robots import robot_description
from ...ros.live_view import live_view_lines
from ..bench.round_trips import measure_bare_round_trips
from ..common.bag import BagError
from ..common.child_process import start_child_as_node
from ..common.discovery import keep_discovery_local, local_discovery_env
from ..precompile import precompile
from ..view.view import ViewError, write_html
from .drop_test import drop_main
from .result import FALL_HEIGHT, REFERENCE_STANDING, DemoError, DemoResult, print_summary, read_bag
from .terrain import COURSES, course_overrides

STEPPING = 0.01                  # sim time [s] on /clock that shows the sim is stepping


# =========================================================================================
# trotting demo over ROS 2
# =========================================================================================
@dataclass(frozen=True)
class DemoRobot:
    """What the demo takes of a robot: its name, trot speed [m/s] and fall height [m]."""

    name: str
    speed: float
    fall_height: float

    @classmethod
    def of(cls, robot: str) -> "DemoRobot":
        """The demo's figures of `robot` (ConfigError naming it when it cannot be built)."""
        desc = robot_description(robot)
        standing = desc.standing_height or REFERENCE_STANDING
        return cls(robot, trot_speed(robot_scale(desc.legs, desc.total_mass)),
                   FALL_HEIGHT * standing / REFERENCE_STANDING)


def default_domain_id() -> int:
    env = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if env:
        try:
            return int(env)
        except ValueError:
            raise DemoError(f"ROS_DOMAIN_ID={env!r} is not an integer") from None
    return os.getpid() % 90 + 10


class NodeProcess:
    """A ROS node in a child process (no stdin, output to a log file); stop() always ends
    it: SIGINT, then SIGTERM, then SIGKILL."""

    def __init__(self, name, module, params, domain_id, log_path, pre_args=()):
        cmd = [sys.executable, "-m", module, *pre_args, "--ros-args", "-r", f"__node:={name}"]
        for k, v in params.items():
            val = f'"{v}"' if isinstance(v, str) else repr(v)
            cmd += ["-p", f"{k}:={val}"]
        env = dict(local_discovery_env(), ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED="1",
                   RCUTILS_LOGGING_BUFFERED_STREAM="0", RCUTILS_COLORIZED_OUTPUT="0")
        self.name, self.log_path = name, log_path
        self._log = open(log_path, "w")
        self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=self._log,
                                     stderr=subprocess.STDOUT, env=env,
                                     preexec_fn=start_child_as_node())

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, timeout=30.0):
        """Returns the exit status (None if it had to be killed)."""
        p = self.proc
        killed = False
        for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 5.0),
                          (signal.SIGKILL, 5.0)):
            if p.poll() is not None:
                break
            p.send_signal(sig)
            killed = sig != signal.SIGINT
            try:
                p.wait(wait)
            except subprocess.TimeoutExpired:
                pass
        self._log.close()
        return None if killed else p.returncode

    def log_tail(self, n=15) -> str:
        try:
            with open(self.log_path) as f:
                lines = f.read().splitlines()
        except OSError:
            return "(no log)"
        return "\n".join("    | " + line for line in lines[-n:])


def _call(ex, client, request, timeout, procs, what, retry_every=1.0):
    """client's response to request, sent again every retry_every s until one comes (an
    idempotent request): a service discovered a moment ago may not have matched its
    response topic yet, and that first request's response is lost."""
    t_end = time.monotonic() + timeout
    futures = []
    while True:
        futures.append(client.call_async(request))
        t_next = time.monotonic() + retry_every
        while time.monotonic() < t_next:
            for fut in futures:
                if fut.done():
                    return fut.result()
            _check_alive(procs)
            if time.monotonic() > t_end:
                raise DemoError(f"timeout ({timeout:g} s) waiting for {what}")
            ex.spin_once(timeout_sec=0.02)


def _check_alive(procs):
    for p in procs:
        if not p.alive():
            raise DemoError(f"{p.name} died (exit status {p.proc.returncode}); its log "
                            f"{p.log_path} ends with:\n{p.log_tail()}")


def drive(domain_id, stand, trot, speed, procs, echo, startup_timeout=90.0,
          run_timeout=300.0):
    """The ROS side of the demo: wait for both nodes, send /cmd_vel, switch to trot at
    t = stand, pause the sim at t_trot + trot. Returns (t_trot, t_pause, wall, sim)."""
    import rclpy
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    driver = None
    try:
        driver = _DemoDriver(ctx, speed, procs, echo)
        driver.start(startup_timeout)
        return driver.run(stand, trot, run_timeout)
    finally:
        if driver is not None:
            driver.node.destroy_node()
        rclpy.try_shutdown(context=ctx)


class _DemoDriver:
    """The demo's node: /clock read, /cmd_vel sent, the controller's ~/trot and sim_node's
    ~/pause called."""

    def __init__(self, ctx, speed, procs, echo):
        import rclpy.executors
        from geometry_msgs.msg import Twist
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock
        from std_srvs.srv import SetBool
        self.SetBool, self.procs, self.echo = SetBool, procs, echo
        self.node = node = Node("starleth_demo", context=ctx)
        self.ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
        self.ex.add_node(node)
        self.clock = {"t": None, "first": None}
        node.create_subscription(Clock, "/clock", self._on_clock,
                                 QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        self.cmd_pub = node.create_publisher(Twist, "/cmd_vel", QoSProfile(depth=10))
        self.trot_cli = node.create_client(SetBool, "/controller_node/trot",
                                           qos_profile=service_qos())
        self.pause_cli = node.create_client(SetBool, "/sim_node/pause", qos_profile=service_qos())
        self.twist = Twist()
        self.twist.linear.x = float(speed)
        self.last_cmd = None

    def _on_clock(self, msg):
        t = msg.clock.sec + msg.clock.nanosec * 1e-9
        self.clock["t"] = t
        if self.clock["first"] is None and t >= STEPPING:
            self.clock["first"] = (t, time.perf_counter())

    def _call(self, client, data, name):
        return _call(self.ex, client, self.SetBool.Request(data=data), 10.0, self.procs, name)

    def start(self, startup_timeout):
        """Both nodes up (in any order: sim_node re-sends its first state until the
        controller answers it), /cmd_vel sent, sim_node unpaused, then the first steps on
        /clock; the time-out counts silence: a node that says it is building its kernels
        makes progress."""
        procs = self.procs
        deadline = Deadline(startup_timeout, [p.log_path for p in procs])
        shown = ""
        while not (self.trot_cli.service_is_ready() and self.cmd_pub.get_subscription_count() > 0
                   and self.pause_cli.service_is_ready()):
            _check_alive(procs)
            if deadline.expired():
                raise DemoError(f"the nodes did not come up within {startup_timeout:g} s "
                                "of their last sign of life")
            if deadline.watch.last != shown:
                shown = deadline.watch.last
                self.echo(f"  {shown}")
            self.ex.spin_once(timeout_sec=0.05)
        self.cmd_pub.publish(self.twist)
        self.last_cmd = time.monotonic()
        # sim_node started paused: its clock starts now, not while this process was still
        # discovering the nodes (a lockstep run at several times real time would otherwise
        # stand longer than asked)
        res = self._call(self.pause_cli, False, "/sim_node/pause")
        self.echo(f"  nodes up; /cmd_vel linear.x = {self.twist.linear.x:g} m/s (applies once "
                  f"trotting); sim_node {res.message}")
        while self.clock["first"] is None:
            _check_alive(procs)
            if deadline.expired():
                raise DemoError(f"the simulation did not start stepping within "
                                f"{startup_timeout:g} s (no /clock beyond t = {STEPPING} s); "
                                f"see the logs {', '.join(p.log_path for p in procs)}")
            self.ex.spin_once(timeout_sec=0.05)

    def run(self, stand, trot, run_timeout):
        """Trot from t = stand, pause at t_trot + trot: (t_trot, t_pause, wall, sim)."""
        clock, t_trot = self.clock, None
        t_end = time.monotonic() + run_timeout
        while True:
            # poll /clock (depth 1: only the latest is kept) at ~200 Hz rather than taking
            # every message: this process competes for the CPU with the lockstep pair
            time.sleep(0.005)
            self.ex.spin_once(timeout_sec=0.0)
            _check_alive(self.procs)
            if time.monotonic() > t_end:
                raise DemoError(f"the run did not finish within {run_timeout:g} s (sim time "
                                f"{clock['t']:.3f} s)")
            if time.monotonic() - self.last_cmd > 0.5:    # keep /cmd_vel fresh
                self.cmd_pub.publish(self.twist)
                self.last_cmd = time.monotonic()
            t = clock["t"]
            if t_trot is None and t >= stand:
                res = self._call(self.trot_cli, True, "/controller_node/trot")
                if not res.success:
                    raise DemoError(f"/controller_node/trot refused: {res.message}")
                t_trot = clock["t"]
                self.echo(f"  t = {t_trot:.3f} s: trot ({res.message})")
            elif t_trot is not None and t >= t_trot + trot:
                res = self._call(self.pause_cli, True, "/sim_node/pause")
                wall_end = time.perf_counter()
                t_pause = clock["t"]
                self.echo(f"  t = {t_pause:.3f} s: {res.message}")
                t0, w0 = clock["first"]
                return t_trot, t_pause, wall_end - w0, t_pause - t0


def run_demo(stand=2.0, trot=18.0, speed=None, physics="HmJ", record="runs/demo.mcap",
             domain_id=None, echo=print, startup_timeout=90.0, run_timeout=300.0,
             in_process=False, bare_seconds=2.0, precompile_first=True,
             live_port=0, terrain="", robot="starleth", sensors="", drives="",
             state_source="ground_truth") -> DemoResult:
    """Run the trotting demo (see the module docstring) and return its figures. Raises
    DemoError if it could not run to the end; both nodes are always stopped.
    in_process: sim_node and controller_node in one process on one executor (the composed
    mode, ``sim_node --composed``) instead of two. bare_seconds > 0: first measure bare
    rclpy round trips for that long, the reference of the lockstep cycle rate.
    precompile_first: make the kernels ready first (starleth-precompile, with its progress
    line), so that the nodes start with them built. terrain: a course of demo/terrain.py
    ("" flat). startup_timeout counts silence: the nodes' build lines
    (compile_notice.shows_compiling) restart it. live_port > 0: the live view's port.
    robot: given to both nodes; speed None: the robot's trot speed (DemoRobot); a bad
    robot: ConfigError. sensors, drives: sim_node's sensors and actuators files (a name in
    msg_configs/sensors/, msg_configs/actuators/ or a path; "" ideal sensors, no drive
    model); state_source: controller_node's (estimator: it walks on its own estimate from
    the sensor topics, recorded and checked against the ground truth)."""
    figures = DemoRobot.of(robot)
    speed = figures.speed if speed is None else speed
    if domain_id is None:
        domain_id = default_domain_id()
    if not 0 <= domain_id <= 232:
        raise DemoError(f"ROS domain id {domain_id} out of range (0..232)")
    bag = os.path.abspath(record)
    os.makedirs(os.path.dirname(bag), exist_ok=True)
    if os.path.exists(bag):
        os.remove(bag)
    stem = os.path.splitext(bag)[0]
    result = DemoResult(bag=bag, domain_id=domain_id, physics=physics, stand=stand, trot=trot,
                        speed=speed, in_process=in_process, terrain=terrain, robot=robot,
                        fall_height=figures.fall_height, sensors=sensors, drives=drives,
                        state_source=state_source)
    where = ", ".join(x for x in (physics, terrain, sensors and f"sensors {sensors}",
                                  drives and f"drives {drives}") if x)
    label = "StarlETH" if robot == "starleth" else robot
    echo(f"{label} demo: sim_node ({where}, lockstep) + controller_node"
         + (" on its state estimate" if state_source == "estimator" else "") + " over ROS 2 "
         + ("in one process " if in_process else "") + f"(ROS_DOMAIN_ID={domain_id})")
    keep_discovery_local()      # this process's own ROS context too
    _before_the_nodes(result, domain_id, precompile_first, bare_seconds, echo)
    procs = []
    try:
        _start_demo_nodes(result, stem, live_port, echo, procs)
        result.logs = {p.name: p.log_path for p in procs}
        t_trot, t_pause, wall, sim_elapsed = drive(domain_id, stand, trot, speed, procs,
                                                   echo, startup_timeout, run_timeout)
        result.t_trot, result.wall, result.sim_elapsed = t_trot, wall, sim_elapsed
    finally:
        # the controller first (the sim is paused), then the sim: SIGINT finalises the MCAP
        for p in sorted(procs, key=lambda p: p.name != "controller_node"):
            result.exit_codes[p.name] = p.stop()
    read_bag(bag, result)
    write_replay(result, stem + ".html")
    return result


def _before_the_nodes(result, domain_id, precompile_first, bare_seconds, echo):
    """The kernels made ready (and said so) before the nodes start; the bare round trips
    measured (the reference of the cycle rate; the demo runs without it if it fails)."""
    if precompile_first:        # the kernels ready (and said so) before the nodes start
        wall, failed = precompile(stream=sys.stdout)
        if failed:
            raise DemoError("the kernels could not be made ready: "
                            + "; ".join(f"{u}: {e}" for u, e in failed))
        echo(f"  kernels ready in {wall:.1f} s")
    if bare_seconds > 0:
        try:
            result.bare_round_trips, rtt = measure_bare_round_trips(domain_id, bare_seconds)
            echo(f"  bare rclpy round trips {result.bare_round_trips:.0f}/s (median "
                 f"{rtt * 1e3:.3f} ms; the reference for the cycle rate)")
        except Exception as e:   # the demo runs without its reference
            result.bare_error = f"{type(e).__name__}: {e}"
            echo(f"  bare rclpy round trips: not measured ({result.bare_error})")


def _start_demo_nodes(result, stem, live_port, echo, procs):
    """sim_node (lockstep, recording, paused) and controller_node (stand) started for
    `result`'s run, two processes or one composed, each into `procs` as it starts (the
    caller stops them)."""
    physics, robot, domain_id, bag = result.physics, result.robot, result.domain_id, result.bag
    terrain, in_process = result.terrain, result.in_process
    sim_params = {"mode": "lockstep", "real_time_factor": 0.0, "physics": physics,
                  "record": bag, "start_paused": True, "robot": robot,
                  "sensors": result.sensors, "actuators": result.drives}
    controller = {"mode": "stand", "robot": robot, "state_source": result.state_source}
    if terrain:
        sim_params["physics_overrides"] = course_overrides(terrain)
    if live_port:
        ok, lines = live_view_lines("127.0.0.1", live_port)
        sim_params.update(live_view=ok, live_view_port=live_port)
        echo("\n".join(lines))
    if in_process:
        procs.append(NodeProcess("sim_node", "starleth_sim.ros.sim_node", sim_params,
                                 domain_id, stem + ".sim_node.log",
                                 pre_args=("--composed", *(
                                     a for k, v in controller.items()
                                     for a in ("--controller-param", f"{k}:={v}")))))
    else:
        procs.append(NodeProcess("sim_node", "starleth_sim.ros.sim_node", sim_params,
                                 domain_id, stem + ".sim_node.log"))
        procs.append(NodeProcess("controller_node", "starleth_controller.controller_node",
                                 controller, domain_id,
                                 stem + ".controller_node.log"))


def write_replay(result: DemoResult, path: str):
    """The recording as a self-contained 3D replay page (starleth-view)."""
    try:
        info = write_html(result.bag, path)
    except (BagError, ViewError, OSError) as e:
        result.html_error = str(e)
        return
    result.html, result.html_frames, result.html_bytes = (info["path"], info["frames"],
                                                          info["bytes"])


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="starleth-demo",
                                 description="StarlETH trotting demo over ROS 2 (default) or "
                                             "the headless drop test (--drop).")
    ap.add_argument("--drop", action="store_true",
                    help="run the headless drop test instead of the ROS demo")
    ap.add_argument("--preset", default="HmJ", help="physics configuration (default HmJ)")
    ap.add_argument("--height", type=float, default=0.1, help="drop test: drop height [m]")
    ap.add_argument("--seconds", type=float, default=5.0, help="drop test: simulated time [s]")
    ap.add_argument("--stand", type=float, default=2.0, help="demo: seconds standing first")
    ap.add_argument("--trot", type=float, default=18.0, help="demo: seconds of trot")
    ap.add_argument("--speed", type=float, default=None,
                    help="demo: forward speed [m/s] (default 0.3 m/s x sqrt(lambda), lambda "
                         "the robot's leg length over StarlETH's: 0.3 for StarlETH)")
    ap.add_argument("--robot", default="starleth",
                    help="the robot: a library name (robots/*.yaml), a robot spec or a URDF "
                         "path (default starleth)")
    ap.add_argument("--record", default=None,
                    help="demo: MCAP file (default runs/demo.mcap, runs/demo_<terrain>.mcap)")
    ap.add_argument("--terrain", choices=tuple(COURSES), default="",
                    help="demo: trot over this terrain course instead of flat ground")
    ap.add_argument("--domain-id", type=int, default=None,
                    help="demo: ROS domain id (default: $ROS_DOMAIN_ID, else from the pid)")
    ap.add_argument("--in-process", action="store_true",
                    help="demo: sim_node and controller_node in one process on one executor "
                         "(sim_node --composed) instead of two processes")
    ap.add_argument("--bare-seconds", type=float, default=2.0,
                    help="demo: seconds of bare rclpy round trips measured first, the "
                         "reference of the cycle rate (0: skip)")
    ap.add_argument("--live", nargs="?", type=int, const=8765, default=0, metavar="PORT",
                    help="demo: sim_node serves the Foxglove live view on PORT (8765)")
    ap.add_argument("--sensors", default="", metavar="NAME|PATH",
                    help="demo: sensor models (msg_configs/sensors/NAME.yaml, e.g. realistic, "
                         "or a file); default ideal")
    ap.add_argument("--drives", default="", metavar="NAME|PATH",
                    help="demo: drive models (msg_configs/actuators/NAME.yaml, e.g. "
                         "starleth_sea, or a file); default none")
    ap.add_argument("--state-source", choices=("ground_truth", "estimator"),
                    default="ground_truth",
                    help="demo: what the controller walks on: the simulator's base state, or "
                         "its own state estimate from the IMU, joints and foot contacts")
    return ap


def main(argv=None):
    args = _parser().parse_args(argv)
    if args.drop:
        try:
            return drop_main(args)
        except ConfigError as e:
            print(f"starleth-demo: {e}", file=sys.stderr)
            return 2
    try:
        record = args.record or os.path.join(
            "runs", f"demo_{args.terrain}.mcap" if args.terrain else "demo.mcap")
        result = run_demo(args.stand, args.trot, args.speed, args.preset, record,
                          args.domain_id, in_process=args.in_process,
                          bare_seconds=args.bare_seconds, live_port=args.live,
                          terrain=args.terrain, robot=args.robot, sensors=args.sensors,
                          drives=args.drives, state_source=args.state_source)
    except ConfigError as e:         # a bad robot, before any node starts
        print(f"starleth-demo: {e}", file=sys.stderr)
        return 2
    except DemoError as e:
        print(f"starleth-demo: FAILED: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("starleth-demo: interrupted", file=sys.stderr)
        return 130
    return 0 if print_summary(result) else 1


if __name__ == "__main__":
    raise SystemExit(main())
