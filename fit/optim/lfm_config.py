"""Light field mapping options (``--model lfm``): a module of its own, without kernels, so that every fit's
config (fit/optim/fitter.py ``FitConfig.lfm``) reads them without building the LFM kernels (fit/models/lfm/problem.py)."""

from __future__ import annotations

import dataclasses

from texstream.core.config import option
from texstream.core.errors import ConfigError

VIEW_MAPS = ("disk", "hemioct")
OPTIMIZERS = ("cg", "sd", "lbfgs")
LOOKUPS = ("nearest", "bilinear")


@dataclasses.dataclass
class LFMConfig:
    """Light field mapping options (``--model lfm``)."""

    terms: int = option(1, "approximation terms K per vertex light field", min=1, max=4)
    view_res: int = option(8, "view map side R (texels) per vertex and term", min=2, max=64)
    view_map: str = option("disk", "view map parameterisation of the vertex's hemisphere: disk (Nusselt analog, "
                                   "the dissertation's) or hemioct (hemi-octahedral, fills the square)",
                           choices=VIEW_MAPS)
    lookup: str = option("bilinear", "view map lookup: nearest (the dissertation's) or bilinear", choices=LOOKUPS)
    surface_lookup: str = option("bilinear", "rendering: the atlas lookup of the surface maps, nearest texel or "
                                             "bilinear blend of the four texels' models", choices=LOOKUPS)
    diffuse: str = option("mean", "view-independent term: mean (least squares per texel, PCA-style) or min "
                                  "(minimum sample per texel, NMF-style)", choices=("mean", "min"))
    method: str = option("stream", "stream (streaming nonlinear fit), pca (Chen et al.: resample into texels x "
                                   "view-map directions, truncated SVD) or nmf (the same matrices, multiplicative "
                                   "updates)", choices=("stream", "pca", "nmf"))
    optimizer: str = option("cg", "streaming fit: cg (Polak-Ribiere+ per patch), sd (steepest descent) or lbfgs "
                                  "(limited-memory BFGS per patch, history of lbfgs_memory pairs)",
                            choices=OPTIMIZERS)
    precondition: str = option("none", "cg / sd: none, or jacobi (the direction from the gradient scaled by the "
                                       "inverse Gauss-Newton diagonal of the patch, computed at the start and at "
                                       "every gauge balancing, fixed in between)", choices=("none", "jacobi"))
    lbfgs_memory: int = option(5, "lbfgs: (step, gradient change) pairs kept per patch", min=1, max=32)
    cg_variant: str = option("pr", "cg beta: pr (Polak-Ribiere+) or fr (Fletcher-Reeves)", choices=("pr", "fr"))
    step: str = option("hessian", "step size: hessian (-g.d / d^T H d from a curvature pass, the dissertation's "
                                  "quadratic model) or backtrack (double on acceptance, halve on rejection; for "
                                  "lbfgs at most 1, the quasi-Newton step, and no curvature pass)",
                       choices=("hessian", "backtrack"))
    laplacian: float = option(1.0, "view-map Laplacian regularization weight, in samples' worth of squared "
                                   "radiance-space residual per unit squared difference of neighbouring view "
                                   "texels (fills directions no photo saw); 0 = none", min=0.0)
    bounds: str = option("none", "surface and view map bounds: none, or nonnegative (with diffuse min, NMF-like)",
                         choices=("none", "nonnegative"))
    iterations: int = option(100, "streaming fit: iteration cap", min=1)
    rel_tol: float = option(1e-7, "streaming fit: stop when the objective's relative decrease over sync_every "
                                  "iterations is below this", min=0.0)
    sync_every: int = option(5, "streaming fit: iterations between reads of the objective", min=1)
    balance_every: int = option(10, "streaming fit: every k iterations equalise the norms of each term's surface "
                                    "and view maps per patch (the g h scale gauge; costs a pass and restarts CG / "
                                    "L-BFGS; with the Laplacian on only view maps larger than their surface maps "
                                    "are shrunk, which lowers the objective); 0 = never", min=0)
    photo_batch: int = option(0, "streaming fit: photos per batch of launches (their observations and slot "
                                 "residuals held together on the device; the same sums as one photo at a time); "
                                 "0 = as many as fit in 1 GiB on a GPU, 512 MiB on the CPU, at most 64", min=0)
    sample_cache: str = option("auto", "streaming fit: keep every photo's samples on the device (float32, photos x "
                                       "texels x 16 bytes; the same values) after the first pass instead of "
                                       "distributing the photos again at every pass: on, off, or auto (on when they "
                                       "take no more device memory than the photos held; on the CPU, up to 1 GiB "
                                       "whatever the photos take)",
                               choices=("auto", "on", "off"))
    nmf_iterations: int = option(200, "nmf: multiplicative update iterations", min=1)
    render_view: str = option("point", "rendering: each vertex's view map read along the direction from the shaded "
                                       "point (point, the interpolated view of Chen et al.'s renderer) or from the "
                                       "vertex (vertex, what the fit assumes)", choices=("point", "vertex"))

    def check(self) -> None:
        for name, allowed in (("view_map", VIEW_MAPS), ("lookup", LOOKUPS), ("surface_lookup", LOOKUPS),
                              ("diffuse", ("mean", "min")), ("method", ("stream", "pca", "nmf")),
                              ("optimizer", OPTIMIZERS), ("step", ("hessian", "backtrack")),
                              ("bounds", ("none", "nonnegative")), ("render_view", ("point", "vertex")),
                              ("cg_variant", ("pr", "fr")), ("sample_cache", ("auto", "on", "off")),
                              ("precondition", ("none", "jacobi"))):
            if getattr(self, name) not in allowed:
                raise ConfigError(f"lfm.{name} {getattr(self, name)!r} unknown", fix=f"use one of {allowed}")
        if not 1 <= self.terms <= 4:
            raise ConfigError(f"lfm.terms {self.terms} out of range", fix="use 1 to 4")
        if not 2 <= self.view_res <= 64:
            raise ConfigError(f"lfm.view_res {self.view_res} out of range", fix="use 2 to 64")
        if self.precondition == "jacobi" and self.optimizer == "lbfgs":
            raise ConfigError("lfm.precondition jacobi is for cg and sd", fix="use --lfm.precondition none with lbfgs")
        if not 1 <= self.lbfgs_memory <= 32:
            raise ConfigError(f"lfm.lbfgs_memory {self.lbfgs_memory} out of range", fix="use 1 to 32")
