"""A memory prefetch hint for the compiled (numba) kernels whose events read pixels at random places of a frame.

An event of a noisy stream reads its neighbourhood of a time surface at an unpredictable place, which is out of
every cache; the kernels are loops over the events in time order, so the processor reaches the next event's reads
only after the current event's. :func:`prefetch` asks it to start loading the cache line of an array element some
events ahead, while the current event is processed. It is a hint only: it reads nothing into the program, writes
nothing, cannot fault, and leaves every result as it was.

Example:
    >>> import numba, numpy as np
    >>> from torchevtrack.prefetch import prefetch
    >>> @numba.njit
    ... def total(a, order):
    ...     s = 0
    ...     for j in range(order.shape[0]):
    ...         if j + 8 < order.shape[0]:
    ...             prefetch(a, order[j + 8])
    ...         s += a[order[j]]
    ...     return s
    >>> int(total(np.arange(100), np.arange(100)[::-1].copy()))
    4950
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["AHEAD", "prefetch"]

AHEAD = 8
"""Events between the prefetch of an event's pixels and their use, in the kernels' event loops (4-16 measured alike on
the 1280x720 noisy sequence; 8 kept)."""


@intrinsic
def prefetch(typingctx, array, index):
    """``prefetch(array, index)`` in a compiled function: hint that the element ``index`` of the contiguous 1-D
    ``array`` will be read soon (LLVM's ``llvm.prefetch``: a read, kept in every cache level). ``index`` may lie
    outside the array (a prefetch never faults), but then only wastes the hint."""
    if not (isinstance(array, types.Array) and array.ndim == 1 and isinstance(index, types.Integer)):
        return None
    sig = types.void(array, index)

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        byte_ptr = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [byte_ptr, i32, i32, i32]),
                                            "llvm.prefetch.p0i8")
        address = builder.bitcast(builder.gep(data, [args[1]]), byte_ptr)
        builder.call(fn, [address, ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return sig, codegen
