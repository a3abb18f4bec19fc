"""The robot library: the robot specs shipped in ``robots/`` (share/starleth_sim/robots in an
install), what a ``robot`` names (a library name, the path of a robot spec, the path of a
URDF; ``starleth.urdf``, the name the presets and older recordings use, is StarlETH), and
where a spec's URDF is: a file beside the spec, or a file of an installed Python
distribution (example-robot-data: ``make robots``)."""
from __future__ import annotations

import importlib.metadata
import os
from functools import lru_cache

from ..config_checks import ConfigError
from ..package_data import package_share_dir
from .spec import RobotSpec, read_spec

#: names kept for what recorded configurations and the presets say
ALIASES = {"starleth.urdf": "starleth"}
#: how to get the robot data packages (requirements-robots.txt)
INSTALL_HINT = "run `make robots` (pip install -r requirements-robots.txt)"
SPEC_SUFFIXES = (".yaml", ".yml")
URDF_SUFFIXES = (".urdf", ".xml")


def robots_dir() -> str:
    return os.path.join(package_share_dir(), "robots")


def available_robots() -> list[str]:
    """The library's robot names (robots/*.yaml)."""
    return sorted(os.path.splitext(f)[0] for f in os.listdir(robots_dir())
                  if f.endswith(SPEC_SUFFIXES))


def resolve(robot: str) -> tuple[str, str]:
    """("spec", path) or ("urdf", path) of a `robot` value; ConfigError naming the field."""
    if not isinstance(robot, str) or not robot:
        raise ConfigError(f"robot: expected a robot name or a path, got {robot!r}")
    robot = ALIASES.get(robot, robot)
    if robot.endswith(SPEC_SUFFIXES + URDF_SUFFIXES):
        kind = "spec" if robot.endswith(SPEC_SUFFIXES) else "urdf"
        shipped = os.path.join(robots_dir() if kind == "spec" else
                               os.path.join(package_share_dir(), "urdf"), robot)
        path = robot if os.path.isabs(robot) or os.path.exists(robot) or \
            not os.path.isfile(shipped) else shipped
        if not os.path.isfile(path):
            raise ConfigError(f"robot: no such {'robot spec' if kind == 'spec' else 'URDF'} "
                              f"file '{robot}'")
        return kind, path
    path = os.path.join(robots_dir(), robot + ".yaml")
    if os.sep in robot or not os.path.isfile(path):
        raise ConfigError(f"robot: unknown robot '{robot}' (the library: "
                          f"{', '.join(available_robots())}; or the path of a robot spec "
                          ".yaml or of a URDF)")
    return "spec", path


def _stamp(path: str):
    """What a cached read of a file is keyed by, besides its path (an edited file is read
    again)."""
    try:
        st = os.stat(path)
        return st.st_mtime_ns, st.st_size
    except OSError:
        return None


@lru_cache(maxsize=64)
def _spec_at(path: str, _stamp) -> RobotSpec:       # _stamp: part of the cache's key
    return read_spec(path)


def load_robot(robot: str) -> RobotSpec:
    """The robot spec a `robot` value names (a library name or a spec path); ConfigError for
    a URDF path (it has no spec) or a bad spec."""
    kind, path = resolve(robot)
    if kind != "spec":
        raise ConfigError(f"robot: '{robot}' is a URDF, not a robot spec")
    path = os.path.abspath(path)
    return _spec_at(path, _stamp(path))


def urdf_file(spec: RobotSpec) -> str:
    """The path of a spec's URDF; ConfigError naming the spec when it is not there (a
    distribution that is not installed: how to install it)."""
    src = spec.urdf
    if src.distribution is None:
        path = os.path.join(os.path.dirname(spec.file), src.path)
    else:
        try:
            dist = importlib.metadata.distribution(src.distribution)
        except importlib.metadata.PackageNotFoundError:
            raise ConfigError(f"{spec.label}: urdf: robot '{spec.name}' needs the Python "
                              f"package {src.distribution}, which is not installed: "
                              f"{INSTALL_HINT}") from None
        path = str(dist.locate_file(src.path))
    if not os.path.isfile(path):
        where = f" in {src.distribution} {dist.version}" if src.distribution else ""
        raise ConfigError(f"{spec.label}: urdf.path: no such file{where}: {path}")
    return os.path.normpath(path)


def robot_urdf(robot: str) -> str:
    """The URDF file a `robot` value stands for (its spec's, or the URDF path itself)."""
    kind, path = resolve(robot)
    return path if kind == "urdf" else urdf_file(load_robot(path))


def package_dirs(spec: RobotSpec) -> list[str]:
    """The roots of the URDF's package:// URIs (meshes), where the spec gives one."""
    src = spec.urdf
    if src.packages is None:
        return []
    if src.distribution is None:
        return [os.path.normpath(os.path.join(os.path.dirname(spec.file), src.packages))]
    return [str(importlib.metadata.distribution(src.distribution).locate_file(src.packages))]


def read_text(path: str) -> str:
    """A file's text (cached until it changes); ConfigError naming it when unreadable."""
    return _text_at(path, _stamp(path))


@lru_cache(maxsize=64)
def _text_at(path: str, _stamp) -> str:             # _stamp: part of the cache's key
    try:
        with open(path, encoding="utf-8") as f:
            return f.read()
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot read: {e}") from None
