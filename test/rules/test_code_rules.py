"""The tree's code rules (issue #34), checked on the source with `ast` (nothing is imported):
over every module of starleth_sim, starleth_controller and starleth_interface,
- no module over MAX_LINES lines, and each starts with a docstring (its responsibility);
- no import cycle between the modules (module-level imports, and also the function-local ones
  that the local-import rule lets through with ``# deferred:``: a cycle closed inside a
  function is still a cycle; not those under ``if TYPE_CHECKING:``);
- no private name (one leading underscore, not a dunder) imported from another module of the
  project;
- function-local imports only for optional dependencies (OPTIONAL_IMPORTS: ray, mujoco,
  meshcat, matplotlib, foxglove, pyarrow; ROS packages); any other carries
  ``# deferred: <reason>`` on its line (on any line of a statement over several);
- starleth_sim.physics imports no ROS (ROS packages, starleth_sim.ros, starleth_interface's ROS
  helpers); starleth_controller imports nothing of starleth_sim; starleth_interface (shared
  by the simulator and the controllers) imports neither.
Each violation names its file, line and rule. The checker is a function of the modules'
sources, so the self-checks at the end feed it synthetic bad modules."""
import ast
import os
import re
from dataclasses import dataclass

import pytest
from repo_root import ROOT

PACKAGES = ("starleth_sim", "starleth_controller", "starleth_interface")
#: a module has one job; at this size it is time to look for a second one in it (not to
#: squeeze it: blank lines and docstrings count like code)
MAX_LINES = 700
#: a function does one thing: past this many lines it says why in its docstring
#: (``(long: <reason>)``), else it is split
MAX_FUNCTION_LINES = 60
LONG_REASON = re.compile(r"\(long:\s*\S")

# top-level names a function may import locally: optional dependencies (setup.py's extras
# included: pyarrow for starleth-sweep's parquet, foxglove and websockets for the live view)
# and ROS packages (rclpy, the rosidl runtime, the interface packages: *_msgs, *_srvs,
# *_interfaces as rcl_interfaces)
OPTIONAL_IMPORTS = {"ray", "mujoco", "meshcat", "matplotlib", "foxglove", "foxglove_sdk",
                    "pyarrow", "websockets"}
ROS_IMPORTS = {"rclpy", "ament_index_python"}
ROS_IMPORT_PATTERNS = tuple(re.compile(p) for p in (r"rosidl_\w+$", r"\w+_msgs$", r"\w+_srvs$",
                                                    r"\w+_interfaces$"))
# what starleth_sim.physics must not import (besides the ROS packages)
PHYSICS_FORBIDDEN = ("starleth_sim.ros", "starleth_interface.ros_helpers")
# ...except ament_index_python: the install's resource index (pure Python, no middleware),
# which physics.description asks, guarded, where the data (urdf/, msg_configs/) lives in a
# colcon install
PHYSICS_ALLOWED_ROS = {"ament_index_python"}
# the layers of doc/architecture.md: the ROS-free core (physics with robots) imports nothing
# of the layers above it; the ROS layer imports nothing of the tools
CORE = ("starleth_sim.physics", "starleth_sim.robots")
#: inside the core, the robot library's API stands on the physics, not beside it
PHYSICS, ROBOT_LIBRARY = ("starleth_sim.physics",), ("starleth_sim.robots",)
ABOVE_CORE = ("starleth_sim.ros", "starleth_sim.tools", "starleth_controller")
ROS_LAYER, TOOLS = ("starleth_sim.ros",), ("starleth_sim.tools",)
DEFERRED = re.compile(r"#\s*deferred:\s*\S")


@dataclass(frozen=True)
class Violation:
    path: str
    line: int
    rule: str
    message: str

    def __str__(self):
        return f"{self.path}:{self.line}: [{self.rule}] {self.message}"


