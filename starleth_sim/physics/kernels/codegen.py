"""The C side of the packed layouts, records and named results that
:mod:`starleth_sim.physics.kernels.layouts` declares: the text of the header
``kernel_layouts.h`` (:func:`c_header`), which :mod:`~starleth_sim.physics.kernels.build`
writes into its build directory and the C sources include through ``step.h``. Nothing here
is written by hand twice: the structs the one-kernel steps unpack their buffers into, the
unpacking and its length checks, the decoders of the settings records, the result structs and
their Python types all follow the declarations.

Standard library only, and no package-relative imports: kernels.build (which setup.py loads
by its path before anything is installed) loads this file by its path too, and passes the
layouts module in.
"""
from __future__ import annotations

import json


def c_string(text: str) -> str:
    return json.dumps(text, ensure_ascii=False)


def upper_snake(name: str) -> str:
    """CamelCase or snake_case -> UPPER_SNAKE."""
    out = ""
    for i, ch in enumerate(name):
        if ch.isupper() and i and not name[i - 1].isupper() and name[i - 1] != "_":
            out += "_"
        out += ch.upper()
    return out


def _c_record(r, L) -> list[str]:
    """A record's length and decoder (its fields from floats; a nested record's by its own
    decoder, into the same struct)."""
    lines = [f"/* {r.name} (kernels.layouts): {r.length} numbers as floats */",
             f"#define {upper_snake(r.name)}_LENGTH {r.length}",
             f"static inline void {r.c_decoder}(const double *f, {r.c_struct} *out) {{"]
    k = 0
    for f in r.fields:
        if isinstance(f, L.Nested):
            assert f.record.c_struct == r.c_struct, f"{r.name}.{f.name}: another C struct"
            lines.append(f"    {f.record.c_decoder}(f + {k}, out); /* {f.doc} */")
            k += f.record.length
            continue
        value = {"double": f"f[{k}]", "i64": f"(i64)f[{k}]", "bool": f"f[{k}] != 0.0"}[f.kind]
        lines.append(f"    out->{f.name} = {value}; /* {f.doc} */")
        k += 1
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
    lines = _c_layout_struct(layout, L)
    sizes = [f.name for f in header] + list(layout.context)
    lengths = {b.name: " + ".join(f"({L.field_size(f)})" for f in b.fields)
               for b in layout.buffers}
    if not header:
        return lines + _c_standalone_views(layout, L, sizes, lengths)
    return lines + _c_unpack(layout, L, sizes, lengths)


