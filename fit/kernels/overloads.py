"""The overloads of the fit's generic kernels that a fit launches, declared when each kernel is made.

Warp hashes a module with every overload its generic kernels have at that moment, and a launch whose argument
types are new adds an overload: the module is hashed again and compiled again. Declared here, up front and the
same in every process, a fit's overloads are in each module before its first launch, so one build of the module
(the cold fit's parallel prewarm, fit/stages/prewarm.py, or a first launch) serves every later launch and run.

The compute precision: every process declares float32's (``stream.accumulate`` auto up to 1,000 photos); a fit
whose passes accumulate in float64 (auto above 1,000 photos, or asked) declares float64's too, with
:func:`declare_precision`, before its prewarm and its first launch, on every generic kernel made so far and on
each one made later (:func:`at_every_precision`). The order is the same in every process (float32 at import,
float64 at the fit's start), so the cold process's build is the warm process's hash.

The parameter counts: every process declares the default run's (:data:`DEFAULT_PARAM_COUNTS`); a fit of another
group of models declares its own with :func:`declare_param_counts` before its prewarm and first launch (the
radiance models' group, fit/stages/prewarm.py ``KERNEL_GROUPS``), in the same place in every process, so a
radiance run's generic modules are built once with every count its candidates launch. Counts no group names
(anisotropic Lafortune, the ambient layouts) and ``stream.image_precision`` fp16 still add their overload at
their first launch and compile then, the declared ones with them.
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


COMPUTE_PRECISIONS = {"fp32": wp.float32, "fp64": wp.float64}
"""the compute scalars of ``stream.accumulate``'s resolved precisions (fit/stream/config.py)"""
_declared_scalars: list = [COMPUTE_SCALAR]
"""the compute scalars declared in this process, in the order they were"""
_declarers: list = []
"""every kernel's declaration of a compute scalar, as a function of the scalar"""
_declared_counts: list = list(DEFAULT_PARAM_COUNTS)
"""the parameter counts declared in this process, in the order they were"""
_count_declarers: list = []
"""every generic kernel's declaration of one parameter count, as a function of (compute scalar, count)"""


def at_every_precision(declarer) -> None:
    """Call ``declarer(scalar)`` for each compute scalar declared so far, and keep it for those declared later."""
    _declarers.append(declarer)
    for scalar in list(_declared_scalars):
        declarer(scalar)


def declare_precision(precision: str) -> None:
    """Declare every generic kernel's overloads of the compute precision ``precision`` ("fp32" or "fp64"), once
    per process, before a fit that accumulates in it builds or launches a kernel."""
    scalar = COMPUTE_PRECISIONS[precision]
    if scalar in _declared_scalars:
        return
    _declared_scalars.append(scalar)
    for declarer in list(_declarers):
        declarer(scalar)
    for declarer in list(_count_declarers):
        for n in list(_declared_counts):
            declarer(scalar, n)


def at_every_count(declarer) -> None:
    """A generic kernel's overloads: ``declarer(scalar, n_params)`` for each compute scalar and parameter count
    declared so far, and for each declared later (:func:`declare_precision`, :func:`declare_param_counts`)."""
    _count_declarers.append(declarer)
    for scalar in list(_declared_scalars):
        for n in list(_declared_counts):
            declarer(scalar, n)


def declare_param_counts(counts) -> None:
    """Declare the generic kernels' overloads of each parameter count in ``counts`` not declared yet, at every
    declared compute precision, before a fit that launches them builds or launches a kernel."""
    for n in counts:
        if int(n) in _declared_counts:
            continue
        _declared_counts.append(int(n))
        for declarer in list(_count_declarers):
            for scalar in list(_declared_scalars):
                declarer(scalar, int(n))


def declared_param_counts() -> tuple:
    """The parameter counts declared in this process, the default run's first."""
    return tuple(_declared_counts)


def declared_precisions() -> tuple:
    """The compute precisions declared in this process ("fp32", and "fp64" after a float64 fit's start)."""
    return tuple(name for name, scalar in COMPUTE_PRECISIONS.items() if scalar in _declared_scalars)


def param_overload(n_params: int, scalar=COMPUTE_SCALAR):
    """(scalar, parameter vector, parameter matrix) of ``n_params`` parameters at the compute precision ``scalar``."""
    return (scalar, *param_types(n_params, scalar))
