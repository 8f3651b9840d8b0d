"""Arrays lent to compiled code by address: views that carry no reference count.

numba counts references to every array it holds: an array read from a struct's field is
incremented on the way in and decremented on the way out, each an indirect call doing an
atomic update. A live frame's step (:mod:`vprscale.method.online`) reads some thirty arrays,
and those sixty calls cost as much as the whole of an L = 1 frame's work. So a struct that is
read on every call holds each array as its address and shape (:func:`lend`), and the call
takes back a plain view of it (:func:`borrow`): no count, no call.

Nothing then keeps a lent array alive: whoever lends it must hold the array for as long as the
struct is used (the matcher holds both).
"""

from __future__ import annotations

import numba
from numba import types
from numba.extending import intrinsic

from vprscale.core.kernelcache import share_kernels

share_kernels()


@intrinsic
def _address(typingctx, a):
    """The first element's address, as a pointer typed like the array's elements."""
    sig = types.CPointer(a.dtype)(a)

    def codegen(context, builder, signature, args):
        array = context.make_array(signature.args[0])(context, builder, args[0])
        return builder.bitcast(array.data, context.get_value_type(signature.return_type))

    return sig, codegen


@numba.njit(cache=True, nogil=True, inline="always")
def lend(a):
    """``(pointer, shape)`` of a C-contiguous array, for a struct to hold without a count."""
    if not a.flags.c_contiguous:
        raise ValueError("only a contiguous array can be lent")
    return _address(a), a.shape


@numba.njit(cache=True, nogil=True, inline="always")
def borrow(lent):
    """The array :func:`lend` gave, as a view with no reference count (valid while its owner
    holds it)."""
    return numba.carray(lent[0], lent[1])
