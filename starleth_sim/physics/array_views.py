"""C-contiguous n-d views of a contiguous 1-d array inside numba kernels, without numba's
reshape: ``a.reshape(shape)`` calls a C helper that checks whether a copy is needed (≈30 ns
per call, measured, as much as allocating a small array), which the one-kernel step pays
for every view of its packed buffers (tree_step.unpack_tree_model) on every step. These
views cost ≈1 ns. They share the array's memory (and keep it alive, as reshape's view
does); the caller guarantees that the shape's product is the array's length: nothing is
checked.

`borrowed` and `keep_alive`: arrays without numba's reference counting inside the one-kernel
steps (atomic increments and decrements of the owner's count on every view, tuple and call
took a third of an HmJ step's kernel time; see their docstrings for when they are safe).
`arena_floats` / `arena_ints`: a one-kernel step's work arrays carved from its workspace
instead of allocated (an allocation and its release cost ≈ 40-90 ns each, measured).
"""
from __future__ import annotations

import numpy as np
from numba.core import cgutils, types
from numba.core.imputils import impl_ret_borrowed
from numba.extending import intrinsic, overload
from numba.np.arrayobj import make_array, populate_array

from .kernel_cache import KERNEL


def _c_view(ndim: int):
    """The intrinsic view(a, shape): a (1-d, C-contiguous) seen as an ndim-d C array."""

    @intrinsic
    def view(typingctx, a, shape):
        if not (isinstance(a, types.Array) and a.ndim == 1 and a.layout == "C"
                and isinstance(shape, types.UniTuple) and shape.count == ndim
                and isinstance(shape.dtype, types.Integer)):
            return None
        sig = types.Array(a.dtype, ndim, "C", readonly=not a.mutable)(a, shape)

        def codegen(context, builder, sig, args):
            src = make_array(sig.args[0])(context, builder, args[0])
            out = make_array(sig.return_type)(context, builder)
            dims = [context.cast(builder, d, sig.args[1].dtype, types.intp)
                    for d in cgutils.unpack_tuple(builder, args[1], ndim)]
            strides = [src.itemsize] * ndim
            for k in range(ndim - 2, -1, -1):
                strides[k] = builder.mul(strides[k + 1], dims[k + 1])
            populate_array(out, data=src.data, shape=cgutils.pack_array(builder, dims),
                           strides=cgutils.pack_array(builder, strides),
                           itemsize=src.itemsize, meminfo=src.meminfo, parent=src.parent)
            return impl_ret_borrowed(context, builder, sig.return_type, out._getvalue())
        return sig, codegen
    return view


#: view2(a, (n0, n1)), view3(a, (n0, n1, n2)): a[:n0 n1 (n2)] as a 2-d / 3-d C array
view2 = _c_view(2)
view3 = _c_view(3)


@intrinsic
def borrowed(typingctx, a):
    """a, seen without numba's reference counting: the same data, shape and strides with no
    owner (a null meminfo, as numba.carray's arrays of a raw pointer). Every view taken of it
    and every call it is passed to then skips the atomic increments and decrements of the
    owner's count (reference counting was 31-37 % of an HmJ step's kernel time, measured
    with perf), which costs a null test instead. Only for arrays that outlive every use of
    the result: a kernel's arguments (the caller holds them for the call), never an array
    the kernel allocates (numba frees it after its last use by name) and never for a result
    that leaves the kernel."""
    if not isinstance(a, types.Array):
        return None
    sig = a(a)

    def codegen(context, builder, sig, args):
        ary = make_array(sig.args[0])(context, builder, args[0])
        ary.meminfo = cgutils.get_null_value(ary.meminfo.type)
        ary.parent = cgutils.get_null_value(ary.parent.type)
        return ary._getvalue()      # (owns nothing: nothing to increment)
    return sig, codegen


@intrinsic
def keep_alive(typingctx, a):
    """Does nothing with a but use it: numba releases an array after the last use of its name,
    so a kernel that works on borrowed(a) calls keep_alive(a) after its last use of the
    borrowed view, on every path (a return included), to hold a's memory until then."""
    sig = types.none(a)

    def codegen(context, builder, sig, args):
        return context.get_dummy_value()
    return sig, codegen


# -- a step's arena: its work arrays carved from one workspace instead of allocated ----------
# arena = (floats, ints, pos): float64 and int64 buffers and pos = [first free float, first
# free int, requests that did not fit (counted, never reset)], or None (the callers that
# keep what they get, e.g. a problem prepared ahead and returned to Python: every request
# allocates). A one-kernel step resets pos[:2] and passes its arena down; what it hands out
# is valid until the next reset.

def arena_floats(arena, n):
    """n float64 entries (uninitialised): the arena's next n, or a new array when the arena
    is None or full."""
    raise NotImplementedError("arena_floats runs in numba kernels only")


def arena_ints(arena, n):
    """n int64 entries (uninitialised), as arena_floats."""
    raise NotImplementedError("arena_ints runs in numba kernels only")


def _no_arena(arena) -> bool:
    return isinstance(arena, (types.NoneType, types.Omitted))


#: an arena hands out parts that start ARENA_ALIGN entries (64 bytes) apart, as numba's own
#: allocations are aligned (an HmJ step with unaligned parts ran 3 % slower, measured)
ARENA_ALIGN = 8


def _arena_take(which, dtype):
    def impl(arena, n):
        buf, pos = arena[which], arena[2]
        o = pos[which]
        if o + n <= buf.shape[0]:
            pos[which] = o + (n + ARENA_ALIGN - 1) // ARENA_ALIGN * ARENA_ALIGN
            return buf[o:o + n]
        pos[2] += 1
        return np.empty(n, dtype=dtype)
    return impl


@overload(arena_floats, jit_options=KERNEL)
def _arena_floats_jit(arena, n):
    if _no_arena(arena):
        return lambda arena, n: np.empty(n)
    return _arena_take(0, np.float64)


@overload(arena_ints, jit_options=KERNEL)
def _arena_ints_jit(arena, n):
    if _no_arena(arena):
        return lambda arena, n: np.empty(n, dtype=np.int64)
    return _arena_take(1, np.int64)
