"""A fused multiply-add for the compiled kernels (`kernels`, `plane_kernels`): what
reproduces OpenBLAS's products bit for bit, which fuse where the C compiler contracted
them."""

from __future__ import annotations

from typing import Any

from numba import types
from numba.extending import intrinsic


@intrinsic
def fma(typingctx: Any, a: Any, b: Any, c: Any) -> Any:
    """a * b + c with one rounding (LLVM's llvm.fma), float64; a library call on a CPU
    without FMA instructions, so the same result everywhere."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        return builder.fma(*args)

    return sig, codegen
