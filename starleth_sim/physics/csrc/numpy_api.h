/* numpy's C API for the bindings' fast path (bind.c's get_array reads a numpy array's data,
 * type and shape from the array itself instead of through the buffer protocol), where the
 * build found numpy's headers: it then defines STARLETH_NUMPY_C_API (kernels/build.py).
 * module.c defines STARLETH_NUMPY_IMPORT before including this and imports the API. */
#ifndef STARLETH_NUMPY_API_H
#define STARLETH_NUMPY_API_H

#ifdef STARLETH_NUMPY_C_API
#define PY_ARRAY_UNIQUE_SYMBOL starleth_kernels_ARRAY_API
#define NPY_NO_DEPRECATED_API  NPY_1_7_API_VERSION
#ifndef STARLETH_NUMPY_IMPORT
#define NO_IMPORT_ARRAY
#endif
#include <numpy/arrayobject.h>
#endif

#endif
