"""The fit of the radiance models (radiance, view-dependent radiance): the shared per-texel fit
(fit/models/per_texel/fit.py) under the radiance models' stopping rule (:func:`settled_config`); what differs
between the per-texel kinds is their layout traits (declared in each plugin's __init__.py)."""

from __future__ import annotations

import dataclasses

from texstream.fit.models.per_texel.fit import fit as per_texel_fit
from texstream.fit.optim.fitter import FitConfig

SETTLED_REL_TOL = 1e-3
"""the radiance models' stopping rule: the fit stops after the first iteration that lowers its objective (the
robust loss of the fitted photos' residuals: training data only) by less than this fraction. The view-dependent
radiance is linear least squares per texel, which Levenberg-Marquardt solves in its first iteration: on the
temple its objective moved by 2e-5 of itself after the first of 10 iterations; the radiance model's robust
(Cauchy) loss reweights its samples and settles more slowly, by 0.1% per iteration after 13 of 30 iterations.
Measured on the temple's registered cameras and mesh (2-core CPU; held out: templeSR0010): view_radiance 2
iterations instead of 10, held-out PSNR 24.67 dB either way (to 1e-5 dB), the candidate's CPU time 24.8 s
against 45.4 s; radiance 13 instead of 30, 23.33 against 23.32 dB, 16.6 s against 24.0 s."""

SETTLED_SYNC_EVERY = 1
"""the radiance models test the rule after every iteration (one scalar read of the trace), so a fit settled after
its second stops there rather than at the tenth (FitConfig's sync_every 5 tests at 5 and 10 at the earliest)"""


def settled_config(cfg):
    """The fit stage config ``cfg`` with the radiance models' stopping rule (:data:`SETTLED_REL_TOL` after every
    iteration) where its fit config keeps FitConfig's own ``rel_tol`` and ``sync_every``; a rule given by the
    caller (``--rel-tol``, ``--sync-every``, a config file) is kept as it is."""
    fit = cfg.fit
    defaults = {f.name: f.default for f in dataclasses.fields(FitConfig) if f.name in ("rel_tol", "sync_every")}
    if fit.rel_tol != defaults["rel_tol"] or fit.sync_every != defaults["sync_every"]:
        return cfg
    return dataclasses.replace(cfg, fit=dataclasses.replace(fit, rel_tol=SETTLED_REL_TOL,
                                                            sync_every=SETTLED_SYNC_EVERY))


def fit(request):
    """The plugin's fit (registry.FitRequest): the per-texel fit under :func:`settled_config`."""
    return per_texel_fit(dataclasses.replace(request, cfg=settled_config(request.cfg)))
