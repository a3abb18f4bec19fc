"""What README.md and doc/*.md name exists: file paths, console scripts, `python -m` modules,
`make` targets, launch files and the dotted names of our packages.

The rule for what counts as a reference (anything else on the pages is prose):

* **Links** ``[text](target)`` and images: every target that is not a URL (``scheme:``) is
  a path relative to the page's own folder (as GitHub renders it) and must exist; a
  ``#anchor`` is cut off first (anchors are not checked).
* **Code**: inline spans, fenced blocks and indented blocks. In code,
  - a token with a ``/`` whose first component is a top-level entry of the repository
    (``starleth_sim``, ``doc``, ``msg_configs``, ``test``, ...: what the repository holds,
    not hidden, not the generated ``runs/``, ``build/``, ``install/``, ``log/``) must exist
    under the repository root; one whose first component is a subpackage of starleth_sim
    (``physics/``, ``ros/``, ``tools/``: the README Layout's short form) must exist under
    ``starleth_sim/``. Any other token with a ``/`` (``runs/my_run.mcap``,
    ``plots/summary.json``, topic names such as ``starleth/base_state``, ``/clock``) is a
    file the user creates or not a file at all: not checked. Tokens with placeholders
    (``<name>``, ``*``, ``{LF,RF}``, ``$VAR``) are not checked;
  - a bare file name ending in ``.py``, ``.c`` or ``.h`` (``prox.py``) must be the name of a
    file somewhere in the repository, or of a file the kernel build generates (BUILT, each
    checked to be named in ``kernels/build.py``);
  - ``starleth-<name>`` is a console script, as is the program after ``ros2 run
    starleth_sim`` or ``.venv/bin/``, and ``sim_node`` / ``controller_node`` /
    ``sim_node_composed`` at the start of a code line: each must be in setup.py's
    ``console_scripts``;
  - ``python -m X``: X must be found by ``importlib.util.find_spec`` (which imports X's
    parent packages, never X itself);
  - ``make X``: X must be a target of the Makefile;
  - ``ros2 launch starleth_sim X``: ``launch/X`` must exist;
  - a dotted name that starts with ``starleth_sim.``, ``starleth_controller.`` or
    ``starleth_interface.``: its longest prefix that is a module must exist, and the name
    after it must be a submodule or be defined at the top level of that module (read with
    ``ast``, not imported).
"""
import ast
import fnmatch
import importlib.util
import os
import re

import pytest
from repo_root import ROOT

PACKAGES = ("starleth_sim", "starleth_controller", "starleth_interface")
GENERATED = {"runs", "build", "install", "log"}
#: files the C kernels' build writes into its build directory, not kept in the repository
BUILT = {"kernel_layouts.h"}
PLACEHOLDER = re.compile(r"[<>*{}$]")
TOKEN = re.compile(r"[\w.\-/<>*{}~$]+")


def pages():
    """README.md and every doc/*.md, as (path relative to the root, text)."""
    names = ["README.md"] + sorted(os.path.join("doc", f) for f in os.listdir(
        os.path.join(ROOT, "doc")) if f.endswith(".md"))
    out = []
    for name in names:
        with open(os.path.join(ROOT, name), encoding="utf-8") as f:
            out.append((name, f.read()))
    return out


def split_code(text):
    """(prose, code lines): fenced and indented code blocks become code lines, inline code
    spans are added as code lines too; the prose keeps the rest (for the links)."""
    prose, code = [], []
    fenced = False
    previous_blank, in_indented = True, False
    for line in text.split("\n"):
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if fenced:
            code.append(line)
            continue
        if line.startswith("    ") and (previous_blank or in_indented) and line.strip():
            in_indented = True
            code.append(line.strip())
            continue
        in_indented = in_indented and not line.strip()
        previous_blank = not line.strip()
        prose.append(line)
        code.extend(m.group(1).strip() for m in re.finditer(r"``?([^`\n]+?)``?", line))
    return "\n".join(prose), code


