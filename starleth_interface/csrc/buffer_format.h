/* The item type of a buffer (Python's buffer protocol: numpy arrays without the numpy C
 * API), checked the same way by every C extension's bindings (the physics kernels' bind.c,
 * py_args.h of the controller's kernels and sim_node's command parsers). */
#ifndef STARLETH_BUFFER_FORMAT_H
#define STARLETH_BUFFER_FORMAT_H

#include <Python.h>

/* Whether the items of b are of `type`: 'd' float64, 'q' int64, '?' bool, 'B' uint8. */
static inline int format_is(const Py_buffer *b, char type) {
    const char *f = b->format ? b->format : "B";
    if (*f == '@' || *f == '=' || *f == '<') f++;
    if (f[0] == 0 || f[1] != 0) return 0;
    switch (type) {
        case 'd':
            return f[0] == 'd' && b->itemsize == 8;
        case 'q':
            return (f[0] == 'l' || f[0] == 'q') && b->itemsize == 8;
        case '?':
            return f[0] == '?' && b->itemsize == 1;
        case 'B':
            return (f[0] == 'B' || f[0] == 'b' || f[0] == 'c') && b->itemsize == 1;
    }
    return 0;
}

/* numpy's name of `type` (format_is) */
static inline const char *dtype_of(char type) {
    return type == 'd' ? "float64" : type == 'q' ? "int64" : type == '?' ? "bool" : "uint8";
}

#endif
