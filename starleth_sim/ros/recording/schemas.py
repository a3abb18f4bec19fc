"""The ``ros2msg`` schemas of a recording: a message type's name, its ``.msg`` text and the
full definition rosbag2 writes (the type's ``.msg`` file followed by every type it depends
on, each after a line of 80 ``=`` and a ``MSG: pkg/Type`` line: rosbag2's
``LocalMessageDefinitionSource`` format).

The ``.msg`` texts come from the ``share/<pkg>/msg`` directories of the message packages
(found with ``AMENT_PREFIX_PATH`` or next to the Python packages of pip-installed ROS
wheels); a type without a ``.msg`` file gets a definition generated from its Python class,
and one without a class either the text given to :func:`register_msg_text`.
"""
from __future__ import annotations

import importlib
import importlib.util
import os
import re
import sys

SEPARATOR = "=" * 80
_PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
               "int32", "uint32", "int64", "uint64", "string", "wstring"}
# field types of a .msg file: "pkg/Type", "Type", "Type[]", "Type[3]", "string<=8" ...
_MSG_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:<=\d+)?(?:\[[^\]]*\])?\s+")


# -- message types ---------------------------------------------------------------------------
def type_name(msg_type) -> str:
    """'pkg/msg/Type' of an rclpy message class (or a 'pkg/msg/Type' / 'pkg/Type' string)."""
    if isinstance(msg_type, str):
        parts = msg_type.split("/")
        if len(parts) == 2:
            return f"{parts[0]}/msg/{parts[1]}"
        if len(parts) == 3:
            return msg_type
        raise ValueError(f"not a ROS type name: {msg_type!r}")
    module = msg_type.__module__.split(".")
    return f"{module[0]}/{module[1]}/{msg_type.__name__}"


def message_class(name: str):
    """The rclpy message class of 'pkg/msg/Type' or 'pkg/Type'."""
    pkg, sub, typ = type_name(name).split("/")
    return getattr(importlib.import_module(f"{pkg}.{sub}"), typ)


def _share_dirs(pkg: str):
    """Candidate share/<pkg> directories: AMENT_PREFIX_PATH, this interpreter's prefixes and
    the prefix of the installed Python package (pip wheels put share/ beside lib/)."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes += [sys.prefix, sys.base_prefix]
    try:
        spec = importlib.util.find_spec(pkg)
        if spec is not None and spec.origin:
            d = os.path.dirname(os.path.abspath(spec.origin))   # .../lib/pythonX/site-packages/pkg
            prefixes.append(os.path.abspath(os.path.join(d, "..", "..", "..", "..")))
    except (ImportError, ValueError):
        pass
    seen = set()
    for p in prefixes:
        d = os.path.join(p, "share", pkg)
        if d not in seen:
            seen.add(d)
            yield d


_IDL_TO_MSG = {"double": "float64", "float": "float32", "boolean": "bool", "octet": "byte",
               "long double": "float64"}


def _idl_field_to_msg(t: str) -> str:
    m = re.fullmatch(r"sequence<(.+?)(?:, (\d+))?>", t)
    if m:
        inner = _idl_field_to_msg(m.group(1))
        return f"{inner}[<={m.group(2)}]" if m.group(2) else f"{inner}[]"
    m = re.fullmatch(r"(.+)\[(\d+)\]", t)
    if m:
        return f"{_idl_field_to_msg(m.group(1))}[{m.group(2)}]"
    m = re.fullmatch(r"(w?string)<(\d+)>", t)
    if m:
        return f"{m.group(1)}<={m.group(2)}"
    return _IDL_TO_MSG.get(t, t)


def generated_msg_text(name: str) -> str:
    """A .msg text generated from the rclpy class: constants and fields, no comments.
    Used only when the package's .msg file cannot be found."""
    cls = message_class(name)
    meta = type(cls)
    consts = getattr(meta, f"_{meta.__name__}__constants", {}) or {}
    lines = []
    for cname, value in consts.items():
        if isinstance(value, bytes):
            lines.append(f"byte {cname}={value[0]}")
        elif isinstance(value, bool):
            lines.append(f"bool {cname}={str(value).lower()}")
        elif isinstance(value, int):
            lines.append(f"int64 {cname}={value}")
        elif isinstance(value, float):
            lines.append(f"float64 {cname}={value!r}")
        elif isinstance(value, str):
            lines.append(f"string {cname}={value}")
    for fname, ftype in cls.get_fields_and_field_types().items():
        lines.append(f"{_idl_field_to_msg(ftype)} {fname}")
    return "\n".join(lines) + "\n"


_MSG_TEXT_CACHE: dict = {}
_FALLBACK_MSG_TEXTS: dict = {}     # 'pkg/msg/Type' -> the .msg text given to register_msg_text


def register_msg_text(name: str, text: str) -> None:
    """The .msg text of a type whose package is not installed (e.g. tf2_msgs outside a full
    ROS install), used when no .msg file is found; its dependencies must be findable."""
    _FALLBACK_MSG_TEXTS[type_name(name)] = text


def registered_msg_text(name: str) -> str | None:
    """The text register_msg_text was given for a type (None if none): what a writer
    process must be told, as it has its own registry."""
    return _FALLBACK_MSG_TEXTS.get(type_name(name))


def msg_text(name: str) -> str:
    """The .msg file text of 'pkg/msg/Type' (generated from the class if no file is found,
    or taken from register_msg_text when there is no class either)."""
    full = type_name(name)
    if full in _MSG_TEXT_CACHE:
        return _MSG_TEXT_CACHE[full]
    pkg, sub, typ = full.split("/")
    text = None
    for d in _share_dirs(pkg):
        path = os.path.join(d, sub, typ + ".msg")
        if os.path.isfile(path):
            with open(path, encoding="utf-8") as f:
                text = f.read()
            break
    if text is None:
        try:
            text = generated_msg_text(full)
        except ImportError:
            if full not in _FALLBACK_MSG_TEXTS:
                raise
            text = _FALLBACK_MSG_TEXTS[full]
    _MSG_TEXT_CACHE[full] = text
    return text


def _dependencies(text: str, pkg: str):
    """Sorted 'pkg/Type' names of the non-primitive field types of a .msg text."""
    deps = set()
    for line in text.splitlines():
        m = _MSG_FIELD_TYPE.match(line.split("#", 1)[0] + " ")
        if not m or m.group(1) in _PRIMITIVES:
            continue
        t = m.group(1)
        deps.add(t if "/" in t else f"{pkg}/{t}")
    return sorted(deps)


def message_definition(msg_type) -> str:
    """Full ``ros2msg`` schema text of a message type: its .msg text followed by every
    dependency (depth first, each once), as rosbag2 writes it."""
    root = type_name(msg_type)
    seen = set()

    def append(name):
        pkg, _, typ = type_name(name).split("/")
        text = msg_text(name)
        out = text
        for dep in _dependencies(text, pkg):
            dep_pkg, dep_typ = dep.split("/")[0], dep.split("/")[-1]
            key = f"{dep_pkg}/{dep_typ}"
            if key in seen:
                continue
            seen.add(key)
            out += f"\n{SEPARATOR}\nMSG: {key}\n" + append(f"{dep_pkg}/msg/{dep_typ}")
        return out

    return append(root)