def _c_layout_struct(layout, L) -> list[str]:
    """A layout's unpacked struct: its members, then a view or value per buffer field."""
    view_type = {"float64": "double *", "int64": "const i64 *", "bool": "const u8 *"}
    lines = [f"/* {layout.name} (kernels.layouts.{upper_snake(layout.name)}), unpacked */",
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
    return lines + [f"}} {layout.c_name}_t;", ""]


def _c_standalone_views(layout, L, sizes, lengths) -> list[str]:
    """A layout without header (one buffer): its length and its views."""
    t = f"{layout.c_name}_t"
    params = ", ".join(f"i64 {n}" for n in sizes)
    (b,) = layout.buffers
    lines = [f"/* the length of a {layout.name} */",
             f"static inline i64 {layout.c_name}_length({params}) {{",
             f"    return {lengths[b.name]};", "}", "",
             f"/* the views of a {layout.name} buffer of {layout.c_name}_length entries */",
             f"static inline void {layout.c_name}_views(double *{b.name}, {params}, "
             f"{t} *out) {{", "    i64 o = 0;"]
    for f in b.fields:
        lines += [f"    out->{f.target} = {b.name} + o;",
                  f"    o += {L.field_size(f)};"]
    return lines + ["    (void)o;", "}", ""]


def _c_unpack(layout, L, sizes, lengths) -> list[str]:
    """A packed model's header constants and unpack_<layout>: the header read and checked,
    each buffer's length checked, the struct's views set."""
    header = layout.header()
    t = f"{layout.c_name}_t"
    ctx = "".join(f", i64 {n}" for n in layout.context)
    n_header = len(header)
    lines = [f"#define {upper_snake(layout.name)}_HEADER {n_header}"]
    lines += [f"#define {upper_snake(layout.name)}_{f.name.upper()} {k} /* ints[{k}]: {f.doc} */"
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
    lines = ["#ifdef Py_PYTHON_H /* the bindings */", "#include <structmember.h>", ""]
    for r in L.RESULTS:
        lines += _c_result_converter(r)
    lines += ["#ifdef KERNEL_LAYOUTS_DEFINE_TYPES /* (module.c) */"]
    for r in L.RESULTS:
        lines += _c_result_type(r)
    lines += _c_add_result_types(L)
    return lines + ["    return 0;", "}", "#endif", "#endif", ""]


def _c_result_converter(r) -> list[str]:
    """A result's object struct and its converter from the C struct."""
    conv = {"i64": "PyLong_FromLongLong((long long)r->{})", "double": "PyFloat_FromDouble(r->{})",
            "bool": "PyBool_FromLong(r->{} != 0)"}
    n = len(r.fields)
    fn = r.c_struct[:-2] + "_to_py"
    lines = [f"/* {r.name}: its fields ({', '.join(f.name for f in r.fields)}) */",
             "typedef struct {", "    PyObject_HEAD", f"    PyObject *f[{n}];",
             f"}} {r.name}_object;", f"extern PyTypeObject {r.name}_Type;", "",
             f"/* a {r.name} of r (NULL with an exception set on failure) */",
             f"static inline PyObject *{fn}(const {r.c_struct} *r) {{",
             f"    {r.name}_object *o = PyObject_New({r.name}_object, &{r.name}_Type);",
             "    if (!o) return NULL;",
             f"    for (int k = 0; k < {n}; k++) o->f[k] = NULL;"]
    for k, f in enumerate(r.fields):
        lines.append(f"    if (!(o->f[{k}] = {conv[f.kind].format(f.name)})) goto fail;")
    return lines + ["    return (PyObject *)o;", "fail:", "    Py_DECREF(o);", "    return NULL;",
                    "}", ""]


def _c_result_type(r) -> list[str]:
    """A result's Python type: dealloc, repr, the read-only members, the type object."""
    n, name = len(r.fields), r.name
    lines = [f"static void {name}_dealloc({name}_object *o) {{",
             f"    for (int k = 0; k < {n}; k++) Py_XDECREF(o->f[k]);",
             "    PyObject_Free(o);", "}", "",
             f"static PyObject *{name}_repr({name}_object *o) {{",
             "    return PyUnicode_FromFormat(\"" + name + "("
             + ", ".join(f"{f.name}=%R" for f in r.fields) + ")\", "
             + ", ".join(f"o->f[{k}]" for k in range(n)) + ");", "}", "",
             f"static PyMemberDef {name}_members[] = {{"]
    lines += [f"    {{{c_string(f.name)}, T_OBJECT_EX, offsetof({name}_object, f) + "
              f"{k} * sizeof(PyObject *), READONLY, {c_string(f.doc)}}},"
              for k, f in enumerate(r.fields)]
    return lines + ["    {NULL, 0, 0, 0, NULL}};", "",
                    f"PyTypeObject {name}_Type = {{",
                    f"    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "
                    f"\"starleth_sim.physics._kernels.{name}\",",
                    f"    .tp_basicsize = sizeof({name}_object),",
                    "    .tp_flags = Py_TPFLAGS_DEFAULT,",
                    f"    .tp_doc = {c_string(r.doc)},",
                    f"    .tp_dealloc = (destructor){name}_dealloc,",
                    f"    .tp_repr = (reprfunc){name}_repr,",
                    f"    .tp_members = {name}_members,", "};", ""]


def _c_add_result_types(L) -> list[str]:
    """add_result_types(m): every result type made ready, with _fields, into the module
    (its closing lines are the caller's)."""
    lines = ["/* The result types, made ready and added to the module m (each with _fields, "
             "its field names); -1 on failure */",
             "static int add_result_types(PyObject *m) {",
             "    static const struct {", "        PyTypeObject *type;",
             "        const char *name, *fields;", "    } types[] = {"]
    lines += [f"        {{&{r.name}_Type, \"{r.name}\", "
              f"\"{' '.join(f.name for f in r.fields)}\"}}," for r in L.RESULTS]
    return lines + [
        "    };",
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


def c_header(L) -> str:
    """The text of kernel_layouts.h, generated from kernels.layouts' declarations: the
    records' decoders, the result structs, packed_model_t, each layout's struct and
    unpacking, and (for the bindings) the results' Python types, from `L`, the
    kernels.layouts module. Needs core.h's types."""
    lines = ["/* kernel_layouts.h: GENERATED by starleth_sim/physics/kernels/codegen.py from the",
             " * declarations of starleth_sim/physics/kernels/layouts.py; edit those, not this. */",
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
