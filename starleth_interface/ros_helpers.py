"""Helpers both nodes use: one parameter schema type (name, type, default, description,
bounds) that feeds ``declare_parameter`` descriptors, validation and the YAML parameter
files, and the check that every parameter given to a node is one it has; the executor
choice; throttled logging of bad input (per problem: kind and detail); Python ``logging``
forwarded to the node's rclpy logger.

Importing this module does not import rclpy (only the functions that need it do), so the
ROS-free service logic and the tools can use the schemas and ThrottledLog.
"""
from __future__ import annotations

import difflib
import itertools
import logging
import math
import os
import signal
import sys
import textwrap
import time
from dataclasses import dataclass, field
from typing import ClassVar

import yaml


# =========================================================================================
# parameter schema
# =========================================================================================
@dataclass(frozen=True)
class ParameterSpec:
    """One ROS parameter: `kind` is bool, int, float, str or list; `choices` the legal
    values of a string; `minimum` a lower bound of a number (exclusive with
    `minimum_exclusive`), `maximum` an upper bound (inclusive); `off_value` one more legal
    value of a number outside those bounds, which switches the feature off (e.g. 0 for
    record_max_size: 0 = no split, else >= 1 MiB), `off_meaning` what it means in words.
    Numbers must be finite. `read_only` parameters are fixed once the node runs.
    ``range_text()`` renders the bounds (in the parameter file's comments and as the
    descriptor's additional_constraints, shown by ``ros2 param describe``)."""

    name: str
    kind: type
    default: object
    description: str
    read_only: bool = True
    choices: tuple = ()
    minimum: float | None = None
    minimum_exclusive: bool = False
    maximum: float | None = None
    off_value: float | None = None
    off_meaning: str = "off"

    def range_text(self) -> str:
        """The legal values in words, e.g. "0 (no split) or >= 1048576" or "> 0 and
        <= 3600"; empty when there are no bounds."""
        if self.choices:
            return "one of " + ", ".join(map(str, self.choices))
        parts = []
        if self.minimum is not None:
            parts.append(f"{'>' if self.minimum_exclusive else '>='} "
                         f"{_bound(self.minimum)}")
        if self.maximum is not None:
            parts.append(f"<= {_bound(self.maximum)}")
        text = " and ".join(parts)
        if self.off_value is not None:
            off = f"{_bound(self.off_value)} ({self.off_meaning})"
            text = f"{off} or {text}" if text else off
        return text

    def coerce(self, value):
        """The value as given on the command line or in YAML, brought to `kind` where that
        loses nothing (an integer for a float, null for an empty string)."""
        if self.kind is float and isinstance(value, int) and not isinstance(value, bool):
            return float(value)
        if self.kind is str and value is None:
            return ""
        if self.kind is list and isinstance(value, tuple):
            return list(value)
        return value

    def check(self, value):
        """Raise ValueError naming the parameter if `value` is not legal."""
        what = f"parameter {self.name}"
        if self.kind is bool:
            if not isinstance(value, bool):
                raise ValueError(f"{what}: expected true or false, got {value!r}")
            return
        if self.kind in (int, float):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                    (self.kind is int and not isinstance(value, int)):
                expected = "an integer" if self.kind is int else "a finite number"
                raise ValueError(f"{what}: expected {expected}, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"{what}: expected a finite number, got {value!r}")
            if self.off_value is not None and value == self.off_value:
                return
            lo, hi = self.minimum, self.maximum
            if (lo is not None and (value < lo or (self.minimum_exclusive and value == lo))) \
                    or (hi is not None and value > hi):
                raise ValueError(f"{what}: must be {self.range_text()}, got {value!r}")
            return
        if not isinstance(value, self.kind):
            raise ValueError(f"{what}: expected a {self.kind.__name__}, got {value!r}")
        if self.choices and value not in self.choices:
            raise ValueError(f"{what}: must be one of {', '.join(map(str, self.choices))}, "
                             f"got {value!r}")


def _bound(x) -> str:
    """A bound in a message: integral values without exponent (1048576, not 1.04858e+06)."""
    if isinstance(x, float) and x.is_integer() and abs(x) < 1e15:
        return str(int(x))
    return f"{x:g}" if isinstance(x, float) else str(x)


def parameter_defaults(specs) -> dict:
    return {p.name: p.default for p in specs}


def declare_parameters(node, specs) -> dict:
    """Declare every parameter of `specs` on the rclpy `node` with its description and
    read-only flag (dynamic typing: `-p threshold:=5`, an integer, is accepted for a float
    and coerced) and return {name: value}. Values are not checked here: call each
    spec's ``check`` (or the settings record's ``validate``)."""
    from rcl_interfaces.msg import ParameterDescriptor
    values = {}
    for p in specs:
        desc = ParameterDescriptor(description=p.description, read_only=p.read_only,
                                   dynamic_typing=True,
                                   additional_constraints=p.range_text())
        values[p.name] = p.coerce(node.declare_parameter(p.name, p.default, desc).value)
    return values


#: parameters of ROS itself, which a node accepts besides its schema's: rclpy declares the
#: first two on every node, and a publisher or subscription with QoS overriding declares its
#: qos_overrides.<topic>.<entity>.<policy> parameters
ROS_PARAMETERS = ("use_sim_time", "start_type_description_service")
ROS_PARAMETER_PREFIXES = ("qos_overrides.",)


class UnknownParameterError(ValueError):
    """Parameters given to a node (``-p``, ``--params-file``, ``parameter_overrides``) that
    it does not have (rclpy would ignore them). Its text is one line naming each with the
    closest known name, e.g. ``unknown parameter 'recrod' (did you mean 'record'?)``."""


def check_parameter_names(node, specs) -> None:
    """Raise UnknownParameterError if a parameter override of the rclpy `node` names neither
    a parameter of `specs` nor one of ROS's own (ROS_PARAMETERS, ROS_PARAMETER_PREFIXES, or
    any the node has declared). Call it after declaring the schema's parameters."""
    known = [p.name for p in specs] + list(ROS_PARAMETERS)
    unknown = [name for name in parameter_override_names(node)
               if name not in known and not name.startswith(ROS_PARAMETER_PREFIXES)
               and not node.has_parameter(name)]
    if unknown:
        raise UnknownParameterError(unknown_parameters_text(unknown, known))


def unknown_parameters_text(unknown, known) -> str:
    """The line "unknown parameter 'recrod' (did you mean 'record'?)" for the names `unknown`,
    each with the closest of `known` (difflib) if one is close."""
    parts = []
    for name in sorted(unknown):
        close = difflib.get_close_matches(name, known, n=1)
        parts.append(repr(name) + (f" (did you mean {close[0]!r}?)" if close else ""))
    return f"unknown parameter{'s' if len(parts) > 1 else ''} " + ", ".join(parts)


def parameter_override_names(node) -> list:
    """The names of the parameter overrides rcl resolved for the rclpy `node` (its ``-p``
    rules, the keys of ``--params-file`` files that match its name and namespace, wildcards
    included) and those given to its constructor. rclpy has no public accessor for them
    (it keeps them to initialise declared parameters and ignores the rest): this reads its
    attribute, and a test (test_strict_inputs) fails if rclpy stops having it."""
    return list(getattr(node, "_parameter_overrides", None) or ())


def _yaml_scalar(value) -> str:
    return yaml.safe_dump(value, default_flow_style=True, width=10 ** 6).strip() \
        .removesuffix("...").strip()


#: the ROS type names of the parameter kinds (the doc tables' type column)
ROS_TYPE_NAMES = {str: "string", float: "double", int: "integer", bool: "bool"}


def parameter_table_row(p) -> str:
    """The markdown row of parameter `p` in a doc page's parameter table: name, ROS type,
    default, legal values (range_text, or "any"), description ('|' escaped)."""
    if p.kind is bool:
        default = "true" if p.default else "false"
    elif p.kind is str:
        default = f'"{p.default}"'
    else:
        default = repr(p.default) if p.kind is float else str(p.default)
    cells = [f"`{p.name}`", ROS_TYPE_NAMES[p.kind], f"`{default}`", p.range_text() or "any",
             p.description]
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


def with_parameter_table(page: str, specs) -> str:
    """`page` (markdown) with the rows of its parameter table (the lines starting with
    "| `name` |" for a parameter of `specs`) rendered from the schema."""
    rows = {p.name: parameter_table_row(p) for p in specs}
    out = []
    for line in page.split("\n"):
        name = line[3:].split("`", 1)[0] if line.startswith("| `") else None
        out.append(rows[name] if name in rows else line)
    return "\n".join(out)


def render_parameters_yaml(specs, header: str, node_key: str = "/**") -> str:
    """A ROS 2 parameter file (``--params-file``) with every parameter at its default and
    its description and its legal values (``range_text``) as a comment above it."""
    out = [f"# {line}".rstrip() for line in header.strip().splitlines()]
    out += [f"{node_key}:", "  ros__parameters:"]
    for p in specs:
        for line in textwrap.wrap(p.description, 88):
            out.append(f"    # {line}")
        if p.range_text():
            for line in textwrap.wrap(f"Legal values: {p.range_text()}.", 88):
                out.append(f"    # {line}")
        out.append(f"    {p.name}: {_yaml_scalar(p.default)}")
    return "\n".join(out) + "\n"


# =========================================================================================
# CPU scheduling
# =========================================================================================
CPU_SCHEDULING = ("default", "batch")
CPU_SCHEDULING_HELP = (
    "default (as started) | batch: every thread of the process (the DDS threads included, "
    "and those it starts later) under SCHED_BATCH, i.e. not preempting the thread that "
    "wakes it: with the simulator and the controller sharing a CPU, a state message no "
    "longer switches to the controller in the middle of the simulator's publishing, nor "
    "the command back to the simulator inside the controller's publish (lockstep: fewer "
    "context switches per cycle; not for the realtime mode, whose ticks want prompt "
    "wake-ups). Needs no privileges.")


#: requests and responses a service and each of its clients keep (SERVICE_QUEUE deep:
#: service_qos). With Fast DDS every client of a service also receives the responses to
#: the other clients, so a client of rclpy's default depth (10) loses its own response when
#: more calls are answered at once: 100 concurrent calls of sim_node's ~/reset, ~/step,
#: ~/pause got 33, 15 and 21 answers at depth 10, all 100 at depth 100 (doc/sim_node.md)
SERVICE_QUEUE = 1000


def service_qos():
    """The QoS profile of the services of both nodes and of every client that calls them:
    reliable, volatile, the last SERVICE_QUEUE requests and responses kept."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(depth=SERVICE_QUEUE, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)


def set_cpu_scheduling(policy: str):
    """Apply `policy` (CPU_SCHEDULING) to every thread of this process: 'batch' =
    SCHED_BATCH (threads started later inherit it from their creator), 'default' changes
    nothing. Returns None, or the reason it could not be applied (one line)."""
    if policy == "default":
        return None
    if policy != "batch":
        return f"unknown CPU scheduling {policy!r} (expected one of {', '.join(CPU_SCHEDULING)})"
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
        for tid in tids:
            os.sched_setscheduler(tid, os.SCHED_BATCH, os.sched_param(0))
    except (OSError, AttributeError, ValueError) as e:
        return f"SCHED_BATCH not applied: {e}"
    return None


# =========================================================================================
# executor, logging
# =========================================================================================
EXECUTORS = ("events", "single_threaded")


def make_executor(kind: str, context):
    """(executor, kind): rclpy's C++ EventsExecutor (much cheaper spin_once) when `kind` is
    'events' and it is available, else the SingleThreadedExecutor."""
    import rclpy.executors
    if kind == "events":
        try:
            from rclpy.experimental import EventsExecutor
            return EventsExecutor(context=context), "events"
        except Exception:  # pragma: no cover - rclpy without the EventsExecutor
            pass
    return rclpy.executors.SingleThreadedExecutor(context=context), "single_threaded"


@dataclass
class ThrottledLog:
    """At most one message per `period` seconds per problem, a problem being a kind (e.g.
    'unknown_joint') and a detail that names the thing (the joint, the link, the topic...):
    each distinct problem is logged at least once, and its next message says how many like
    it were suppressed. `counts` has every occurrence by kind. Call it (or ``warn``) with
    (kind, message, detail); returns whether the message was logged.

    At most MAX_DETAILS details of one kind are throttled apart (a flood of distinct names
    cannot flood the log): the further ones share one throttle, and the first of them says
    so."""

    MAX_DETAILS: ClassVar[int] = 32

    log: object = None
    period: float = 2.0
    clock: object = time.monotonic
    counts: dict = field(default_factory=dict)
    _last: dict = field(default_factory=dict, repr=False)
    _suppressed: dict = field(default_factory=dict, repr=False)
    _details: dict = field(default_factory=dict, repr=False)

    def __call__(self, kind: str, message: str, detail: str = "") -> bool:
        self.counts[kind] = self.counts.get(kind, 0) + 1
        key = (kind, detail)
        if key not in self._last:
            n = self._details.get(kind, 0)
            if n >= self.MAX_DETAILS:
                key = (kind, None)             # the overflow: one throttle for the rest
                if key not in self._last:
                    message += (f" (more than {self.MAX_DETAILS} distinct problems of this "
                                "kind: the further ones are throttled together)")
            else:
                self._details[kind] = n + 1
        now = self.clock()
        last = self._last.get(key)
        if last is not None and now - last < self.period:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return False
        n = self._suppressed.pop(key, 0)
        self._last[key] = now
        if n:
            message += f" ({n} more like this suppressed in the last {now - last:.1f} s)"
        if self.log is not None:
            self.log(message)
        return True

    warn = __call__


class RosLogHandler(logging.Handler):
    """Forwards Python ``logging`` records to an rclpy logger (the node's), the level mapped
    (the numbers are the same: DEBUG 10 ... ERROR 40, CRITICAL 50 = FATAL): the physics
    core, which imports no ROS, logs through ``logging``, and in a node its messages come
    out in the node's format, ``[WARN] [...] [sim_node]: ...``, and on /rosout."""

    def __init__(self, ros_logger):
        super().__init__()
        self.ros_logger = ros_logger

    def emit(self, record):
        try:
            msg = self.format(record)
            log = self.ros_logger
            # one call site per severity: rclpy refuses a call site that changes severity
            if record.levelno >= logging.CRITICAL:
                log.fatal(msg)
            elif record.levelno >= logging.ERROR:
                log.error(msg)
            elif record.levelno >= logging.WARNING:
                log.warning(msg)
            elif record.levelno >= logging.INFO:
                log.info(msg)
            else:
                log.debug(msg)
        except Exception:   # a context already shut down: never let logging raise
            self.handleError(record)


def route_python_logging(ros_logger, names=("starleth_sim", "starleth_controller",
                                            "starleth_interface")):
    """Forward the Python loggers `names` (and their children) to the rclpy `ros_logger`,
    their level set to its effective one; a logger another node of this process forwards
    already is left to it. Returns a function that undoes what this call did (call it when
    the node is destroyed)."""
    level = int(ros_logger.get_effective_level())       # LoggingSeverity, an IntEnum
    undo = []
    for name in names:
        py_logger = logging.getLogger(name)
        if any(isinstance(h, RosLogHandler) for h in py_logger.handlers):
            continue
        handler = RosLogHandler(ros_logger)
        old_level = py_logger.level
        py_logger.addHandler(handler)
        py_logger.setLevel(level)
        undo.append((py_logger, handler, old_level))

    def restore():
        for py_logger, handler, old_level in undo:
            py_logger.removeHandler(handler)
            py_logger.setLevel(old_level)
        undo.clear()
    return restore


def capture_python_warnings(ros_logger):
    """Python ``warnings`` (numpy's, pinocchio's...) of this process through the rclpy
    `ros_logger` instead of bare lines on stderr (``logging.captureWarnings``: process-wide,
    for a node's console script)."""
    logging.captureWarnings(True)
    return route_python_logging(ros_logger, ("py.warnings",))


# =========================================================================================
# process life cycle of a node's console script
# =========================================================================================
def init_ros(prog: str, argv) -> bool:
    """rclpy.init with the given argv and without rclpy's own signal handlers (the
    node's StopSignals decide what a signal does). False, with one line on stderr, when
    ROS cannot start (e.g. a malformed --ros-args rule)."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as e:
        print(f"{prog}: cannot initialise ROS: {e}" + mapping_override_hint(argv),
              file=sys.stderr)
        return False
    return True


def mapping_override_hint(argv) -> str:
    """For a `-p name:={...}` rule in argv (ROS parses the value as YAML, and a mapping is
    no parameter type: rcl says "Unknown YAML event"), the line saying how to pass it as the
    string a parameter such as physics_overrides takes; "" when there is none."""
    argv = list(argv or ())
    for flag, rule in itertools.pairwise(argv):
        name, sep, value = rule.partition(":=")
        if flag in ("-p", "--param") and sep and value.lstrip().startswith("{"):
            return (f"\n{flag} {rule}: ROS reads a value in braces as a YAML mapping, which no "
                    "parameter type holds; quote it once more so that ROS reads a string: "
                    f"-p \"{name}:='{value}'\"")
    return ""


class StopSignals:
    """SIGINT and SIGTERM set `requested` and call on_stop(); the third one raises
    KeyboardInterrupt (give up on a clean exit). ``ignore()`` while finalising."""

    def __init__(self, on_stop=None):
        self.count = 0
        self.on_stop = on_stop
        signal.signal(signal.SIGINT, self._handle)
        signal.signal(signal.SIGTERM, self._handle)

    @property
    def requested(self) -> bool:
        return self.count > 0

    def _handle(self, _signum, _frame):
        self.count += 1
        if self.on_stop is not None:
            self.on_stop()
        if self.count > 2:
            raise KeyboardInterrupt

    @staticmethod
    def ignore():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)


def shutdown_ros(node=None, executor=None):
    """Shut the executor down, destroy the rclpy node and shut ROS down, ignoring errors
    of a context that is already gone."""
    import rclpy
    for close in ((lambda: executor.shutdown(timeout_sec=0.1)) if executor else None,
                  node.destroy_node if node is not None else None):
        if close is None:
            continue
        try:
            close()
        except Exception:
            pass
    rclpy.try_shutdown()
