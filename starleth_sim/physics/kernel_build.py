"""Builds the C physics kernels (``csrc/*.c``) into the extension module
``starleth_sim.physics._kernels``.

One build for every way the package is installed: ``setup.py`` (pip, colcon) calls `build`
for its extension, and in a source checkout `starleth_sim.physics.kernels` calls it when the
sources changed since the module was built (their digest, with the flags, is written beside
the module), so that an edit never runs stale machine code. The sources compile in parallel
processes, in a few seconds.

Flags: the kernels' results are pinned bit for bit (test/test_bitexact.py), so no flag may
change the floating-point results: ``-ffp-contract=off`` (no fused multiply-adds, which GCC
forms by default where the CPU has them), no ``-ffast-math`` or any of its parts that
reassociate or assume finite values. ``-fno-math-errno`` only lets sqrt compile to one
instruction (the same correctly rounded value). ``-O3`` and the machine's own instruction
set (`ARCH`) vectorize the loops over independent entries (the maximal coordinates' JOR
sweep: HMJP 6,100 -> 10,600 steps/s against -O2 for the default target, measured).

The build also writes the header ``kernel_layouts.h`` (`c_header`), which the sources include
through ``step.h``: the C side of the packed layouts and named results that
:mod:`starleth_sim.physics.kernel_layouts` declares (the structs the one-kernel steps unpack
their buffers into, the unpacking and its length checks, the decoders of the settings
records, the result structs and their Python types), so that each layout is written once. It
goes into the build's own directory, not the sources (``python -m
starleth_sim.physics.kernel_build --header`` prints it), and its text is part of the digest.

Standard library only: setup.py loads this file before anything is installed (and this file
loads kernel_layouts by its path).
"""
from __future__ import annotations

import functools
import hashlib
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor

HERE = os.path.dirname(os.path.abspath(__file__))
CSRC = os.path.join(HERE, "csrc")
MODULE = "_kernels"
#: the file of the built module, and the digest of what it was built from, in the package
SUFFIX = sysconfig.get_config_var("EXT_SUFFIX") or ".so"
DIGEST_SUFFIX = ".digest"
#: a source checkout's object files (kernels.ensure_built), beside the module
OBJECTS = ".kernel_objects"

#: the target CPU: this machine's (``-march=native``, as numba's JIT targeted it), or what
#: $STARLETH_KERNEL_ARCH names (empty: the compiler's default target, for a build that runs
#: on other machines than the one it was built on). Vector instructions change no result:
#: without reassociation only independent entries are computed side by side.
ARCH = os.environ.get("STARLETH_KERNEL_ARCH", "native")
FLAGS = ("-std=gnu11", "-O3", "-ffp-contract=off", "-fno-math-errno", "-fPIC",
         "-fvisibility=hidden", "-Wall") + ((f"-march={ARCH}",) if ARCH else ())


#: the generated header, in the build's include directory
LAYOUT_HEADER = "kernel_layouts.h"


