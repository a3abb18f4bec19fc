"""YAML: the project's one loader of configuration files (presets, physics_overrides,
sim_node's parameter file, sweep specs, initial states, robot specs, the configuration a
recording holds): a key given twice in one mapping, a file that is not UTF-8 text (e.g.
binary), a text larger than :data:`MAX_CONFIG_BYTES` or one whose aliases expand it beyond
its size is a ConfigError naming the file (and the key and its lines)."""
from __future__ import annotations

import yaml

from .config_checks import ConfigError

#: the largest configuration file read [bytes]: a preset is ~2 kB; the cap keeps a wrong
#: path (a recording, /dev/zero) from being read into memory
MAX_CONFIG_BYTES = 16 * 1024 * 1024
_MERGE_TAG = "tag:yaml.org,2002:merge"


class DuplicateKeyError(yaml.constructor.ConstructorError):
    """A mapping of a YAML document has the same key twice."""

    def __init__(self, key, line, first_line):
        self.key, self.line, self.first_line = key, line, first_line
        text = str(key) if len(str(key)) <= 60 else str(key)[:57] + "..."
        super().__init__(problem=f"duplicate key '{text}' at line {line} (first at line "
                                 f"{first_line})")


class UniqueKeyLoader(yaml.SafeLoader):
    """yaml.SafeLoader that refuses a mapping with the same key twice (PyYAML would keep
    the last one silently). Keys brought in by a merge (``<<: *base``) may be overridden,
    as YAML defines."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen = {}
            for key_node, _ in node.value:
                if key_node.tag == _MERGE_TAG:
                    continue
                key = self.construct_object(key_node, deep=True)
                line = key_node.start_mark.line + 1
                try:
                    if key in seen:
                        raise DuplicateKeyError(key, line, seen[key])
                    seen[key] = line
                except TypeError:       # an unhashable key: the base class reports it
                    continue
        return super().construct_mapping(node, deep=deep)


def _yaml_problem(e: yaml.YAMLError) -> str:
    """A YAML error in one line, with its line and column."""
    if isinstance(e, yaml.MarkedYAMLError) and e.problem:
        mark = e.problem_mark or e.context_mark
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        context = f"{e.context}: " if e.context else ""
        return f"{context}{e.problem}{where}"
    return " ".join(str(e).split())


def load_yaml_text(text: str, source: str):
    """The YAML document `text` (safe types only); ConfigError naming `source` if it is
    longer than MAX_CONFIG_BYTES, not valid YAML, repeats a key in a mapping, or if its
    aliases expand it beyond its size (:func:`_check_expansion`)."""
    if len(text) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{source}: {len(text)} characters of YAML, more than a "
                          f"configuration has ({MAX_CONFIG_BYTES // 2 ** 20} MiB)")
    try:
        data = yaml.load(text, Loader=UniqueKeyLoader)
    except DuplicateKeyError as e:
        raise ConfigError(f"{source}: {e.problem}") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{source}: not valid YAML: {_yaml_problem(e)}") from None
    except RecursionError:
        raise ConfigError(f"{source}: not valid YAML: nested too deeply") from None
    _check_expansion(data, len(text), source)
    return data


def _check_expansion(data, characters: int, source: str):
    """ConfigError where the aliases of a YAML document of `characters` characters expand it
    to more values than it has characters: a few hundred bytes of nested aliases make a
    list of a billion numbers, which a check (or numpy) would then walk. Without aliases a
    document has fewer values than characters; the walk stops at that bound."""
    budget = 2 * characters + 16
    stack = [data]
    while stack:
        x = stack.pop()
        budget -= 1
        if budget < 0:
            raise ConfigError(f"{source}: its YAML aliases expand it far beyond its "
                              f"{characters} characters")
        if isinstance(x, dict):
            stack.extend(x.keys())
            stack.extend(x.values())
        elif isinstance(x, (list, tuple)):
            stack.extend(x)


def load_yaml_file(path: str, source: str | None = None):
    """The YAML document of the file `path`, read with :func:`load_yaml_text`. ConfigError
    naming the file when it is missing, unreadable, larger than MAX_CONFIG_BYTES, not UTF-8
    text (a binary file), not valid YAML or repeats a key. `source`: the name in the
    messages about its content (default: the path as given)."""
    source = source or str(path)
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_CONFIG_BYTES + 1)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except OSError as e:
        raise ConfigError(f"{path}: cannot read: {e.strerror or e}") from None
    if len(raw) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{path}: larger than {MAX_CONFIG_BYTES // 2 ** 20} MiB, not a "
                          "configuration file")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not a YAML text file (not UTF-8: byte 0x{raw[e.start]:02x} "
                          f"at offset {e.start})") from None
    if "\x00" in text:
        raise ConfigError(f"{path}: not a YAML text file (binary: a NUL byte at offset "
                          f"{raw.index(0)})")
    return load_yaml_text(text, source)
