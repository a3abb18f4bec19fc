"""C-contiguous n-d views of a contiguous 1-d array inside numba kernels, without numba's
reshape: ``a.reshape(shape)`` calls a C helper that checks whether a copy is needed (≈30 ns
per call, measured, as much as allocating a small array), which the one-kernel step pays
for every view of its packed buffers (tree_step.unpack_tree_model) on every step. These
views cost ≈1 ns. They share the array's memory (and keep it alive, as reshape's view
does); the caller guarantees that the shape's product is the array's length: nothing is
checked.
"""
from __future__ import annotations

from numba.core import cgutils, types
from numba.core.imputils import impl_ret_borrowed
from numba.extending import intrinsic
from numba.np.arrayobj import make_array, populate_array


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
