"""Photometric refinement: registered cameras and the reconstructed mesh moved until the photos agree.

Structure from motion places each camera to within a pixel or two, and a mesh from sparse or dense points
lies within about as much of the surface; a texture of detail a few pixels across, fitted to such photos,
blurs and ghosts, and held-out views score far below what the same model reaches with exact cameras
(docs/real-data.md). This stage aligns them the way colour-map optimisation does (Zhou and Koltun 2014;
Open3D's ``color_map_optimization``), with the fit's streaming structure: every iteration streams every photo
over the atlas's texels and accumulates, per texel, a colour shared by all photos (the photo's shading divided
out: exposure, and a known light's irradiance and cosine), per photo, the Gauss-Newton system of a 6-degree-of-
freedom pose update, and per welded mesh vertex, the curvature and gradient of a displacement along its normal
(smoothed by a graph Laplacian). Steps are damped and kept only where the Huber objective falls, coarse to fine
over blurred copies of the photos.

Under known lights (every photo has one) the levels are followed by a shaded refinement
(:class:`ShadingNormals`, ``normal_iterations``, ``intensity_iterations``): the mesh's shading normals, which
set a known light's cosine, are fitted to the photos' intensities (per welded vertex, a tilt of its normal
from the smoothing choice of ``normal_smoothing``), then poses and displacements take further steps on the
intensities shaded by them, where the levels compare only the photos' detail. The normals are written as the
refined mesh's vertex normals.

Held-out photos (every ``holdout_every``-th, as the fit splits them) move neither the colours nor the mesh; with
``align_heldout`` each one's pose is aligned to the texture the other photos made (6 numbers per photo, as a
new photo is registered to a model), so their held-out scores measure the model rather than the camera
registration; the report says so.

Kernels in geometry/refine_kernels.py (the shading normals' in geometry/refine_shading.py and
geometry/refine_normal_kernels.py). On the CPU the heavy launches split their photos or texels over the cores
(``threads``, geometry/cpu_threads.py; the same bits). Imports only numpy and warp at import time.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import math
import os
import shutil
import time
from pathlib import Path

import numpy as np
import warp as wp

from texstream.capture.capture_json import Capture, Light, read_capture, split_holdout, write_capture
from texstream.core.config import save_config
from texstream.core.errors import ConfigError, InputError
from texstream.core.outputs import StageResult, atomic_output_dir, write_json_atomic
from texstream.core.progress import bar, phase, say
from texstream.render.camera import ImageInfo, PhotoFrame, image_infos, struct_array
from texstream.render.visibility import depth_maps_kernel

from . import refine_checkpoint
from . import refine_kernels as rk
from . import refine_levels as rl
from .refine_config import RefineConfig
from .refine_shading import ShadingNormals
from .bake import TexelBake, bake_texels
from .cpu_threads import threads_for
from .density import pixel_footprint
from .mesh_io import load_mesh, save_mesh


def _gaussian(sigma: float) -> tuple[np.ndarray, int]:
    if sigma <= 0.0:
        return np.ones(1, np.float32), 0
    radius = max(1, int(math.ceil(3.0 * sigma)))
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * (x / sigma) ** 2)
    return (w / w.sum()).astype(np.float32), radius


def weld_vertices(mesh) -> tuple[np.ndarray, np.ndarray]:
    """(weld index per vertex, welded positions): the vertices an atlas split along seams become one again
    (:meth:`~texstream.render.mesh.SurfaceMesh.weld_key`)."""
    key = mesh.weld_key()
    welded = np.zeros((int(key.max()) + 1 if key.size else 0, 3))
    welded[key] = np.asarray(mesh.vertices, np.float64)
    return key.astype(np.int32), welded


def welded_normals(welded: np.ndarray, faces_welded: np.ndarray) -> np.ndarray:
    """Area-weighted unit normals of the welded vertices."""
    v = welded[faces_welded]
    fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    acc = np.zeros_like(welded)
    for c in range(3):
        np.add.at(acc, faces_welded[:, c], fn)
    ln = np.linalg.norm(acc, axis=1, keepdims=True)
    return np.divide(acc, ln, out=np.tile([0.0, 0.0, 1.0], (len(acc), 1)), where=ln > 0)


def smoothed_normals(normals: np.ndarray, offsets: np.ndarray, neighbours: np.ndarray, rounds: int) -> np.ndarray:
    """Unit vertex normals averaged with their 1-ring neighbours' ``rounds`` times (CSR graph)."""
    out = np.asarray(normals, np.float64)
    counts = np.diff(offsets)
    owner = np.repeat(np.arange(len(out)), counts)
    for _ in range(rounds):
        acc = out.copy()
        np.add.at(acc, owner, out[neighbours])
        ln = np.linalg.norm(acc, axis=1, keepdims=True)
        out = np.divide(acc, ln, out=out.copy(), where=ln > 0)
    return out