def _load_layouts():
    """kernel_layouts, loaded by its path (setup.py loads this file outside the package)."""
    spec = importlib.util.spec_from_file_location("_starleth_kernel_layouts",
                                                  os.path.join(HERE, "kernel_layouts.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class BuildError(RuntimeError):
    """The C compiler failed (its output is in the message) or was not found."""


def sources(csrc: str = CSRC) -> list[str]:
    """The C sources (.c) of the kernels, sorted."""
    return sorted(os.path.join(csrc, f) for f in os.listdir(csrc) if f.endswith(".c"))


def source_digest(csrc: str = CSRC) -> str:
    """SHA-256 over the kernels' sources and headers (names and contents, the generated
    header's too), the flags and the Python ABI the module is built for."""
    h = hashlib.sha256()
    h.update(" ".join(FLAGS).encode())
    h.update(SUFFIX.encode())
    h.update(c_header().encode())
    for name in sorted(os.listdir(csrc)):
        if name.endswith((".c", ".h")):
            h.update(name.encode() + b"\0")
            h.update(_read_bytes(os.path.join(csrc, name)))
    return h.hexdigest()


def compiler() -> list[str]:
    """The C compiler command: $CC, else Python's own (sysconfig), else cc."""
    cc = os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc"
    cmd = cc.split()
    if shutil.which(cmd[0]) is None:
        for alt in ("cc", "gcc", "clang"):
            if shutil.which(alt):
                return [alt]
        raise BuildError("no C compiler found (install gcc, e.g. `sudo apt install gcc`, or "
                         "set CC)")
    return cmd


def _python_include() -> str:
    inc = sysconfig.get_paths()["include"]
    if not os.path.exists(os.path.join(inc, "Python.h")):
        raise BuildError(f"Python.h not found in {inc}: install Python's headers (e.g. `sudo "
                         f"apt install python{sys.version_info[0]}.{sys.version_info[1]}-dev`)")
    return inc


def _run(cmd):
    p = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if p.returncode != 0:
        raise BuildError(f"{' '.join(cmd)}\n{p.stdout}")
    return p.stdout


def _read_bytes(path: str) -> bytes:
    with open(path, "rb") as f:
        return f.read()


def _object_key(src: str, cc, headers: bytes) -> str:
    """What an object file depends on: the compiler command, the flags, the Python headers'
    place, every header of the kernels and the source itself."""
    h = hashlib.sha256()
    h.update(" ".join(cc + list(FLAGS)).encode() + b"\0" + _python_include().encode())
    h.update(headers)
    h.update(_read_bytes(src))
    return h.hexdigest()[:32]


# -- the generated header (kernel_layouts' declarations in C) ------------------------------

def _c_string(text: str) -> str:
    return json.dumps(text, ensure_ascii=False)


def _upper(name: str) -> str:
    """CamelCase or snake_case -> UPPER_SNAKE."""
    out = ""
    for i, ch in enumerate(name):
        if ch.isupper() and i and not name[i - 1].isupper() and name[i - 1] != "_":
            out += "_"
        out += ch.upper()
    return out


def _c_record(r, L) -> list[str]:
    """A record's length and decoder (its fields from floats)."""
    lines = [f"/* {r.name} (kernel_layouts): {len(r.fields)} numbers as floats */",
             f"#define {_upper(r.name)}_LENGTH {len(r.fields)}",
             f"static inline void {r.c_decoder}(const double *f, {r.c_struct} *out) {{"]
    for k, f in enumerate(r.fields):
        value = {"double": f"f[{k}]", "i64": f"(i64)f[{k}]", "bool": f"f[{k}] != 0.0"}[f.kind]
        lines.append(f"    out->{f.name} = {value}; /* {f.doc} */")
    return lines + ["}", ""]


def _c_result_struct(r, L) -> list[str]:
    lines = [f"/* {r.name}: {r.doc} */", "typedef struct {"]
    lines += [f"    {L.C_TYPES[f.kind]} {f.name}; /* {f.doc} */" for f in r.fields]
    return lines + [f"}} {r.c_struct};", ""]


def _c_packed_buffers(L) -> list[str]:
    """packed_model_t: every buffer of the layouts with a header, with its length."""
    ctype = {"float64": "double *", "int64": "const i64 *", "bool": "const u8 *"}
    names = {}
    for layout in L.LAYOUTS:
        if layout.header():
            for b in layout.buffers:
                names.setdefault(b.name, ctype[b.dtype])
    lines = ["/* The packed buffers of a kernel model (TreeStepModel, CutModel), with their "
             "lengths */", "typedef struct {"]
    for name, t in names.items():
        lines += [f"    {t}{name};", f"    i64 n_{name};"]
    return lines + ["} packed_model_t;", ""]


def _c_layout(layout, L) -> list[str]:
    """A layout's struct, its length functions and its unpacking."""
    header = layout.header()
    standalone = not header
    t = f"{layout.c_name}_t"
    view_type = {"float64": "double *", "int64": "const i64 *", "bool": "const u8 *"}
    lines = [f"/* {layout.name} (kernel_layouts.{_upper(layout.name)}), unpacked */",
             "typedef struct {"]
    lines += [f"    {ctype} {member};" for ctype, member in layout.members]
    for b in layout.buffers:
        for f in b.fields:
            if not f.target or "." in f.target:
                continue
            if f.kind in L.HEADER_KINDS:
                decl = f"i64 {f.target}"
            elif f.kind == "value":
                decl = f"double {f.target}"
            elif f.kind == "record":
                decl = f"{f.record.c_struct} {f.target}"
            else:
                decl = f"{view_type[b.dtype]}{f.target}"
            lines.append(f"    {decl}; /* {f.name}: {f.doc} */")
    lines += [f"}} {t};", ""]
    sizes = [f.name for f in header] + list(layout.context)
    params = ", ".join(f"i64 {n}" for n in sizes)
    lengths = {b.name: " + ".join(f"({L.field_size(f)})" for f in b.fields)
               for b in layout.buffers}
    if standalone:
        (b,) = layout.buffers
        lines += [f"/* the length of a {layout.name} */",
                  f"static inline i64 {layout.c_name}_length({params}) {{",
                  f"    return {lengths[b.name]};", "}", "",
                  f"/* the views of a {layout.name} buffer of {layout.c_name}_length entries */",
                  f"static inline void {layout.c_name}_views(double *{b.name}, {params}, "
                  f"{t} *out) {{", "    i64 o = 0;"]
        for f in b.fields:
            lines += [f"    out->{f.target} = {b.name} + o;",
                      f"    o += {L.field_size(f)};"]
        return lines + ["    (void)o;", "}", ""]
    ctx = "".join(f", i64 {n}" for n in layout.context)
    n_header = len(header)
    lines += [f"#define {_upper(layout.name)}_HEADER {n_header}"]
    lines += [f"#define {_upper(layout.name)}_{f.name.upper()} {k} /* ints[{k}]: {f.doc} */"
              for k, f in enumerate(header)]
    lines += [
              f"/* unpack_{layout.c_name}: the views of a {layout.name}'s buffers; 0 (nothing "
              "written) if the header is short or negative or a buffer's length is not the "
              "layout's for the header's sizes */",
              f"static inline int unpack_{layout.c_name}(const packed_model_t *pm{ctx}, "
              f"{t} *out) {{",
              f"    if (pm->n_ints < {n_header}) return 0;"]
    for k, f in enumerate(header):
        read = f"pm->ints[{k}] != 0" if f.kind == "flag" else f"pm->ints[{k}]"
        lines.append(f"    const i64 {f.name} = {read};")
    lines.append("    if (" + " || ".join(f"{n} < 0" for n in sizes) + ") return 0;")
    for b in layout.buffers:
        op = "!=" if b.exact else "<"
        lines.append(f"    if (pm->n_{b.name} {op} {lengths[b.name]}) return 0;")
    for b in layout.buffers:
        lines.append("    {")
        lines.append("        i64 o = 0;")
        for f in b.fields:
            size = L.field_size(f)
            if f.target:
                tgt = f"out->{f.target}"
                if f.kind in L.HEADER_KINDS:
                    lines.append(f"        {tgt} = {f.name};")
                elif f.kind == "value":
                    lines.append(f"        {tgt} = pm->{b.name}[o];")
                elif f.kind == "record":
                    lines.append(f"        {f.record.c_decoder}(pm->{b.name} + o, &{tgt});")
                else:
                    lines.append(f"        {tgt} = pm->{b.name} + o;")
            lines.append(f"        o += {size};")
        lines += ["        (void)o;", "    }"]
    return lines + ["    return 1;", "}", ""]


def _c_result_types(L) -> list[str]:
    """The results' Python types and their converters, for the bindings. Each result is an
    object of its own type whose fields are read-only object slots (T_OBJECT_EX members,
    which Python's attribute look-up specializes: a field costs what a __slots__ attribute
    costs; a struct sequence's fields, not specialized, cost several times more)."""
    conv = {"i64": "PyLong_FromLongLong((long long)r->{})", "double": "PyFloat_FromDouble(r->{})",
            "bool": "PyBool_FromLong(r->{} != 0)"}
    lines = ["#ifdef Py_PYTHON_H /* the bindings */", "#include <structmember.h>", ""]
    for r in L.RESULTS:
        n = len(r.fields)
        fn = r.c_struct[:-2] + "_to_py"
        lines += [f"/* {r.name}: its fields ({', '.join(f.name for f in r.fields)}) */",
                  "typedef struct {", "    PyObject_HEAD", f"    PyObject *f[{n}];",
                  f"}} {r.name}_object;", f"extern PyTypeObject {r.name}_Type;", "",
                  f"/* a {r.name} of r (NULL with an exception set on failure) */",
                  f"static inline PyObject *{fn}(const {r.c_struct} *r) {{",
                  f"    {r.name}_object *o = PyObject_New({r.name}_object, &{r.name}_Type);",
                  "    if (!o) return NULL;",
                  f"    for (int k = 0; k < {n}; k++) o->f[k] = NULL;"]
        for k, f in enumerate(r.fields):
            lines.append(f"    if (!(o->f[{k}] = {conv[f.kind].format(f.name)})) goto fail;")
        lines += ["    return (PyObject *)o;", "fail:", "    Py_DECREF(o);", "    return NULL;",
                  "}", ""]
    lines += ["#ifdef KERNEL_LAYOUTS_DEFINE_TYPES /* (module.c) */"]
    for r in L.RESULTS:
        n, name = len(r.fields), r.name
        lines += [f"static void {name}_dealloc({name}_object *o) {{",
                  f"    for (int k = 0; k < {n}; k++) Py_XDECREF(o->f[k]);",
                  "    PyObject_Free(o);", "}", "",
                  f"static PyObject *{name}_repr({name}_object *o) {{",
                  "    return PyUnicode_FromFormat(\"" + name + "("
                  + ", ".join(f"{f.name}=%R" for f in r.fields) + ")\", "
                  + ", ".join(f"o->f[{k}]" for k in range(n)) + ");", "}", "",
                  f"static PyMemberDef {name}_members[] = {{"]
        lines += [f"    {{{_c_string(f.name)}, T_OBJECT_EX, offsetof({name}_object, f) + "
                  f"{k} * sizeof(PyObject *), READONLY, {_c_string(f.doc)}}},"
                  for k, f in enumerate(r.fields)]
        lines += ["    {NULL, 0, 0, 0, NULL}};", "",
                  f"PyTypeObject {name}_Type = {{",
                  f"    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "
                  f"\"starleth_sim.physics._kernels.{name}\",",
                  f"    .tp_basicsize = sizeof({name}_object),",
                  "    .tp_flags = Py_TPFLAGS_DEFAULT,",
                  f"    .tp_doc = {_c_string(r.doc)},",
                  f"    .tp_dealloc = (destructor){name}_dealloc,",
                  f"    .tp_repr = (reprfunc){name}_repr,",
                  f"    .tp_members = {name}_members,", "};", ""]
    lines += ["/* The result types, made ready and added to the module m (each with _fields, "
              "its field names); -1 on failure */",
              "static int add_result_types(PyObject *m) {",
              "    static const struct {", "        PyTypeObject *type;",
              "        const char *name, *fields;", "    } types[] = {"]
    lines += [f"        {{&{r.name}_Type, \"{r.name}\", "
              f"\"{' '.join(f.name for f in r.fields)}\"}}," for r in L.RESULTS]
    lines += ["    };",
              "    for (size_t k = 0; k < sizeof(types) / sizeof(types[0]); k++) {",
              "        if (PyType_Ready(types[k].type) < 0) return -1;",
              "        PyObject *names = PyUnicode_FromString(types[k].fields);",
              "        PyObject *fields = names ? PyUnicode_Split(names, NULL, -1) : NULL;",
              "        PyObject *tuple = fields ? PyList_AsTuple(fields) : NULL;",
              "        Py_XDECREF(names);", "        Py_XDECREF(fields);",
              "        if (!tuple) return -1;",
              "        int bad = PyDict_SetItemString(types[k].type->tp_dict, \"_fields\", "
              "tuple);",
              "        Py_DECREF(tuple);",
              "        if (bad < 0) return -1;",
              "        PyType_Modified(types[k].type);",
              "        Py_INCREF(types[k].type);",
              "        if (PyModule_AddObject(m, types[k].name, (PyObject *)types[k].type) < 0) {",
              "            Py_DECREF(types[k].type);", "            return -1;", "        }",
              "    }"]
    return lines + ["    return 0;", "}", "#endif", "#endif", ""]


@functools.lru_cache(maxsize=None)
def c_header() -> str:
    """The text of kernel_layouts.h, generated from kernel_layouts' declarations: the
    records' decoders, the result structs, packed_model_t, each layout's struct and
    unpacking, and (for the bindings) the results' Python types. Needs core.h's types."""
    L = _load_layouts()
    lines = ["/* kernel_layouts.h: GENERATED by starleth_sim/physics/kernel_build.py from the",
             " * declarations of starleth_sim/physics/kernel_layouts.py; edit those, not this. */",
             "#ifndef STARLETH_KERNEL_LAYOUTS_H", "#define STARLETH_KERNEL_LAYOUTS_H", "",
             '#include "core.h"', ""]
    for r in L.RECORDS:
        lines += _c_record(r, L)
    for r in L.RESULTS:
        lines += _c_result_struct(r, L)
    lines += _c_packed_buffers(L)
    for layout in L.LAYOUTS:
        lines += _c_layout(layout, L)
    lines += _c_result_types(L)
    return "\n".join(lines + ["#endif", ""])


def build(out_path: str, csrc: str = CSRC, jobs: int | None = None, progress=None,
          object_cache: str | None = None) -> float:
    """Compiles the kernels into the extension module file out_path (replaced atomically,
    with the digest beside it: out_path + DIGEST_SUFFIX); returns the wall time [s].
    progress(done, total) is called as the sources finish. object_cache: a directory that
    keeps each source's object file under the digest of what it depends on (its own text,
    the headers, the flags), so that after an edit only the edited sources compile again
    (all of them after an edit of a header). Raises BuildError."""
    t0 = time.perf_counter()
    cc = compiler()
    digest = source_digest(csrc)
    srcs = sources(csrc)
    jobs = max(1, min(jobs or os.cpu_count() or 1, len(srcs)))
    out_dir = os.path.dirname(os.path.abspath(out_path))
    os.makedirs(out_dir, exist_ok=True)
    generated = c_header().encode()
    headers = generated + b"".join(_read_bytes(os.path.join(csrc, n))
                                   for n in sorted(os.listdir(csrc)) if n.endswith(".h"))
    with tempfile.TemporaryDirectory(prefix="starleth-kernels-") as tmp:
        with open(os.path.join(tmp, LAYOUT_HEADER), "wb") as f:
            f.write(generated)
        include = ["-I" + csrc, "-I" + tmp, "-I" + _python_include()]
        cache = object_cache or tmp
        os.makedirs(cache, exist_ok=True)
        objects = [os.path.join(cache, os.path.basename(s)[:-2] + "-"
                                + _object_key(s, cc, headers) + ".o") for s in srcs]
        done = 0

        def compile_one(pair):
            src, obj = pair
            if os.path.exists(obj):
                return
            part = obj + f".{os.getpid()}.tmp"
            _run(cc + list(FLAGS) + include + ["-c", src, "-o", part])
            os.replace(part, obj)

        with ThreadPoolExecutor(jobs) as pool:
            for _ in pool.map(compile_one, zip(srcs, objects)):
                done += 1
                if progress:
                    progress(done, len(srcs))
        if object_cache:    # the objects of other versions: removed
            keep = set(objects)
            for name in os.listdir(object_cache):
                path = os.path.join(object_cache, name)
                if name.endswith(".o") and path not in keep:
                    os.remove(path)
        fd, tmp_out = tempfile.mkstemp(prefix=".build-", suffix=SUFFIX, dir=out_dir)
        os.close(fd)
        try:
            _run(cc + ["-shared", "-fPIC"] + objects + ["-lm", "-o", tmp_out])
            os.chmod(tmp_out, 0o755)
            os.replace(tmp_out, out_path)
        finally:
            if os.path.exists(tmp_out):
                os.remove(tmp_out)
    digest_file = out_path + DIGEST_SUFFIX
    part = f"{digest_file}.{os.getpid()}.tmp"
    with open(part, "w") as f:
        f.write(digest + "\n")
    os.replace(part, digest_file)
    return time.perf_counter() - t0


def inplace_path(package_dir: str = HERE) -> str:
    """Where a source checkout keeps its built module: beside this file."""
    return os.path.join(package_dir, MODULE + SUFFIX)


def main(argv=None) -> int:
    """python -m starleth_sim.physics.kernel_build [OUT | --header]: builds the module (in
    place by default), printing the time; --header prints the generated header instead."""
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--header"]:
        sys.stdout.write(c_header())
        return 0
    out = argv[0] if argv else inplace_path()
    try:
        seconds = build(out)
    except BuildError as e:
        print(f"kernel_build: FAILED: {e}", file=sys.stderr)
        return 1
    print(f"kernel_build: {out} in {seconds:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
