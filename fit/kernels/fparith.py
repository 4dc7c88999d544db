"""One floating-point operation per thread, for measuring a device's arithmetic (``texstream fpcheck``).

Each kernel applies the eight measured operations to operand arrays of one dtype and writes one row
per operation. The operands arrive in arrays, so the compiler can neither fold a result nor fuse two
operations (no multiply-add contraction: every result is one rounded operation), and each dtype has
its own compiled overload so the arithmetic is exactly the dtype's, not a wider one converted back.

Row order: :data:`OPERATIONS`. Unary operations (sqrt, exp, log) read ``a`` only.
"""

from __future__ import annotations

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

OPERATIONS = ("add", "sub", "mul", "div", "sqrt", "exp", "log", "pow")
"""the rows of a kernel's output, in order"""


@wp.kernel
def fp_ops(a: wp.array(dtype=Any), b: wp.array(dtype=Any), out: wp.array2d(dtype=Any)):
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


FP_DTYPES = {"float16": wp.float16, "float32": wp.float32, "float64": wp.float64}
FP_OPS_KERNELS = {}
"""the kernel of each measured dtype: one explicit overload of :func:`fp_ops` per dtype"""
for _name, _t in FP_DTYPES.items():
    FP_OPS_KERNELS[_name] = wp.overload(fp_ops, {"a": wp.array(dtype=_t), "b": wp.array(dtype=_t),
                                                 "out": wp.array2d(dtype=_t)})
