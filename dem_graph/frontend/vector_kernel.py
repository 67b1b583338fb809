"""The correlation's numerator in explicit vectors: a numba intrinsic that writes LLVM IR.

numba compiles the plain loop (:func:`~dem_graph.frontend.match_kernel.ncc_grid` before) into
vector code, but it reads and writes every partial sum from memory once per template pixel, and
the loop's start-up cost comes back for every row of 8 or 16 sums. :func:`correlate_block` keeps a
block of ``BLOCK_ROWS`` x ``BLOCK_LANES`` sums in vector registers over the whole template instead.

Each sum is formed exactly as the plain loop formed it: zero, then for every template pixel in row-
major order, the product rounded, then the sum rounded (a multiply, then an add; no fused
multiply-add, which LLVM does not form without fast-math flags). The scores are therefore the same
to the bit (tests/test_fast_paths.py), and the EKF baselines' tracks with them.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

BLOCK_LANES = 8  # sums along a row per block: one 512-bit vector of float64 (two 256-bit ones, where that is all there is)
BLOCK_ROWS = 4  # rows of sums per block: independent chains of additions in flight


@intrinsic
def correlate_block(typingctx, region, region_stride, weights, t_rows, t_cols, row0, col0, out, out_stride):
    """``out[r * out_stride + q]`` for ``r < BLOCK_ROWS``, ``q < BLOCK_LANES`` becomes the sum over
    template pixels ``(a, b)`` (row-major) of ``region[(row0 + r + a) * region_stride + col0 + b + q]
    * weights[a * t_cols + b]``. ``region``, ``weights`` and ``out`` are contiguous float64 arrays;
    the caller makes sure every index read or written is inside them (no check here)."""
    sig = types.void(region, region_stride, weights, t_rows, t_cols, row0, col0, out, out_stride)

    def codegen(context, builder, signature, args):
        region_v, stride, weights_v, n_a, n_b, r0, c0, out_v, ostride = args
        i64 = ir.IntType(64)
        i32 = ir.IntType(32)
        vec = ir.VectorType(ir.DoubleType(), BLOCK_LANES)
        region_p = context.make_array(signature.args[0])(context, builder, region_v).data
        weights_p = context.make_array(signature.args[2])(context, builder, weights_v).data
        out_p = context.make_array(signature.args[7])(context, builder, out_v).data
        stride, n_a, n_b, r0, c0, ostride = (context.cast(builder, v, t, types.int64) for v, t in zip(
            (stride, n_a, n_b, r0, c0, ostride), (signature.args[1], signature.args[3], signature.args[4], signature.args[5], signature.args[6], signature.args[8])
        ))  # fmt: skip
        sums = [cgutils.alloca_once_value(builder, ir.Constant(vec, [0.0] * BLOCK_LANES)) for _ in range(BLOCK_ROWS)]
        undef = ir.Constant(vec, ir.Undefined)
        splat = ir.Constant(ir.VectorType(i32, BLOCK_LANES), [0] * BLOCK_LANES)
        with cgutils.for_range(builder, n_a, intp=i64) as loop_a:
            a = loop_a.index
            with cgutils.for_range(builder, n_b, intp=i64) as loop_b:
                b = loop_b.index
                w = builder.load(builder.gep(weights_p, [builder.add(builder.mul(a, n_b), b)]))
                w_vec = builder.shuffle_vector(builder.insert_element(undef, w, ir.Constant(i32, 0)), undef, splat)
                for r in range(BLOCK_ROWS):
                    row = builder.add(builder.add(r0, ir.Constant(i64, r)), a)
                    pixel = builder.gep(region_p, [builder.add(builder.add(builder.mul(row, stride), c0), b)])
                    x = builder.load(builder.bitcast(pixel, vec.as_pointer()), align=8)
                    builder.store(builder.fadd(builder.load(sums[r]), builder.fmul(x, w_vec)), sums[r])
        for r in range(BLOCK_ROWS):
            target = builder.gep(out_p, [builder.mul(ir.Constant(i64, r), ostride)])
            builder.store(builder.load(sums[r]), builder.bitcast(target, vec.as_pointer()), align=8)
        return context.get_dummy_value()

    return sig, codegen


__all__ = ["BLOCK_LANES", "BLOCK_ROWS", "correlate_block"]
