"""The checks of configuration values (physics/config.py, physics/terrain.py): each returns
the value (a number as a float) or raises :class:`ConfigError` with one line naming the
field (`path`) and the rule it broke."""
from __future__ import annotations

import math


class ConfigError(ValueError):
    """A configuration value is missing, of the wrong type, or out of range."""


def fmt_bound(x) -> str:
    """A bound or value for a message: integers without exponent (10000, not 1e+04)."""
    if isinstance(x, int) and not isinstance(x, bool):
        return str(x)
    x = float(x)
    if math.isfinite(x) and x.is_integer() and abs(x) < 1e15:
        return str(int(x))
    return f"{x:g}"


def short_repr(v, limit=60) -> str:
    """repr(v), cut to `limit` characters (a hostile value must not flood the message)."""
    r = repr(v) if not isinstance(v, int) or isinstance(v, bool) or abs(v) < 10 ** 30 \
        else f"{'-' if v < 0 else ''}an integer of {len(str(abs(v)))} digits"
    return r if len(r) <= limit else r[:limit - 3] + "..."


def check_number(path, v, lo=None, hi=None, lo_open=False, hi_open=False):
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ConfigError(f"{path}: expected a number, got {short_repr(v)}")
    try:
        x = float(v)
    except OverflowError:      # an integer beyond the floats
        x = math.inf if v > 0 else -math.inf
    if not math.isfinite(x):
        raise ConfigError(f"{path}: must be finite, got {short_repr(v)}")
    if lo is not None and (x < lo or (lo_open and x == lo)):
        raise ConfigError(f"{path}: must be {'>' if lo_open else '>='} {fmt_bound(lo)}, "
                          f"got {fmt_bound(x)}")
    if hi is not None and (x > hi or (hi_open and x == hi)):
        raise ConfigError(f"{path}: must be {'<' if hi_open else '<='} {fmt_bound(hi)}, "
                          f"got {fmt_bound(x)}")
    return x


def check_int(path, v, lo=None, hi=None):
    if isinstance(v, bool) or not isinstance(v, int):
        raise ConfigError(f"{path}: expected an integer, got {short_repr(v)}")
    if lo is not None and v < lo:
        raise ConfigError(f"{path}: must be >= {lo}, got {short_repr(v)}")
    if hi is not None and v > hi:
        raise ConfigError(f"{path}: must be <= {fmt_bound(hi)}, got {short_repr(v)}")
    return int(v)


def check_choice(path, v, choices):
    if not isinstance(v, str) or v not in choices:
        raise ConfigError(f"{path}: must be one of {sorted(choices)}, got {short_repr(v)}")
    return v


def check_bool(path, v):
    if not isinstance(v, bool):
        raise ConfigError(f"{path}: expected true or false, got {short_repr(v)}")
    return v


def check_str(path, v):
    if not isinstance(v, str):
        raise ConfigError(f"{path}: expected a string, got {short_repr(v)}")
    return v
