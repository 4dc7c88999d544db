"""The overloads of the fit's generic kernels that the default run launches, declared when each kernel is made.

Warp hashes a module with every overload its generic kernels have at that moment, and a launch whose argument
types are new adds an overload: the module is hashed again and compiled again. Declared here, up front and the
same in every process, the default run's overloads are in each module before its first launch, so one build
of the module (the cold fit's parallel prewarm, fit/stages/prewarm.py, or a first launch) serves every later
launch and run. Other precisions or parameter counts (``stream.accumulate`` fp64 above 1,000 photos,
``stream.image_precision`` fp16, two-lobe or anisotropic Lafortune, the radiance models) still add their
overload at their first launch and compile then, the declared ones with them.
"""

from __future__ import annotations

import warp as wp

from texstream.fit.kernels.lafortune_grad import param_types

DEFAULT_PARAM_COUNTS = (9, 3)
"""parameters per texel of the default run's models: one-lobe isotropic Lafortune (rho_d, rho_s, C_xy, C_z,
n) and diffuse (rho_d), the two the README's ``texstream run`` fits (tests/test_fit_prewarm.py checks it)"""
COMPUTE_SCALAR = wp.float32
"""``stream.accumulate`` auto up to 1,000 photos (fit/stream/config.py)"""
STORAGE_SCALAR = wp.float32
"""``stream.storage`` fp32, the default"""
IMAGE_PIXEL = wp.vec3
"""``stream.image_precision`` fp32, the default"""


def declare(kernel, **dtypes) -> None:
    """``wp.overload`` of ``kernel`` with each generic argument's type, an array argument's given by its dtype
    (its dimension is the kernel's). An argument left generic fails here, at import, not at a launch."""
    types = {}
    for name, dtype in dtypes.items():
        template = kernel.adj.arg_types[name]
        types[name] = wp.array(dtype=dtype, ndim=template.ndim) if wp.types.is_array(template) else dtype
    wp.overload(kernel, types)


def param_overloads(param_counts=DEFAULT_PARAM_COUNTS):
    """(scalar, parameter vector, parameter matrix) of the compute precision, per parameter count."""
    return [(COMPUTE_SCALAR, *param_types(n, COMPUTE_SCALAR)) for n in param_counts]
