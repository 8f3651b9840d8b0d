"""LLVM intrinsics numba does not expose: population count, trailing and leading zeros, funnel
shift and a cache prefetch.

``popcount`` lets a bit-plane distance count differing frames 64 at a time (and vectorise
to ``vpopcntq`` where the CPU has it); ``funnel_shift_right`` reads 64 frames that start
anywhere in two consecutive words as one instruction (``vpshrdvq`` with AVX-512 VBMI2,
three shifts and an or without); ``trailing_zeros`` and ``leading_zeros`` find the
next or previous set bit in one instruction (``tzcnt``, ``lzcnt``) where the succinct
directory scans its bit vectors; ``prefetch`` hides the memory latency of scoring
candidates scattered over a reference map far larger than the caches.
"""

from __future__ import annotations

import llvmlite.ir as ir
from numba import types
from numba.extending import intrinsic

_I8P = ir.IntType(8).as_pointer()
_I32 = ir.IntType(32)
_I64 = ir.IntType(64)


@intrinsic
def popcount(typingctx, x):
    """Number of set bits of a uint64, as int64."""
    if x != types.uint64:
        return None

    def codegen(context, builder, signature, args):
        fn = builder.module.declare_intrinsic("llvm.ctpop", [ir.IntType(64)])
        return builder.call(fn, args)

    return types.int64(types.uint64), codegen


@intrinsic
def trailing_zeros(typingctx, x):
    """Index of the lowest set bit of a uint64 (64 for zero), as int64."""
    if x != types.uint64:
        return None

    def codegen(context, builder, signature, args):
        fn = builder.module.declare_intrinsic("llvm.cttz", [_I64], fnty=ir.FunctionType(_I64, [_I64, ir.IntType(1)]))
        return builder.call(fn, [args[0], ir.Constant(ir.IntType(1), 0)])

    return types.int64(types.uint64), codegen


@intrinsic
def leading_zeros(typingctx, x):
    """Number of zero bits above the highest set bit of a uint64 (64 for zero), as int64."""
    if x != types.uint64:
        return None

    def codegen(context, builder, signature, args):
        fn = builder.module.declare_intrinsic("llvm.ctlz", [_I64], fnty=ir.FunctionType(_I64, [_I64, ir.IntType(1)]))
        return builder.call(fn, [args[0], ir.Constant(ir.IntType(1), 0)])

    return types.int64(types.uint64), codegen


@intrinsic
def funnel_shift_right(typingctx, hi, lo, shift):
    """The low 64 bits of the 128-bit ``hi:lo`` shifted right by ``shift`` (mod 64), all uint64."""
    if not all(a == types.uint64 for a in (hi, lo, shift)):
        return None

    def codegen(context, builder, signature, args):
        fn = builder.module.declare_intrinsic("llvm.fshr", [_I64], fnty=ir.FunctionType(_I64, [_I64] * 3))
        return builder.call(fn, args)

    return types.uint64(types.uint64, types.uint64, types.uint64), codegen


@intrinsic
def prefetch(typingctx, arr, flat_index):
    """Hint that element ``flat_index`` of a C-contiguous array will be read soon (no effect on results)."""
    if not isinstance(arr, types.Array) or not isinstance(flat_index, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        ptr = builder.bitcast(builder.gep(data, [args[1]]), _I8P)
        fn = builder.module.declare_intrinsic(
            "llvm.prefetch", fnty=ir.FunctionType(ir.VoidType(), [_I8P, _I32, _I32, _I32]))
        # read, keep in all cache levels, data cache
        builder.call(fn, [ptr, ir.Constant(_I32, 0), ir.Constant(_I32, 3), ir.Constant(_I32, 1)])
        return context.get_dummy_value()

    return types.void(arr, flat_index), codegen
