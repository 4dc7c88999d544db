"""Photometric shading normals under known lights (:class:`ShadingNormals`), on the device state of the
photometric refinement (geometry/refine.py, which runs them after its levels: ``normal_iterations``,
``intensity_iterations``). Kernels in geometry/refine_normal_kernels.py; numpy and warp only."""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from . import refine_kernels as rk
from . import refine_normal_kernels as rnk


class ShadingNormals:
    """Photometric shading normals under known lights, on a :class:`PhotometricRefinement`'s device state.

    Each welded vertex's normal is its start normal b tilted in its tangent plane, n = normalize(b + x0 tu +
    x1 tv); a texel's shading normal interpolates its face's vertex normals. A sample's residual is r = I - C
    s (wi . n_t) (``refine_kernels.observe``: the texture's colour C, the photo's exposure and the light's
    irradiance s, the unit direction to the light wi; the texel's surface normal, not its shading normal,
    decides visibility and weighs the sample). Samples are compared in intensities (the shading is the
    signal), averaged over each vertex's patch (its faces' texels, weighted by its barycentric share): the
    objective is the sum over photos and vertices of W rho(R), R the patch's weighted mean residual, W its
    weight, rho the Huber loss. The mean keeps the shading, smooth on the surface, and averages out most of
    the residual a texel's point samples leave where the photos alias the texture.

    An iteration: the colours in closed form, then with them held a damped Gauss-Newton step of every tilt
    (exact gradient, a lumped 2x2 curvature per vertex) with a smoothness of the correction between neighbours
    and a pull toward the start, solved by Jacobi sweeps; the step is clamped, and each vertex keeps it where
    its patch's objective plus its priors fell. No host reads."""

    def __init__(self, job: PhotometricRefinement, start: np.ndarray):
        self.job, cfg, dev, n = job, job.cfg, job.device, job.n_welded
        base = np.asarray(start, np.float64)
        base = base / np.maximum(np.linalg.norm(base, axis=1, keepdims=True), 1e-30)
        helper = np.where(np.abs(base[:, :1]) < 0.6, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        tu = np.cross(base, helper)
        tu /= np.linalg.norm(tu, axis=1, keepdims=True)
        self.start = base
        vec3 = {"dtype": wp.vec3, "device": dev}
        self.base, self.tu, self.tv = (wp.array(a.astype(np.float32), **vec3)
                                       for a in (base, tu, np.cross(base, tu)))
        self.shade = wp.array(base.astype(np.float32), **vec3)
        self.tilt = wp.zeros(n, dtype=wp.vec2, device=dev)
        self.saved, self.x_a, self.x_b = (wp.zeros_like(self.tilt) for _ in range(3))
        self.system = wp.zeros((n, rnk.NORMAL_TERMS), dtype=wp.float64, device=dev)
        self.before = wp.zeros((n, 2), dtype=wp.float64, device=dev)
        self.after = wp.zeros_like(self.before)
        self.mean = wp.zeros(2, dtype=wp.float64, device=dev)
        self.prior_before = wp.zeros(n, dtype=wp.float64, device=dev)
        self.prior_after = wp.zeros_like(self.prior_before)
        self.damping = wp.full(n, 1e-3, dtype=wp.float64, device=dev)
        self.accepted = wp.zeros(1, dtype=wp.int32, device=dev)
        shape = (len(job.frames), n)
        self.patch_w = wp.zeros(shape, dtype=float, device=dev)
        self.patch_r, self.patch_ju, self.patch_jv, self.back = (wp.zeros(shape, **vec3) for _ in range(4))
        self.max_step = math.tan(math.radians(min(2.0, cfg.max_normal_tilt)))
        self.max_total = math.tan(math.radians(cfg.max_normal_tilt))
        job.t_shade = wp.empty_like(job.t_n)
        self.texel_normals()
        job._gaussian_blur(cfg.intensity_blur, job.blurred)  # intensities: shading is the signal

    def texel_normals(self) -> None:
        """The texels' shading normals from the vertices'."""
        j = self.job
        wp.launch(rnk.texel_normals_kernel, dim=j.n_texels, outputs=[j.t_shade], device=j.device,
                  inputs=[j.t_face, j.t_bary, j.faces, self.shade, j.weld])

    def set_tilt(self, tilt) -> None:
        """Tilts (welded vertices, 2) from the host (tests)."""
        self.tilt.assign(np.asarray(tilt, np.float32))
        wp.launch(rnk.tilted_normals_kernel, dim=self.job.n_welded, outputs=[self.shade],
                  inputs=[self.base, self.tu, self.tv, self.tilt], device=self.job.device)
        self.texel_normals()

    def evaluate(self, out, with_system: bool) -> None:
        """Each vertex's patch objective into ``out`` (welded vertices, 2: sum of W rho(R), sum of W) and,
        with ``with_system``, its tilt's lumped curvature and exact gradient into ``system`` (zeroed by the
        caller), the colours held."""
        j, cfg = self.job, self.job.cfg
        out.zero_()
        for a in (self.patch_w, self.patch_r, self.patch_ju, self.patch_jv, self.back):
            a.zero_()
        samples = (len(j.frames), j.n_texels)
        state = [j.t_p, j.t_n, j.t_shade, self.shade, self.base, self.tu, self.tv, self.tilt, j.colour,
                 j.known, cfg.cos_view_min, cfg.depth_tol]
        head = [j.infos, j.blurred, j.depth, j.roles, j.t_face, j.t_bary, j.faces, j.weld]
        wp.launch(rnk.patch_residual_kernel, dim=samples, device=j.device,
                  inputs=[*head, *state, int(with_system)],
                  outputs=[self.patch_w, self.patch_r, self.patch_ju, self.patch_jv])
        wp.launch(rnk.patch_system_kernel, dim=(len(j.frames), j.n_welded), device=j.device,
                  inputs=[self.patch_w, self.patch_r, self.patch_ju, self.patch_jv, j.huber,
                          int(with_system)],
                  outputs=[self.system, out, self.back])
        if with_system:
            wp.launch(rnk.normal_gradient_kernel, dim=samples, device=j.device,
                      inputs=[*head, *state, self.back], outputs=[self.system])

    def iterate(self, history) -> None:
        """One iteration (see the class); ``history`` (2,) += the objective before the step (sum, weight)."""
        j, cfg, dev, n = self.job, self.job.cfg, self.job.device, self.job.n_welded
        j.colours(j.blurred)
        self.system.zero_()
        self.evaluate(self.before, with_system=True)
        wp.launch(rk.vertex_total_kernel, dim=n, inputs=[self.before], outputs=[history], device=dev)
        self.mean.zero_()
        wp.launch(rnk.mean_tilt_curvature_kernel, dim=n, inputs=[self.system], outputs=[self.mean], device=dev)
        priors = [j.offsets, j.neighbours, self.base, self.tu, self.tv, self.mean, cfg.normal_smoothness,
                  cfg.normal_prior]
        wp.launch(rnk.tilt_prior_kernel, dim=n, inputs=[self.tilt, *priors], outputs=[self.prior_before],
                  device=dev)
        wp.copy(self.x_a, self.tilt)
        src, dst = self.x_a, self.x_b
        for _ in range(20):  # Jacobi sweeps: the priors spread a step over a few rings
            wp.launch(rnk.tilt_sweep_kernel, dim=n, device=dev,
                      inputs=[self.tilt, self.system, *priors, self.damping, src], outputs=[dst])
            src, dst = dst, src
        wp.launch(rnk.apply_tilt_kernel, dim=n, inputs=[src, self.max_step, self.max_total], device=dev,
                  outputs=[self.tilt, self.saved, self.base, self.tu, self.tv, self.shade])
        self.texel_normals()
        self.evaluate(self.after, with_system=False)
        wp.launch(rnk.tilt_prior_kernel, dim=n, inputs=[self.tilt, *priors], outputs=[self.prior_after],
                  device=dev)
        wp.launch(rnk.tilt_accept_kernel, dim=n, device=dev,
                  inputs=[self.before, self.after, self.prior_before, self.prior_after, self.saved],
                  outputs=[self.tilt, self.base, self.tu, self.tv, self.shade, self.damping, self.accepted])
        self.texel_normals()

    def normals(self) -> np.ndarray:
        """(welded vertices, 3) the current shading normals (a host read)."""
        return self.shade.numpy().astype(np.float64)