@dataclass(frozen=True)
class Import:
    module: str  # the project module (or top-level external name) imported
    line: int
    names: tuple  # the names of a `from X import a, b` (empty for `import X`)
    local: bool  # inside a function
    runtime: bool  # runs at all (not under `if TYPE_CHECKING:`)
    deferred: bool  # carries `# deferred: <reason>`


def under(module, packages):
    """Whether `module` is one of `packages` or inside one."""
    return any(module == p or module.startswith(p + ".") for p in packages)


def is_ros(top):
    return top in ROS_IMPORTS or any(p.match(top) for p in ROS_IMPORT_PATTERNS)


def is_optional(top):
    return top in OPTIONAL_IMPORTS or is_ros(top)


def is_private(name):
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def find_modules(root=ROOT, packages=PACKAGES):
    """{module name: (path relative to root, source)} of every .py file of the packages."""
    modules = {}
    for package in packages:
        for dirpath, dirnames, filenames in os.walk(os.path.join(root, package)):
            dirnames[:] = sorted(d for d in dirnames if d != "__pycache__")
            for filename in sorted(filenames):
                if not filename.endswith(".py"):
                    continue
                path = os.path.relpath(os.path.join(dirpath, filename), root)
                parts = path[:-3].split(os.sep)
                if parts[-1] == "__init__":
                    parts = parts[:-1]
                with open(os.path.join(root, path), encoding="utf-8") as f:
                    modules[".".join(parts)] = (path, f.read())
    return modules


