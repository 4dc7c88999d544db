"""One floating-point operation per thread, for measuring a device's arithmetic (``texstream fpcheck``).

Each kernel applies the eight measured operations to operand arrays of one dtype and writes one row
per operation. The operands arrive in arrays, so the compiler can neither fold a result nor fuse two
operations (no multiply-add contraction: every result is one rounded operation), and each dtype has
its own kernel so the arithmetic is exactly the dtype's, not a wider one converted back.

Row order: :data:`OPERATIONS`. Unary operations (sqrt, exp, log) read ``a`` only.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})

OPERATIONS = ("add", "sub", "mul", "div", "sqrt", "exp", "log", "pow")
"""the rows of a kernel's output, in order"""


@wp.kernel
def fp_ops_float16(a: wp.array(dtype=wp.float16), b: wp.array(dtype=wp.float16),
                   out: wp.array2d(dtype=wp.float16)):
    i = wp.tid()
    x = a[i]
    y = b[i]
    out[0, i] = x + y
    out[1, i] = x - y
    out[2, i] = x * y
    out[3, i] = x / y
    out[4, i] = wp.sqrt(x)
    out[5, i] = wp.exp(x)
    out[6, i] = wp.log(x)
    out[7, i] = wp.pow(x, y)


@wp.kernel
def fp_ops_float32(a: wp.array(dtype=wp.float32), b: wp.array(dtype=wp.float32),
                   out: wp.array2d(dtype=wp.float32)):
    i = wp.tid()
    x = a[i]
    y = b[i]
    out[0, i] = x + y
    out[1, i] = x - y
    out[2, i] = x * y
    out[3, i] = x / y
    out[4, i] = wp.sqrt(x)
    out[5, i] = wp.exp(x)
    out[6, i] = wp.log(x)
    out[7, i] = wp.pow(x, y)


@wp.kernel
def fp_ops_float64(a: wp.array(dtype=wp.float64), b: wp.array(dtype=wp.float64),
                   out: wp.array2d(dtype=wp.float64)):
    i = wp.tid()
    x = a[i]
    y = b[i]
    out[0, i] = x + y
    out[1, i] = x - y
    out[2, i] = x * y
    out[3, i] = x / y
    out[4, i] = wp.sqrt(x)
    out[5, i] = wp.exp(x)
    out[6, i] = wp.log(x)
    out[7, i] = wp.pow(x, y)


FP_OPS_KERNELS = {"float16": fp_ops_float16, "float32": fp_ops_float32, "float64": fp_ops_float64}
"""the kernel of each measured dtype"""