def vertex_neighbours(faces_welded: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR (offsets, neighbours) of the welded mesh's edge graph."""
    e = np.concatenate([faces_welded[:, [0, 1]], faces_welded[:, [1, 2]], faces_welded[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    e = np.unique(e[e[:, 0] != e[:, 1]], axis=0)
    offsets = np.zeros(n + 1, np.int64)
    np.add.at(offsets, e[:, 0] + 1, 1)
    return np.cumsum(offsets).astype(np.int32), e[:, 1].astype(np.int32)


def camera_attached_lights(frames) -> tuple[np.ndarray, np.ndarray]:
    """(attached, offset in camera axes) per frame: a point light at the camera centre (a flash,
    ``--colocated-light``) moves with a refined camera; other lights stay where they are."""
    attached = np.zeros(len(frames), np.int32)
    offset = np.zeros((len(frames), 3), np.float32)
    for i, f in enumerate(frames):
        if f.light is not None and f.light.type == "point":
            cam = np.asarray(f.R, float) @ np.asarray(f.light.position, float) + np.asarray(f.t, float).reshape(3)
            if np.linalg.norm(cam) <= 1e-6 * max(np.linalg.norm(f.center), 1e-12):
                attached[i] = 1
                offset[i] = cam
    return attached, offset


@dataclasses.dataclass
class RefineResult:
    """Refined poses (world-to-camera R, t per frame), welded vertex displacements and the trace."""

    rotations: np.ndarray
    translations: np.ndarray
    points: np.ndarray
    displacement: np.ndarray
    trace: list
    summary: dict
    normals: np.ndarray | None = None
    """(welded vertices, 3) shading normals chosen for the refined mesh (None: the mesh's own)"""


class PhotometricRefinement:
    """The refinement's device state: photos, masks, depth maps, poses, mesh, texels (see the module)."""

    def __init__(self, capture, mesh, bake, cfg: RefineConfig, device: str = "cpu", log=None):
        self.cfg, self.device, self.log = cfg, device, log or (lambda m: None)
        self.frames = list(capture.frames)
        n = len(self.frames)
        fitted, held = split_holdout(self.frames, cfg.holdout_every)
        held_ids = {id(f) for f in held}
        roles = np.array([rk.ALIGN if id(f) in held_ids else rk.FIT for f in self.frames], np.int32)
        if not cfg.align_heldout:
            roles[roles == rk.ALIGN] = rk.UNUSED
        if not np.any(roles == rk.FIT):
            raise InputError("no photo left to refine with after the held-out split", capture.root,
                             "lower --holdout-every or add photos")
        self.roles_host = roles
        self.level, self.resolution = rl.finest_level(mesh, bake, self.frames, cfg.photo_level)
        self.schedule = rl.level_schedule(cfg.levels(), self.level, self.frames, cfg.pyramid)
        first = self.frames[0].intrinsics
        fine_mb = n * (first.height >> self.level) * (first.width >> self.level) * 12 * 4 / 2 ** 20
        if fine_mb > cfg.max_photo_mb:  # the photos, their blurred copy, a wide blur and scratch
            raise ConfigError(f"refining {n} photos of {first.width >> self.level}x{first.height >> self.level} "
                              f"takes {fine_mb:,.0f} MB (refine.max_photo_mb {cfg.max_photo_mb:,.0f})",
                              fix="raise --refine.max-photo-mb or --refine.photo-level, or run with --refine off")
        self.pyramid = rl.PhotoPyramid(capture, [lv for lv, _ in self.schedule] + [self.level])
        self.threads, self.pool = threads_for(cfg.threads, device), None
        if self.threads > 1:  # the kernels' modules loaded before two threads launch them
            wp.load_module(rk, device=device)
            wp.load_module(depth_maps_kernel.module, device=device)
            self.pool = concurrent.futures.ThreadPoolExecutor(self.threads, thread_name_prefix="texstream-refine")
        # texels: the bake's covered texels (a coarse level's: a coarser bake of the same charts), at the
        # surface's current position
        self.fine_level, self.texel_level = self.level, None
        self.bakes = {self.level: bake}
        if cfg.coarse_texels:
            for lv, _ in self.schedule:
                if lv not in self.bakes:  # a level repeated in the schedule bakes once
                    self.bakes[lv] = rl.coarse_bake(mesh, bake, lv - self.fine_level, device)
        images, masks, _ = self.pyramid.stacked(self.level)
        fg = masks.astype(bool)
        self.huber = cfg.huber * max(float(images[fg].sum()) / max(3.0 * float(fg.sum()), 1.0), 1e-12)
        del images, masks, fg
        pframes = [PhotoFrame.from_capture_frame(f) for f in self.pyramid.frames_at(self.level)]
        self.infos = struct_array(image_infos(pframes, None, None, 0.0, 0), ImageInfo, device)
        self.saved_infos = wp.empty_like(self.infos)
        self.set_level(self.level)
        self.roles = wp.array(roles, dtype=wp.int32, device=device)
        attached, offset = camera_attached_lights(self.frames)
        self.light_attached = wp.array(attached, dtype=wp.int32, device=device)
        self.light_offset = wp.array(offset, dtype=wp.vec3, device=device)

        # the mesh, welded so a displacement moves both sides of a seam
        self.mesh = mesh
        self.weld_host, welded = weld_vertices(mesh)
        faces = np.asarray(mesh.faces, np.int32)
        normals = welded_normals(welded, self.weld_host[faces])
        self.n_welded = len(welded)
        self.diagonal = float(np.linalg.norm(welded.max(axis=0) - welded.min(axis=0)))
        fitted_frames = [f for f, r in zip(self.pyramid.frames_at(self.fine_level), roles) if r == rk.FIT]
        try:  # scene units per finest-level pixel: the displacement's bound is in the photos' pixels
            self.pixel = pixel_footprint(mesh, fitted_frames)
        except ValueError:
            raise InputError("no fitted photo sees the mesh in front of its camera", capture.root,
                             "check that the mesh is in the cameras' frame") from None
        if cfg.mesh_level >= 0:  # dense stereo's mesh: about a pixel of the level it was made at off the surface
            self.max_displacement = (cfg.max_displacement_px * self.pixel
                                     * 2.0 ** max(0, cfg.mesh_level - self.fine_level))
        else:
            self.max_displacement = cfg.max_displacement * self.diagonal
        offsets, neighbours = vertex_neighbours(self.weld_host[faces], self.n_welded)
        self.graph_host = (offsets, neighbours)
        self.lit = all(f.light is not None for f in self.frames)
        self.weld = wp.array(self.weld_host, dtype=wp.int32, device=device)
        self.faces = wp.array(faces, dtype=wp.vec3i, device=device)
        self.base = wp.array(welded.astype(np.float32), dtype=wp.vec3, device=device)
        self.direction = wp.array(normals.astype(np.float32), dtype=wp.vec3, device=device)
        self.welded_points = wp.array(welded.astype(np.float32), dtype=wp.vec3, device=device)
        self.points = wp.array(np.asarray(mesh.vertices, np.float32), dtype=wp.vec3, device=device)
        self.bvh = wp.Mesh(points=self.points, indices=wp.array(faces.reshape(-1), dtype=wp.int32, device=device))
        self.offsets = wp.array(offsets, dtype=wp.int32, device=device)
        self.neighbours = wp.array(neighbours, dtype=wp.int32, device=device)
        self.disp = wp.zeros(self.n_welded, dtype=wp.float64, device=device)
        self.disp_saved = wp.zeros_like(self.disp)
        self.disp_a = wp.zeros_like(self.disp)
        self.disp_b = wp.zeros_like(self.disp)
        self.curvature = wp.zeros_like(self.disp)
        self.gradient = wp.zeros_like(self.disp)
        self.curv_mean = wp.zeros(2, dtype=wp.float64, device=device)
        self.disp_damping = wp.array([1.0], dtype=wp.float64, device=device)
        self.disp_accepted = wp.zeros(1, dtype=wp.int32, device=device)

        # per photo
        self.system = wp.zeros((n, rk.POSE_TERMS), dtype=wp.float64, device=device)
        self.obj_before = wp.zeros((n, 2), dtype=wp.float64, device=device)
        self.obj_after = wp.zeros_like(self.obj_before)
        self.pose_damping = wp.full(n, 1e-3, dtype=wp.float64, device=device)
        self.pose_accepted = wp.zeros(n, dtype=wp.int32, device=device)
        centres = np.array([f.center for f in self.frames])
        mid = 0.5 * (welded.max(axis=0) + welded.min(axis=0))
        self.max_translation = wp.array((cfg.max_translation_step * np.linalg.norm(centres - mid, axis=1)
                                         ).astype(np.float32), dtype=float, device=device)
        self.totals = wp.zeros(4, dtype=wp.float64, device=device)  # before sum, count; after sum, count

    def close(self) -> None:
        """End the launch threads (the state stays readable)."""
        if self.pool is not None:
            self.pool.shutdown()
            self.pool = None

    def _split(self, count: int, launch) -> None:
        """``launch(a, b)`` over [0, count) in ``threads`` parts, one a thread, on the CPU (Warp runs a CPU kernel
        on the launching thread and releases the GIL; the parts write disjoint rows, so the results are those of
        one launch to the bit); one launch elsewhere."""
        if self.pool is None or count < 2:
            launch(0, count)
            return
        parts = min(self.threads, count)
        edges = [count * i // parts for i in range(parts + 1)]
        for done in [self.pool.submit(launch, a, b) for a, b in zip(edges[:-1], edges[1:])]:
            done.result()

    def set_texels(self, level: int) -> None:
        """The texels of pyramid ``level``'s bake (the atlas's own without ``coarse_texels``), with their colour
        and scratch arrays."""
        bake = self.bakes.get(level, self.bakes[self.fine_level])
        if self.texel_level is not None and bake is self.bakes.get(self.texel_level, self.bakes[self.fine_level]):
            return
        self.texel_level, device = level, self.device
        covered = bake.covered.reshape(-1)
        self.n_texels = int(covered.sum())
        if self.n_texels == 0:
            raise InputError("the atlas has no texels", fix="re-run texstream atlas")
        self.t_face = wp.array(bake.face.reshape(-1)[covered].astype(np.int32), dtype=wp.int32, device=device)
        self.t_bary = wp.array(bake.bary.reshape(-1, 3)[covered].astype(np.float32), dtype=wp.vec3, device=device)
        self.t_p = wp.empty(self.n_texels, dtype=wp.vec3, device=device)
        self.t_n = wp.empty(self.n_texels, dtype=wp.vec3, device=device)
        self.t_shade = self.t_n  # the texels' shading normals: their surface normals until ShadingNormals
        self.num = wp.zeros(self.n_texels, dtype=wp.vec3, device=device)
        self.den = wp.zeros_like(self.num)
        self.colour = wp.zeros_like(self.num)
        self.known = wp.zeros(self.n_texels, dtype=wp.int32, device=device)

    def set_level(self, level: int) -> None:
        """The photos, masks and depth maps at pyramid ``level``, the cameras' intrinsics with them (poses kept)."""
        images, masks, sizes = self.pyramid.stacked(level)
        n, dev = len(self.frames), self.device
        self.hmax, self.wmax = images.shape[1:3]
        self.images = wp.array(images, dtype=wp.vec3, device=dev)
        self.blurred = wp.empty_like(self.images)
        self._scratch = wp.empty_like(self.images)
        self._wide = wp.empty_like(self.images) if self.cfg.detail > 0.0 else None
        self.masks = wp.array(masks, dtype=wp.uint8, device=dev)
        self.widths = wp.array(sizes[:, 1].astype(np.int32), device=dev)
        self.heights = wp.array(sizes[:, 0].astype(np.int32), device=dev)
        self.depth = wp.zeros((n, self.hmax, self.wmax), dtype=wp.float32, device=dev)
        self.depth_saved = wp.zeros_like(self.depth)
        self.set_texels(level)
        if level != self.level:
            infos = rl.rescale_infos(self.infos.numpy(), sizes, 2.0 ** (self.level - level))
            self.infos = struct_array(infos, ImageInfo, dev)
            self.saved_infos = wp.empty_like(self.infos)
        self.level = level

    # ------------------------------------------------------------------------------------------- passes
    def _gaussian_blur(self, sigma: float, out) -> None:
        w, radius = _gaussian(sigma)
        if radius == 0:
            wp.copy(out, self.images)
            return
        weights = wp.array(w, dtype=float, device=self.device)
        for src, along_x, dst in ((self.images, 1, self._scratch), (self._scratch, 0, out)):
            self._split(len(self.frames), lambda a, b: wp.launch(
                rk.blur_axis_kernel, dim=(b - a, self.hmax, self.wmax), device=self.device,
                inputs=[src[a:b], weights, radius, along_x, self.widths[a:b], self.heights[a:b]], outputs=[dst[a:b]]))

    def blur(self, sigma: float) -> None:
        """``blurred``: the photos at this level, blurred by ``sigma`` pixels, less their ``detail``-wide blur."""
        self._gaussian_blur(sigma, self.blurred)
        if self.cfg.detail > 0.0:
            self._gaussian_blur(self.cfg.detail, self._wide)
            wp.launch(rk.subtract_kernel, dim=(len(self.frames), self.hmax, self.wmax), inputs=[self._wide],
                      outputs=[self.blurred], device=self.device)

    def update_geometry(self, depth: bool = True) -> None:
        """Mesh vertices from the welded ones, the BVH, texel positions, and (``depth``) every photo's depth map."""
        wp.launch(rk.scatter_points_kernel, dim=len(self.mesh.vertices), inputs=[self.welded_points, self.weld],
                  outputs=[self.points], device=self.device)
        self.bvh.refit()
        wp.launch(rk.texel_points_kernel, dim=self.n_texels,
                  inputs=[self.t_face, self.t_bary, self.faces, self.points, self.direction, self.weld],
                  outputs=[self.t_p, self.t_n], device=self.device)
        if depth:
            self._split(len(self.frames), lambda a, b: wp.launch(
                depth_maps_kernel, dim=(b - a, self.hmax, self.wmax), device=self.device,
                inputs=[self.bvh.id, self.infos, a, self.masks[a:b], 1], outputs=[self.depth[a:b]]))

    def colours(self, images) -> None:
        self.num.zero_()
        self.den.zero_()
        self._split(self.n_texels, lambda a, b: wp.launch(  # by texels: a texel's sums keep the photos' order
            rk.albedo_sums_kernel, dim=(len(self.frames), b - a), device=self.device,
            inputs=[self.infos, images, self.depth, self.roles, self.t_p[a:b], self.t_n[a:b], self.t_shade[a:b],
                    self.cfg.cos_view_min, self.cfg.depth_tol], outputs=[self.num[a:b], self.den[a:b]]))
        wp.launch(rk.albedo_kernel, dim=self.n_texels, inputs=[self.num, self.den], outputs=[self.colour, self.known],
                  device=self.device)

    def objective(self, images, out, system: bool = False) -> None:
        """Per-photo Huber objective (and the pose systems) into ``out`` (n, 2: sum, samples)."""
        out.zero_()
        if system:
            self.system.zero_()
        self._split(len(self.frames), lambda a, b: wp.launch(  # by photos: each has its own sums
            rk.pose_system_kernel, dim=(b - a, self.n_texels), device=self.device,
            inputs=[self.infos[a:b], images[a:b], self.depth[a:b], self.roles[a:b], self.t_p, self.t_n,
                    self.t_shade, self.colour, self.known, self.cfg.cos_view_min, self.cfg.depth_tol, self.huber,
                    int(system)],
            outputs=[self.system[a:b], out[a:b]]))

    def geometry_step(self, images, objective=None) -> None:
        """One pose step of every camera (``cameras``), then the colours and one displacement step of the mesh
        (``mesh``), each followed by the geometry's update; the colours the pose step compares are the caller's.
        With ``objective`` (n, 2), the per-photo objective after the step, against the colours it compared."""
        if self.cfg.cameras:
            self.pose_step(images)
            self.update_geometry()
        if not self.cfg.mesh:
            if objective is not None:
                self.objective(images, objective)
            return
        if self.cfg.cameras:
            self.colours(images)  # else the caller's are still current
        self.displacement_step(images)
        # a kept step leaves the depth maps it was scored with, a refused one those before it (restored);
        # the objective after the step is the one of the two the geometry kept, with the same colours
        self.update_geometry(depth=False)
        wp.launch(rk.keep_depth_kernel, dim=(len(self.frames), self.hmax, self.wmax), device=self.device,
                  inputs=[self.totals[0:2], self.totals[2:4], self.depth_saved], outputs=[self.depth])
        if objective is not None:
            wp.launch(rk.kept_objective_kernel, dim=len(self.frames), device=self.device,
                      inputs=[self.totals[0:2], self.totals[2:4], self.obj_before, self.obj_after],
                      outputs=[objective])

    def pose_step(self, images) -> None:
        self.objective(images, self.obj_before, system=True)
        wp.launch(rk.pose_step_kernel, dim=len(self.frames), device=self.device,
                  inputs=[self.system, self.pose_damping, math.radians(self.cfg.max_rotation_step),
                          self.max_translation, 12, self.light_attached, self.light_offset],
                  outputs=[self.infos, self.saved_infos])
        self.objective(images, self.obj_after)
        wp.launch(rk.pose_accept_kernel, dim=len(self.frames), device=self.device,
                  inputs=[self.obj_before, self.obj_after, self.saved_infos],
                  outputs=[self.infos, self.pose_damping, self.pose_accepted])

    def displacement_step(self, images) -> None:
        dev = self.device
        self.objective(images, self.obj_before)
        self.curvature.zero_()
        self.gradient.zero_()
        self.curv_mean.zero_()
        wp.launch(rk.vertex_system_kernel, dim=(len(self.frames), self.n_texels), device=dev,
                  inputs=[self.infos, images, self.depth, self.roles, self.t_face, self.t_bary, self.faces, self.weld,
                          self.direction, self.t_p, self.t_n, self.t_shade, self.colour, self.known,
                          self.cfg.cos_view_min, self.cfg.depth_tol, self.huber],
                  outputs=[self.curvature, self.gradient])
        wp.launch(rk.mean_curvature_kernel, dim=self.n_welded, inputs=[self.curvature], outputs=[self.curv_mean],
                  device=dev)
        wp.copy(self.disp_a, self.disp)
        src, dst = self.disp_a, self.disp_b
        for _ in range(30):  # Jacobi sweeps: the Laplacian spreads a step over ~5 rings of vertices
            wp.launch(rk.displacement_sweep_kernel, dim=self.n_welded, device=dev,
                      inputs=[self.disp, self.curvature, self.gradient, self.offsets, self.neighbours, self.curv_mean,
                              self.cfg.smoothness, self.disp_damping, src], outputs=[dst])
            src, dst = dst, src
        edge = self.max_displacement
        wp.launch(rk.apply_displacement_kernel, dim=self.n_welded, device=dev,
                  inputs=[src, 0.25 * edge, edge], outputs=[self.disp, self.disp_saved, self.base, self.direction,
                                                             self.welded_points])
        wp.copy(self.depth_saved, self.depth)  # a refused step restores them (geometry_step)
        self.update_geometry()
        self.objective(images, self.obj_after)
        self.totals.zero_()
        wp.launch(rk.total_kernel, dim=len(self.frames), inputs=[self.obj_before, self.roles],
                  outputs=[self.totals], device=dev)
        wp.launch(rk.total_kernel, dim=len(self.frames), inputs=[self.obj_after, self.roles],
                  outputs=[self.totals[2:]], device=dev)
        wp.launch(rk.displacement_accept_kernel, dim=self.n_welded, device=dev,
                  inputs=[self.totals[0:2], self.totals[2:4], self.disp_saved],
                  outputs=[self.disp, self.base, self.direction, self.welded_points, self.disp_damping,
                           self.disp_accepted])

    def run(self, checkpoint=None) -> RefineResult:
        """Every level's iterations (colours, pose steps, displacement steps), then the summary; with a
        ``checkpoint`` (:func:`.refine_checkpoint.refine_checkpoint`) the state is saved after an iteration
        (every ``checkpoint_every_s`` seconds and at each level's end) and a saved one resumed from."""
        cfg, finest, schedule = self.cfg, self.level, self.schedule
        t0 = time.perf_counter()
        history = wp.zeros((len(schedule) * cfg.iterations, len(self.frames), 2), dtype=wp.float64,
                           device=self.device)
        saved = None if checkpoint is None else refine_checkpoint.restore_state(self, checkpoint, history)
        self.set_level(finest)  # a resumed state's cameras are at the level it was saved at
        self.update_geometry()
        self.blur(0.0)
        self.colours(self.blurred)
        if saved is None:
            step, start = 0, self._score()
            if checkpoint is not None:
                refine_checkpoint.save_start(checkpoint, start)
        else:
            step, start = saved
            checkpoint.say(f"resuming from {checkpoint.folder}: {step} of {len(schedule) * cfg.iterations} "
                           "iterations of the levels done")
        shaded = self.lit and cfg.normal_iterations > 0
        extra = cfg.normal_iterations + cfg.intensity_iterations if shaded else 0
        progress = bar(total=len(schedule) * cfg.iterations + extra, desc="refine", unit="it")
        progress.update(step)
        ran, finer = [], {"ran": len(schedule) > 1, "reason": "one blur level"}
        if step > cfg.iterations:  # resumed after the coarse level: its decision as it was taken
            finer = refine_checkpoint.read_decision(checkpoint) or {"ran": True,
                                                                    "reason": "resumed after the coarse level"}
        saved_at = time.perf_counter()
        for k, (level, sigma) in enumerate(schedule):
            if k == 1 and step <= cfg.iterations:  # the coarse level just finished (or did before an interruption)
                moved, by = rl.coarse_moved(self, self.frames, self.pyramid.frames_at(finest), cfg.min_move)
                finer = {"ran": moved, "moved_finest_px": by, "reason": (
                    f"the coarse level moved a camera or the mesh by {max(by.values()):.3g} px of level {finest}, "
                    + (f"at least {cfg.min_move:g}: the finer levels ran" if moved else
                       f"less than {cfg.min_move:g}: the finer levels skipped"))}
                if checkpoint is not None:
                    refine_checkpoint.save_decision(checkpoint, finer)
                if not moved:
                    progress.update((len(schedule) - 1) * cfg.iterations)
                    break
            ran.append(k)
            if step >= (k + 1) * cfg.iterations:
                continue  # done before the interruption
            self.set_level(level)
            self.update_geometry()
            self.blur(sigma)
            self.log(f"level {level}, blur {sigma:g} px: at most {cfg.iterations} iterations")
            step, saved_at = self._level_iterations(k, step, history, checkpoint, progress, saved_at)
        hist = history.numpy()  # read once, after the loop
        trace = [{"photo_level": schedule[k][0], "blur_px": schedule[k][1], "iteration": it,
                  **self._per_role(hist[k * cfg.iterations + it])} for k in ran for it in range(cfg.iterations)
                 if hist[k * cfg.iterations + it, :, 1].sum() > 0]  # a settled level's rows after its stop: 0
        self.set_level(finest)
        self.update_geometry()
        self.blur(0.0)
        self.colours(self.blurred)
        end = self._score()
        rounds, normals, scores = self.choose_shading_normals()
        shading = {"smoothing_rounds": rounds, "intensity_rms_by_rounds": scores}
        if shaded:
            if normals is None:
                welded = self.welded_points.numpy().astype(np.float64)  # once, after the loop
                normals = welded_normals(welded, self.weld_host[np.asarray(self.mesh.faces, np.int32)])
            normals, shading["photometric"] = self.shaded_refinement(normals, progress)
        progress.close()
        result = self._result(start, end, trace, time.perf_counter() - t0)
        result.summary["shading_normals"] = shading
        result.summary["levels"] = {"schedule": [{"photo_level": lv, "blur_px": b} for lv, b in schedule],
                                    "ran": len(ran), "finer_levels": finer,
                                    "iterations": [int((hist[k * cfg.iterations:(k + 1) * cfg.iterations, :, 1]
                                                        .sum(axis=1) > 0).sum()) for k in ran],
                                    "rel_tol": cfg.rel_tol}
        size = self.resolution["size"]
        result.summary["resolution"] = (
            f"{size[0]}x{size[1]} (level {finest}; {self.resolution['why']}); coarse first at level {schedule[0][0]}"
            + ("" if len(schedule) == 1 else f"; {finer['reason']}"))
        result.normals = normals
        return result

    def _level_iterations(self, k: int, step: int, history, checkpoint, progress, saved_at: float):
        """Level ``k``'s iterations from ``step`` (of the levels' count; each level has ``iterations`` rows of
        ``history``), until they are done or the objective settled: an iteration lowered the fitted photos' mean
        objective per sample by less than ``rel_tol`` of it (the level's rows left are skipped, zero in
        ``history``). Returns (step, time of the last checkpoint save)."""
        cfg = self.cfg
        end = (k + 1) * cfg.iterations

        fitted = self.roles_host == rk.FIT  # the held-out photos' rows play no part in when to stop

        def mean(row) -> float:  # one small read an iteration
            sums = history[row].numpy()[fitted].sum(axis=0)
            return sums[0] / max(sums[1], 1.0)

        previous = mean(step - 1) if cfg.rel_tol > 0.0 and step > k * cfg.iterations else None  # resumed in it
        while step < end:
            progress.update(1)
            self.colours(self.blurred)
            self.geometry_step(self.blurred, history[step])
            step += 1
            if cfg.rel_tol > 0.0 and step < end:
                current = mean(step - 1)
                if previous is not None and previous - current < cfg.rel_tol * previous:
                    progress.update(end - step)
                    step = end
                previous = current
            if checkpoint is not None and (step == end or time.perf_counter() - saved_at >= cfg.checkpoint_every_s):
                refine_checkpoint.save_state(self, checkpoint, step, history)
                saved_at = time.perf_counter()
        return step, saved_at

    def shaded_refinement(self, start: np.ndarray, progress=None) -> tuple[np.ndarray, dict]:
        """With known lights, after the levels: ``normal_iterations`` of :meth:`ShadingNormals.iterate` from
        ``start`` (welded unit normals), then ``intensity_iterations`` of (a pose step, a displacement step,
        each on the photos' intensities against the texture shaded by the fitted normals; one iteration of the
        normals). Returns (welded shading normals, summary)."""
        cfg, dev, n = self.cfg, self.device, self.n_welded
        job = ShadingNormals(self, start)
        f64 = {"dtype": wp.float64, "device": dev}
        history = wp.zeros((cfg.normal_iterations + cfg.intensity_iterations + 1, 2), **f64)
        intensity = wp.zeros((cfg.intensity_iterations + 1, len(self.frames), 2), **f64)
        self.log(f"shading normals: {cfg.normal_iterations} iterations, then {cfg.intensity_iterations} on "
                 "intensities")
        for it in range(cfg.normal_iterations):
            job.iterate(history[it])
            if progress is not None:
                progress.update(1)
        self.colours(self.blurred)
        self.objective(self.blurred, intensity[0])
        for it in range(cfg.intensity_iterations):
            if progress is not None:
                progress.update(1)
            self.geometry_step(self.blurred)
            job.iterate(history[cfg.normal_iterations + it])  # colours first
            self.colours(self.blurred)
            self.objective(self.blurred, intensity[it + 1])
        job.evaluate(job.before, with_system=False)
        wp.launch(rk.vertex_total_kernel, dim=n, inputs=[job.before], outputs=[history[-1]], device=dev)
        hist, inten = history.numpy(), intensity.numpy()  # read once, after the loops
        normals = job.normals()
        self.t_shade = self.t_n
        angle = np.degrees(np.arccos(np.clip(np.sum(normals * job.start, axis=1), -1.0, 1.0)))
        return normals, {
            "normal_iterations": cfg.normal_iterations, "intensity_iterations": cfg.intensity_iterations,
            "patch_rms": [float(math.sqrt(2.0 * a / c)) if c > 0 else None for a, c in hist],
            "intensity_rms": [self._per_role(h) for h in inten],
            "vertex_steps_kept": int(job.accepted.numpy()[0]),
            "tilt_deg": {"median": float(np.median(angle)), "p90": float(np.percentile(angle, 90)),
                         "max": float(angle.max())}}

    def choose_shading_normals(self) -> tuple[int, np.ndarray | None, dict]:
        """After the iterations: the refined mesh's vertex normals averaged over 1-ring neighbours for each of
        ``normal_smoothing``'s rounds, scored by the fitted photos' intensity residual (unblurred, no detail
        band: shading is what normals change) against the shared texture each makes; with known lights only
        (without, shading is not modelled and the mesh's own normals stay). Returns (rounds, welded normals or
        None for the mesh's own, {rounds: RMS})."""
        rounds = self.cfg.smoothing_rounds()
        if rounds == [0] or not self.lit:
            return 0, None, {}
        welded = self.welded_points.numpy().astype(np.float64)  # once, after the loop
        faces = self.weld_host[np.asarray(self.mesh.faces, np.int32)]
        own = welded_normals(welded, faces)
        kept = wp.clone(self.direction)
        self._gaussian_blur(0.0, self.blurred)  # intensities
        scores, candidates = {}, {}
        for r in rounds:
            candidates[r] = smoothed_normals(own, *self.graph_host, r)
            self.direction.assign(candidates[r].astype(np.float32))  # the texels' shading normals read it
            wp.launch(rk.texel_points_kernel, dim=self.n_texels,
                      inputs=[self.t_face, self.t_bary, self.faces, self.points, self.direction, self.weld],
                      outputs=[self.t_p, self.t_n], device=self.device)
            self.colours(self.blurred)
            self.objective(self.blurred, self.obj_after)
            scores[r] = self._per_role(self.obj_after.numpy())["fit_rms"]
        wp.copy(self.direction, kept)
        best = min(rounds, key=lambda r: (math.inf if scores[r] is None else scores[r], r))
        return best, candidates[best], {str(r): v for r, v in scores.items()}

    # ------------------------------------------------------------------------------------------ results
    def _per_role(self, obj: np.ndarray) -> dict:
        out = {}
        for name, role in (("fit", rk.FIT), ("align", rk.ALIGN)):
            sel = self.roles_host == role
            if sel.any():
                s, c = obj[sel, 0].sum(), obj[sel, 1].sum()
                # None: no sample of that role this pass (a photo too small to see a texel), no residual to give
                out[f"{name}_rms"] = float(math.sqrt(2.0 * s / c)) if c > 0 else None
        return out

    def _score(self) -> dict:
        """Huber-RMS residual of the photos as compared (unblurred; their detail when ``detail`` is on) against
        the colours they make, per role."""
        self.objective(self.blurred, self.obj_after)
        return self._per_role(self.obj_after.numpy())

    def _result(self, start: dict, end: dict, trace: list, seconds: float) -> RefineResult:
        infos = self.infos.numpy()
        rot = np.asarray(infos["rot"], np.float64).reshape(-1, 3, 3)
        trans = np.asarray(infos["trans"], np.float64).reshape(-1, 3)
        disp = self.disp.numpy()
        before_c = np.array([f.center for f in self.frames])
        after_c = -np.einsum("nji,nj->ni", rot, trans)
        dang = []
        for f, r in zip(self.frames, rot):
            c = np.clip((np.trace(r @ np.asarray(f.R, float).T) - 1.0) / 2.0, -1.0, 1.0)
            dang.append(math.degrees(math.acos(c)))
        dpos = np.linalg.norm(after_c - before_c, axis=1) / self.diagonal
        accepted_poses = self.pose_accepted.numpy()
        summary = {
            "photos": len(self.frames), "fitted": int((self.roles_host == rk.FIT).sum()),
            "aligned_heldout": int((self.roles_host == rk.ALIGN).sum()),
            "texels": self.n_texels, "welded_vertices": self.n_welded, "seconds": seconds,
            "residual_before": start, "residual_after": end,
            "camera_rotation_deg": {"median": float(np.median(dang)), "max": float(np.max(dang))},
            "camera_centre_moved": {"median": float(np.median(dpos)), "max": float(np.max(dpos)),
                                    "unit": "bounding-box diagonal"},
            "pose_steps_kept": {"median": float(np.median(accepted_poses)), "min": int(accepted_poses.min())},
            "displacement": {"median_abs": float(np.median(np.abs(disp)) / self.diagonal),
                             "max_abs": float(np.max(np.abs(disp)) / self.diagonal), "unit": "bounding-box diagonal",
                             "bound": self.max_displacement / self.diagonal,
                             "median_abs_px": float(np.median(np.abs(disp)) / self.pixel),
                             "bound_px": self.max_displacement / self.pixel, "mesh_level": self.cfg.mesh_level,
                             "steps_kept": int(self.disp_accepted.numpy()[0])},
        }
        points = self.points.numpy().astype(np.float64)
        for name, v in (("points", points), ("rotations", rot), ("translations", trans)):
            if not np.all(np.isfinite(v)):
                raise RuntimeError(f"photometric refinement produced non-finite {name}")
        return RefineResult(rot, trans, points, disp, trace, summary)


def refined_capture(capture, result: RefineResult, out: Path):
    """The capture with refined poses (lights fixed to a camera moved with it), its files referenced from
    ``out``."""
    frames = []
    attached, offset = camera_attached_lights(capture.frames)
    for i, f in enumerate(capture.frames):
        r, t = result.rotations[i], result.translations[i]
        light = f.light
        if attached[i]:
            light = Light.point(r.T @ (offset[i].astype(np.float64) - t), f.light.intensity)
        rel = os.path.relpath(capture.root / f.file_path, out)
        mask = None if f.mask_path is None else os.path.relpath(capture.root / f.mask_path, out)
        frames.append(dataclasses.replace(f, R=r, t=t, light=light, file_path=rel, mask_path=mask))
    extra = dict(capture.extra)
    extra["refined"] = "photometric (texstream refine)"
    return Capture(root=out, frames=frames, extra=extra)


def refinement_kept(summary: dict, moves: bool = True) -> tuple[bool, str]:
    """(whether the refined cameras and mesh are handed on, why): only when they fit the fitted photos better than
    the registered ones did (the Huber-RMS residual at the finest level, unblurred, against the shared texture each
    makes: ``residual_before`` / ``residual_after``). Never the held-out photos' residual: they score the model.
    From its true cameras and mesh, a glossy flash capture's refinement moved them to follow highlights the shared
    texture cannot hold and its residual rose (0.00631 -> 0.00660, issue 39; from the same capture's photos alone
    it fell, 0.01129 -> 0.0108, and the rule keeps it); the temple's and the 6 MP sphere's fell (0.049 -> 0.046,
    0.024 -> 0.013).
    ``moves``: whether cameras or mesh were refined at all (shading normals alone are chosen by their own residual,
    ``choose_shading_normals``)."""
    if not moves:
        return True, "no camera or vertex was to move"
    before = (summary.get("residual_before") or {}).get("fit_rms")
    after = (summary.get("residual_after") or {}).get("fit_rms")
    if before is None or after is None:
        return True, "no residual to compare"
    if after < before:
        return True, f"the fitted photos' residual fell from {before:.4g} to {after:.4g}"
    return False, (f"the refined cameras and mesh fit the photos no better (residual {after:.4g} against {before:.4g} "
                   "before): the registered cameras and the mesh stage's mesh are kept")


def refine_stage(capture_dir: str | Path, geometry: str | Path, out: str | Path, cfg: RefineConfig | None = None,
                 device: str = "cpu", log=None):
    """Refine the capture's cameras and the atlas's mesh against the photos; write ``out``:

    ``capture.json`` (refined poses; photos and masks referenced where they are), ``mesh.obj`` (moved vertices,
    the same faces and UVs), ``bake.npz`` (texels re-baked on the moved surface at the same size), ``seams.npz``
    (copied: the atlas is unchanged), ``refine.json`` (summary and trace), ``refine_config.json``.

    Args:
        capture_dir: a posed capture folder.
        geometry: an atlas folder (``texstream atlas``: mesh.obj, bake.npz, seams.npz).
        out: output folder (written atomically).
        cfg: options (defaults when None).
        device: Warp device.
    """
    cfg = cfg or RefineConfig()
    cfg.levels()
    cfg.smoothing_rounds()
    capture_dir, geometry, out = Path(capture_dir), Path(geometry), Path(out)
    if not (geometry / "bake.npz").is_file() or not (geometry / "mesh.obj").is_file():
        raise InputError("not an atlas folder (needs mesh.obj and bake.npz)", geometry, "run texstream atlas first")
    capture = read_capture(capture_dir)
    mesh = load_mesh(geometry / "mesh.obj")
    bake = TexelBake.load(geometry / "bake.npz")
    checkpoint = refine_checkpoint.refine_checkpoint(capture, geometry, out, cfg, device, log)
    with phase("refine", f"cameras and mesh against {len(capture.frames)} photos"):
        job = PhotometricRefinement(capture, mesh, bake, cfg, device, log)
        try:
            result = job.run(checkpoint)
        finally:
            job.close()
    summary = dict(result.summary)
    summary["kept"], summary["kept_why"] = refinement_kept(summary, cfg.cameras or cfg.mesh)
    if not summary["kept"]:  # the stage hands on its input: the cameras and mesh as they came
        say("refine", summary["kept_why"])
        result = dataclasses.replace(result, points=np.asarray(mesh.vertices, np.float64), normals=None,
                                     rotations=[np.asarray(f.R, np.float64) for f in capture.frames],
                                     translations=[np.asarray(f.t, np.float64).reshape(3) for f in capture.frames])
    normals = None if result.normals is None else result.normals[job.weld_host]
    moved = dataclasses.replace(mesh, vertices=result.points, normals=normals)
    if summary["kept"]:
        with phase("refine", f"texel bake ({bake.width}x{bake.height})"):
            new_bake = bake_texels(moved, bake.width, bake.height, device=device, padding=bake.padding)
    else:
        new_bake = bake
    summary["trace"] = result.trace
    with atomic_output_dir(out) as tmp:
        write_capture(refined_capture(capture, result, out), tmp)
        save_mesh(tmp / "mesh.obj", moved)
        new_bake.save(tmp / "bake.npz")
        if (geometry / "seams.npz").is_file():
            shutil.copy2(geometry / "seams.npz", tmp / "seams.npz")
        save_config(cfg, tmp / "refine_config.json")
        write_json_atomic(tmp / "refine.json", summary)
    checkpoint.remove()
    return StageResult(output=out, summary={k: v for k, v in summary.items() if k != "trace"})