def console_scripts():
    with open(os.path.join(ROOT, "setup.py")) as f:
        text = f.read()
    return set(re.findall(r"['\"]([\w-]+) = [\w.]+:\w+['\"]", text))


def make_targets():
    with open(os.path.join(ROOT, "Makefile")) as f:
        return set(re.findall(r"^([\w-]+):", f.read(), flags=re.M))


def top_level_entries():
    return {e for e in os.listdir(ROOT) if not e.startswith(".") and e not in GENERATED
            and not e.endswith(".egg-info")}


def file_names():
    names = set()
    for _dirpath, dirnames, files in os.walk(ROOT):
        dirnames[:] = [d for d in dirnames if not d.startswith(".") and d not in GENERATED]
        names.update(files)
    return names


def top_level_names(path):
    """The names a module defines at its top level (functions, classes, assignments,
    imports), read from its source."""
    with open(path, encoding="utf-8") as f:
        tree = ast.parse(f.read())
    names = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Assign):
            for t in node.targets:
                names.update(n.id for n in ast.walk(t) if isinstance(n, ast.Name))
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
    return names


def check_dotted(name):
    """None if `name` (starleth_sim.x.y.Z...) names a module and a name in it, else why."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        module = ".".join(parts[:i])
        try:
            spec = importlib.util.find_spec(module)
        except (ImportError, ValueError):
            spec = None
        if spec is None:
            continue
        if i == len(parts):
            return None
        attr = parts[i]
        if spec.submodule_search_locations and importlib.util.find_spec(
                f"{module}.{attr}") is not None:
            return None
        if spec.origin and spec.origin.endswith(".py") and attr in top_level_names(spec.origin):
            return None
        return f"{module} has no {attr}"
    return "no such module"


def references():
    """Every reference of the pages, as (page, kind, value)."""
    refs = []
    for page, text in pages():
        prose, code = split_code(text)
        for m in re.finditer(r"\[[^\]]*\]\(([^)\s]+)\)", prose):
            target = m.group(1)
            if re.match(r"^[a-zA-Z][\w+.-]*:", target) or target.startswith("#"):
                continue
            refs.append((page, "link", target.split("#")[0]))
        for line in code:
            for m in re.finditer(r"\bpython3? -m ([\w.]+)", line):
                refs.append((page, "python -m", m.group(1)))
            for m in re.finditer(r"(?:^|[\s(`;&|])make ([a-z][\w-]*)", line):
                refs.append((page, "make", m.group(1)))
            for m in re.finditer(r"\bros2 launch starleth_sim ([\w.]+)", line):
                refs.append((page, "launch", m.group(1)))
            for m in re.finditer(r"(?:\bros2 run starleth_sim |\.venv/bin/)([\w-]+)", line):
                refs.append((page, "script", m.group(1)))
            first = line.split()[0] if line.split() else ""
            if first in ("sim_node", "controller_node", "sim_node_composed"):
                refs.append((page, "script", first))
            for m in re.finditer(r"(?<![\w/-])(starleth-[a-z][a-z0-9-]*[a-z0-9])", line):
                refs.append((page, "script", m.group(1)))
            for m in re.finditer(r"\b((?:%s)(?:\.\w+)+)" % "|".join(PACKAGES), line):
                refs.append((page, "dotted", m.group(1)))
            for token in TOKEN.findall(line):
                token = token.rstrip(".,;:")
                if PLACEHOLDER.search(token) or "." in token.split("/")[0] and "/" in token:
                    continue
                if "/" in token:
                    refs.append((page, "path", token))
                elif re.fullmatch(r"[\w-]+\.(py|c|h)", token):
                    refs.append((page, "file name", token))
    return refs


def problem(page, kind, value, scripts, targets, tops, names):
    """None if the reference exists, else what is wrong."""
    if kind == "link":
        path = os.path.normpath(os.path.join(ROOT, os.path.dirname(page), value))
        return None if os.path.exists(path) else "no such file"
    if kind == "path":
        first = value.split("/")[0]
        if first in tops:
            return None if os.path.exists(os.path.join(ROOT, value)) else "no such file"
        if os.path.isdir(os.path.join(ROOT, "starleth_sim", first)) and first:
            return None if os.path.exists(os.path.join(ROOT, "starleth_sim", value)) \
                else "no such file under starleth_sim/"
        return None             # not ours: a file the user creates, a topic name, ...
    if kind == "file name":
        if value in BUILT:
            with open(os.path.join(ROOT, "starleth_sim", "physics", "kernels", "build.py")) as f:
                return None if value in f.read() else "not generated by kernels/build.py"
        return None if value in names else "no file of that name"
    if kind == "script":
        return None if value in scripts else "not a console script of setup.py"
    if kind == "make":
        return None if value in targets else "not a Makefile target"
    if kind == "launch":
        exists = os.path.isfile(os.path.join(ROOT, "launch", value))
        return None if exists else "no such launch file"
    if kind == "python -m":
        try:
            return None if importlib.util.find_spec(value) is not None else "no such module"
        except (ImportError, ValueError) as e:
            return f"no such module ({e})"
    if kind == "dotted":
        return check_dotted(value)
    raise AssertionError(kind)


@pytest.fixture(scope="module")
def refs():
    return references()


def test_the_pages_name_many_things(refs):
    """The rule finds real references (so the check below cannot pass on nothing)."""
    kinds = {}
    for _, kind, _ in refs:
        kinds[kind] = kinds.get(kind, 0) + 1
    assert len(refs) > 200, kinds
    for kind, least in (("link", 10), ("path", 30), ("script", 20), ("python -m", 3),
                        ("make", 3), ("dotted", 10), ("file name", 5), ("launch", 1)):
        assert kinds.get(kind, 0) >= least, (kind, kinds)


def test_everything_the_pages_name_exists(refs):
    scripts, targets = console_scripts(), make_targets()
    tops, names = top_level_entries(), file_names()
    missing = sorted({f"{page}: {kind} {value!r}: {why}" for page, kind, value in refs
                      if (why := problem(page, kind, value, scripts, targets, tops, names))})
    assert not missing, "\n".join(missing)


def test_a_stale_name_is_found():
    """The checks fail on the kinds of staleness they are for."""
    scripts, targets = console_scripts(), make_targets()
    tops, names = top_level_entries(), file_names()
    assert problem("README.md", "python -m", "starleth_sim.bench_ros", scripts, targets,
                   tops, names)
    assert problem("README.md", "dotted", "starleth_sim.ros.nodes.tf", scripts, targets,
                   tops, names)
    assert problem("README.md", "dotted", "starleth_sim.tools.view.view.no_such_function",
                   scripts, targets, tops, names)
    assert problem("README.md", "path", "starleth_sim/ros/nodes/tf.py", scripts, targets,
                   tops, names)
    assert problem("doc/physics.md", "link", "no_such_page.md", scripts, targets, tops, names)
    assert problem("README.md", "script", "starleth-no-such-tool", scripts, targets, tops,
                   names)
    assert problem("README.md", "make", "no-such-target", scripts, targets, tops, names)
    assert problem("README.md", "path", "runs/my_run.mcap", scripts, targets, tops,
                   names) is None


def test_readme_stays_a_page_for_users():
    """The README is for users (at most 400 lines; measurements go to doc/performance.md)
    and starts with the two commands."""
    with open(os.path.join(ROOT, "README.md")) as f:
        text = f.read()
    assert text.count("\n") <= 400, f"README.md has {text.count(chr(10))} lines (at most 400)"
    first_block = text[:text.index("```", text.index("```") + 3)]
    assert "make demo" in first_block and "make test" in first_block


# -- doc/architecture.md's Modules: one row per module --------------------------------------

ARCH_PACKAGES = ("starleth_sim", "starleth_controller", "starleth_interface")
MODULE_SUFFIXES = (".py", ".c", ".h", ".html")


def package_modules():
    """Every module file of the three packages (root-relative paths), the packages'
    __init__.py left out (they may be listed, need not be)."""
    found = set()
    for pkg in ARCH_PACKAGES:
        for dirpath, dirs, files in os.walk(os.path.join(ROOT, pkg)):
            dirs[:] = [d for d in dirs if d != "__pycache__"]
            for name in files:
                if name.endswith(MODULE_SUFFIXES) and name != "__init__.py":
                    found.add(os.path.relpath(os.path.join(dirpath, name), ROOT))
    return found


def architecture_rows(text, files):
    """{file: [the row paths that name it]} and the row paths that name no file, from the
    Modules tables: a section row ``| **`dir/`** |`` sets the folder its rows' paths lie
    under; a path names the files under that folder whose path ends with it (``*`` as in
    fnmatch: ``csrc/bind*.c``)."""
    named, stale = {}, []
    base = ""
    for line in text[text.index("## Modules"):].splitlines():
        if not line.startswith("| ") or line.startswith("|---"):
            continue
        first = line.split(" | ")[0][2:]
        section = re.fullmatch(r"\*\*`([\w/]+)/`\*\*", first)
        if section:
            base = section.group(1) + "/"
            continue
        if first.startswith("*") or first == "path":     # a sub-heading row, the header
            continue
        for path in re.findall(r"`([^`]+)`", first):
            hits = [f for f in files if f.startswith(base)
                    and fnmatch.fnmatch("/" + f, "*/" + path)]
            if not hits:
                stale.append(f"{path} (under {base})")
            for f in hits:
                named.setdefault(f, []).append(path)
    return named, stale


def test_architecture_lists_every_module_once():
    """doc/architecture.md's Modules tables name every module of the packages (Python, C,
    the page template) once, and no file that is not there; the README's Layout points to
    the page."""
    with open(os.path.join(ROOT, "README.md")) as f:
        readme = f.read()
    assert "(doc/architecture.md)" in readme[readme.index("## Layout"):]
    with open(os.path.join(ROOT, "doc", "architecture.md")) as f:
        text = f.read()
    files = package_modules()
    inits = {os.path.relpath(os.path.join(d, "__init__.py"), ROOT)
             for pkg in ARCH_PACKAGES for d, _, fs in os.walk(os.path.join(ROOT, pkg))
             if "__init__.py" in fs}
    named, stale = architecture_rows(text, files | inits)
    missing = sorted(files - set(named))
    twice = sorted(f for f, paths in named.items() if len(paths) > 1)
    assert not missing, f"doc/architecture.md Modules does not list {missing}"
    assert not twice, f"doc/architecture.md Modules lists these more than once: {twice}"
    assert not stale, f"doc/architecture.md Modules names files that do not exist: {stale}"


def test_architecture_rows_self_check():
    files = {"starleth_sim/physics/a.py", "starleth_sim/physics/csrc/bind_x.c",
             "starleth_sim/tools/view/recording.py", "starleth_sim/tools/replay/recording.py"}
    text = ("## Modules\n| path | what |\n|---|---|\n| **`starleth_sim/physics/`** | core |\n"
            "| `physics/a.py` | a |\n| `csrc/bind*.c`, `physics/gone.py` | b |\n"
            "| **`starleth_sim/tools/`** | tools |\n| *`tools/view/`* | view |\n"
            "| `tools/view/recording.py` | r |\n| `recording.py` | both |\n")
    named, stale = architecture_rows(text, files)
    assert stale == ["physics/gone.py (under starleth_sim/physics/)"]
    assert named == {"starleth_sim/physics/a.py": ["physics/a.py"],
                     "starleth_sim/physics/csrc/bind_x.c": ["csrc/bind*.c"],
                     "starleth_sim/tools/view/recording.py": ["tools/view/recording.py",
                                                              "recording.py"],
                     "starleth_sim/tools/replay/recording.py": ["recording.py"]}