def _is_type_checking(test):
    return ((isinstance(test, ast.Name) and test.id == "TYPE_CHECKING")
            or (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"))


def _import_nodes(tree):
    """(node, local, runtime) for every import statement of a module's tree."""
    out = []

    def visit(node, local, runtime):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                out.append((child, local, runtime))
            elif isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                visit(child, True, runtime)
            elif isinstance(child, ast.If) and _is_type_checking(child.test):
                for stmt in child.body:
                    visit(ast.Module(body=[stmt], type_ignores=[]), local, False)
                for stmt in child.orelse:
                    visit(ast.Module(body=[stmt], type_ignores=[]), local, runtime)
            else:
                visit(child, local, runtime)

    visit(tree, False, True)
    return out


def module_imports(name, path, source, modules):
    """The imports of module `name` (its file `path`): each resolved to the project module it
    loads (`from pkg import sub` to pkg.sub when sub is a module), or to the external name."""
    tree = ast.parse(source, filename=path)
    lines = source.splitlines()
    is_package = os.path.basename(path) == "__init__.py"
    imports = []
    for node, local, runtime in _import_nodes(tree):
        text = "\n".join(lines[node.lineno - 1:(node.end_lineno or node.lineno)])
        deferred = bool(DEFERRED.search(text))

        def add(module, names=(), line=node.lineno, local=local, runtime=runtime,
                deferred=deferred):
            imports.append(Import(module, line, tuple(names), local, runtime, deferred))

        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name)
            continue
        if node.level:
            base = name.split(".") if is_package else name.split(".")[:-1]
            base = base[:len(base) - (node.level - 1)]
            target = ".".join(base + ([node.module] if node.module else []))
        else:
            target = node.module
        names = [a.name for a in node.names]
        submodules = [n for n in names if f"{target}.{n}" in modules]
        others = [n for n in names if f"{target}.{n}" not in modules]
        if others or not submodules:
            add(target, others)
        for n in submodules:
            add(f"{target}.{n}", ())
    return imports


def _in_project(module, modules):
    return module in modules or module.split(".")[0] in PACKAGES


def _private_module_outside(module, importer):
    """Whether `module` has a private part (pkg._mod) and `importer` is not in its package."""
    parts, importer_parts = module.split("."), importer.split(".")
    return any(is_private(part) and importer_parts[:i] != parts[:i]
               for i, part in enumerate(parts))


def _strongly_connected(graph):
    """Tarjan's strongly connected components of {node: set(successors)}."""
    index, low, stack, on_stack, components = {}, {}, [], set(), []

    def connect(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            components.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return components


def _cycle_in(component, graph):
    """One cycle through the component's first module: its modules in import order."""
    members = set(component)
    start = component[0]
    paths = {start: [start]}
    queue = [start]
    while queue:
        v = queue.pop(0)
        for w in sorted(graph[v] & members):
            if w == start:
                return paths[v]
            if w not in paths:
                paths[w] = paths[v] + [w]
                queue.append(w)
    return component


def check(modules, max_lines=MAX_LINES, max_function_lines=MAX_FUNCTION_LINES):
    """Every violation of the rules in `modules` ({name: (path, source)}), sorted."""
    violations = []
    graph = {name: set() for name in modules}
    edge_line, local_edges = {}, set()
    for name, (path, source) in sorted(modules.items()):
        tree = ast.parse(source, filename=path)
        n_lines = len(source.splitlines())
        if n_lines > max_lines:
            violations.append(Violation(path, n_lines, "module-size",
                                        f"{n_lines} lines (at most {max_lines})"))
        if ast.get_docstring(tree) is None:
            violations.append(Violation(path, 1, "module-docstring",
                                        "no module docstring (what the module is for)"))
        violations += long_functions(path, tree, max_function_lines)
        for imp in module_imports(name, path, source, modules):
            if imp.runtime and imp.module in modules and imp.module != name:
                graph[name].add(imp.module)
                if (name, imp.module) not in edge_line or (
                        (name, imp.module) in local_edges and not imp.local):
                    edge_line[name, imp.module] = imp.line
                    (local_edges.add if imp.local else local_edges.discard)((name, imp.module))
            violations += _import_violations(name, path, imp, modules)
    violations += _cycle_violations(modules, graph, edge_line, local_edges)
    return sorted(violations, key=lambda v: (v.rule, v.path, v.line))


def long_functions(path, tree, max_function_lines=MAX_FUNCTION_LINES):
    """The functions of `tree` longer than `max_function_lines` (the def line to the last)
    whose docstring does not say why: ``(long: <reason>)``."""
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        n = node.end_lineno - node.lineno + 1
        if n > max_function_lines and not LONG_REASON.search(ast.get_docstring(node) or ""):
            found.append(Violation(path, node.lineno, "function-length",
                                   f"{node.name}: {n} lines (at most {max_function_lines}, "
                                   "or a reason in its docstring: `(long: <reason>)`)"))
    return found


def _import_violations(name, path, imp, modules):
    """The violations of one import `imp` of module `name`."""
    violations = []
    top = imp.module.split(".")[0]
    if _in_project(imp.module, modules):
        for n in imp.names:
            if is_private(n):
                violations.append(Violation(
                    path, imp.line, "private-import",
                    f"imports the private name {n} from {imp.module}"))
        if _private_module_outside(imp.module, name):
            violations.append(Violation(
                path, imp.line, "private-import",
                f"imports the private module {imp.module} from outside its package"))
    if imp.local and not is_optional(top) and not imp.deferred:
        violations.append(Violation(
            path, imp.line, "local-import",
            f"function-local import of {imp.module}: hoist it to the module top, or "
            f"mark the line `# deferred: <reason>` (local imports are for optional "
            f"dependencies only: {', '.join(sorted(OPTIONAL_IMPORTS))}, ROS)"))
    if name.startswith("starleth_sim.physics") and (
            (is_ros(top) and top not in PHYSICS_ALLOWED_ROS)
            or any(imp.module == m or imp.module.startswith(m + ".")
                   for m in PHYSICS_FORBIDDEN)):
        violations.append(Violation(path, imp.line, "physics-imports-ros",
                                    f"starleth_sim.physics imports {imp.module}"))
    if name.split(".")[0] == "starleth_controller" and top == "starleth_sim":
        violations.append(Violation(path, imp.line, "controller-imports-sim",
                                    f"starleth_controller imports {imp.module}"))
    if name.split(".")[0] == "starleth_interface" and \
            top in ("starleth_sim", "starleth_controller"):
        violations.append(Violation(path, imp.line, "interface-imports-sim",
                                    f"starleth_interface imports {imp.module}"))
    return violations


def _cycle_violations(modules, graph, edge_line, local_edges):
    """One violation per import cycle of `graph`, naming each import of the cycle."""
    violations = []
    for component in _strongly_connected(graph):
        if len(component) < 2:
            continue
        cycle = _cycle_in(component, graph)
        steps = [(a, cycle[(i + 1) % len(cycle)]) for i, a in enumerate(cycle)]
        chain = ", ".join(f"{modules[a][0]}:{edge_line[a, b]} imports {b}"
                          + (" in a function" if (a, b) in local_edges else "")
                          for a, b in steps)
        first = steps[0]
        violations.append(Violation(
            modules[first[0]][0], edge_line[first], "import-cycle",
            f"import cycle {' -> '.join(cycle + [cycle[0]])} ({chain}); all modules of the "
            f"cycle: {', '.join(component)}"))
    return violations


def _report(violations):
    return "\n" + "\n".join(str(v) for v in violations)


@pytest.fixture(scope="module")
def violations():
    return check(find_modules())


RULES = ("module-size", "module-docstring", "function-length", "import-cycle", "private-import",
         "local-import", "physics-imports-ros", "controller-imports-sim",
         "interface-imports-sim")


@pytest.mark.parametrize("rule", RULES)
def test_rule(violations, rule):
    found = [v for v in violations if v.rule == rule]
    assert not found, _report(found)


def test_every_package_found():
    modules = find_modules()
    for package in PACKAGES:
        assert package in modules
    assert "starleth_sim.physics.simulator" in modules


# -- self-checks: the checker catches what it must --------------------------------------------

def _synthetic(**sources):
    """{module name: (path, source)} from keyword arguments named like pkg__mod (pkg.mod)."""
    modules = {}
    for key, source in sources.items():
        name = key.replace("__", ".")
        path = name.replace(".", "/") + ".py"
        if name in PACKAGES or name.count(".") == 0:
            path = name + "/__init__.py"
        modules[name] = (path, source)
    return modules


def _check(modules, **kwargs):
    """check's violations but a missing docstring (the synthetic modules have none mostly)."""
    return [v for v in check(modules, **kwargs) if v.rule != "module-docstring"]


def _rules(violations):
    return sorted({v.rule for v in violations})


def test_self_check_clean_modules_pass():
    modules = _synthetic(
        starleth_sim='"""pkg"""\nfrom .a import f\n',
        starleth_sim__a='"""a"""\nimport numpy as np\nfrom .b import g\n\n\ndef f():\n'
                        '    import rclpy\n    from matplotlib import pyplot\n'
                        '    from sensor_msgs.msg import Imu\n'
                        '    import json  # deferred: ordered after a notice\n'
                        '    return g, np, rclpy, pyplot, Imu, json\n',
        starleth_sim__b='"""b"""\nfrom typing import TYPE_CHECKING\nif TYPE_CHECKING:\n'
                        '    from .a import f\n\n\ndef g():\n'
                        '    from . import (  # deferred: ordered after a notice\n'
                        '        d)\n    return d, f\n',
        starleth_sim__d='"""d"""\n',
        starleth_sim__c='"""c"""\nfrom .a import __all__\nfrom ._own import x\n',
        starleth_sim___own='x = 1\n',
    )
    found = _check(modules)
    assert not found, _report(found)


def test_self_check_cycle():
    modules = _synthetic(
        starleth_sim__a='from . import b\n',
        starleth_sim__b='from starleth_sim.c import h\n',
        starleth_sim__c='import starleth_sim.a\n',
        starleth_sim__d='from .a import x\n',
        starleth_sim__e='"""e"""\nfrom .f import y\n',
        starleth_sim__f='def y():\n    from .e import z  # deferred: closes a cycle\n'
                        '    return z\n',
    )
    found = _check(modules)
    assert _rules(found) == ["import-cycle"], _report(found)
    first, second = found
    assert first.path == "starleth_sim/a.py" and first.line == 1
    for module in ("starleth_sim.a", "starleth_sim.b", "starleth_sim.c"):
        assert module in first.message
    assert "starleth_sim.d" not in first.message
    assert "starleth_sim/c.py:1 imports starleth_sim.a" in first.message
    assert second.path == "starleth_sim/e.py" and second.line == 2
    assert "starleth_sim/f.py:2 imports starleth_sim.e in a function" in second.message


def test_self_check_private_import():
    modules = _synthetic(
        starleth_sim__a='def _helper():\n    pass\n',
        starleth_sim__b='from .a import _helper\n',
        starleth_sim__c='from starleth_sim.a import (\n    public,\n    _helper,\n)\n',
        starleth_sim__d='from numpy import _private_is_theirs\n',
        starleth_interface__g='from starleth_sim._hidden import x\n',
        starleth_sim__e__ok='from .._hidden import x\n',
        starleth_sim___hidden='x = 1\n',
    )
    found = [v for v in _check(modules) if v.rule == "private-import"]
    assert [(v.path, v.line, v.rule) for v in found] == [
        ("starleth_interface/g.py", 1, "private-import"),
        ("starleth_sim/b.py", 1, "private-import"),
        ("starleth_sim/c.py", 1, "private-import")], _report(found)


def test_self_check_local_import():
    modules = _synthetic(
        starleth_sim__a='def f():\n    import json\n    from . import b\n'
                        '    from ray import remote\n    return json, b, remote\n',
        starleth_sim__b='class C:\n    def m(self):\n        from .c import f\n'
                        '        from std_msgs.msg import String\n        return f, String\n',
        starleth_sim__c='def g():\n    import json\n    return json  # deferred: not its line\n',
    )
    found = _check(modules)
    assert [(v.path, v.line, v.rule) for v in found] == [
        ("starleth_sim/a.py", 2, "local-import"),
        ("starleth_sim/a.py", 3, "local-import"),
        ("starleth_sim/b.py", 3, "local-import"),
        ("starleth_sim/c.py", 2, "local-import")], _report(found)


def test_self_check_layering_and_size():
    modules = _synthetic(
        starleth_sim__physics__x='def f():\n    import rclpy\n    return rclpy\n',
        starleth_sim__physics__y='from starleth_sim.ros import sim_node\n',
        starleth_sim__physics__w='def f():\n    from ament_index_python import packages\n'
                                 '    return packages\n',
        starleth_controller__z='import starleth_sim\n',
        starleth_interface__big='x = 1\n' * 11,
        starleth_interface__robot__s='from starleth_sim.physics import config\n',
    )
    found = _check(modules, max_lines=10)
    assert [(v.path, v.line, v.rule) for v in found] == [
        ("starleth_controller/z.py", 1, "controller-imports-sim"),
        ("starleth_interface/robot/s.py", 1, "interface-imports-sim"),
        ("starleth_interface/big.py", 11, "module-size"),
        ("starleth_sim/physics/x.py", 2, "physics-imports-ros"),
        ("starleth_sim/physics/y.py", 1, "physics-imports-ros")], _report(found)


def layer_violations(modules):
    """The imports that run up the layers of doc/architecture.md: from the core (physics,
    robots) to the ROS layer, the tools or the controller (core-imports-above), from the
    physics to the robot library's API over it (physics-imports-robots), from the ROS layer
    to the tools (ros-imports-tools)."""
    found = []
    for name, (path, source) in sorted(modules.items()):
        for imp in module_imports(name, path, source, modules):
            if under(name, CORE) and under(imp.module, ABOVE_CORE):
                found.append(Violation(path, imp.line, "core-imports-above",
                                       f"the core module {name} imports {imp.module}, of a "
                                       "layer above it"))
            if under(name, PHYSICS) and under(imp.module, ROBOT_LIBRARY):
                found.append(Violation(path, imp.line, "physics-imports-robots",
                                       f"the physics module {name} imports {imp.module}, the "
                                       "robot library's API over it"))
            if under(name, ROS_LAYER) and under(imp.module, TOOLS):
                found.append(Violation(path, imp.line, "ros-imports-tools",
                                       f"the ROS layer's {name} imports {imp.module}"))
    return found


def test_imports_point_down_the_layers():
    found = layer_violations(find_modules())
    assert not found, _report(found)


def test_self_check_layers():
    modules = _synthetic(
        starleth_sim__robots__r='from starleth_sim.tools.common import bag\n',
        starleth_sim__physics__v='from starleth_controller import controller\n',
        starleth_sim__physics__y='def f():\n    from ..ros import sim_node\n    return sim_node\n',
        starleth_sim__physics__ok='from starleth_interface import topics\n',
        starleth_sim__physics__u='from ..robots import robot_description\n',
        starleth_sim__robots__ok='from ..physics import robot_build\n',
        starleth_sim__ros__t='from ..tools import precompile\n',
        starleth_sim__ros__ok='from ..physics import config\n',
        starleth_sim__tools__ok='from starleth_controller import controller\n',
    )
    assert [(v.path, v.line, v.rule) for v in layer_violations(modules)] == [
        ("starleth_sim/physics/u.py", 1, "physics-imports-robots"),
        ("starleth_sim/physics/v.py", 1, "core-imports-above"),
        ("starleth_sim/physics/y.py", 2, "core-imports-above"),
        ("starleth_sim/robots/r.py", 1, "core-imports-above"),
        ("starleth_sim/ros/t.py", 1, "ros-imports-tools")]


def test_self_check_docstring():
    modules = _synthetic(starleth_sim__a='"""What a is for."""\nimport os\n',
                         starleth_sim__b='# a comment is no docstring\nimport os\n',
                         starleth_sim__c='')
    found = check(modules)
    assert [(v.path, v.line, v.rule) for v in found] == [
        ("starleth_sim/b.py", 1, "module-docstring"),
        ("starleth_sim/c.py", 1, "module-docstring")], _report(found)


def test_c_sources_at_most_max_lines():
    """The C kernels (``starleth_sim/physics/csrc``) follow the modules' size rule too."""
    csrc = os.path.join(ROOT, "starleth_sim", "physics", "csrc")
    sources = [f for f in os.listdir(csrc) if f.endswith((".c", ".h"))]
    assert len(sources) > 10
    long = []
    for name in sorted(sources):
        with open(os.path.join(csrc, name)) as f:
            n = sum(1 for _ in f)
        if n > MAX_LINES:
            long.append(f"starleth_sim/physics/csrc/{name}: {n} lines (at most {MAX_LINES})")
    assert not long, "\n".join(long)


def test_self_check_function_length():
    """A function over the limit is a violation unless its docstring says why."""
    body = "".join(f"    x{i} = {i}\n" for i in range(8))
    modules = _synthetic(
        starleth_sim='"""pkg"""\n',
        starleth_sim__a=f'"""a"""\n\n\ndef short():\n{body}\n\ndef long_one():\n{body * 2}'
                        f'\n\ndef long_said():\n    """(long: a table of cases)"""\n{body * 2}')
    found = [v for v in _check(modules, max_function_lines=10) if v.rule == "function-length"]
    assert [(v.path, v.line) for v in found] == [("starleth_sim/a.py", 15)], found
    assert "long_one: 17 lines" in found[0].message


def test_test_functions_follow_the_function_length_rule():
    """The tests and their helpers (test/) keep the function-length rule too."""
    found = []
    for dirpath, dirnames, filenames in os.walk(os.path.join(ROOT, "test")):
        dirnames[:] = sorted(d for d in dirnames if d != "__pycache__")
        for filename in sorted(f for f in filenames if f.endswith(".py")):
            path = os.path.join(dirpath, filename)
            with open(path, encoding="utf-8") as f:
                tree = ast.parse(f.read(), filename=path)
            found += long_functions(os.path.relpath(path, ROOT), tree)
    assert not found, _report(found)

