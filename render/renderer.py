"""The synthetic renderer: a textured mesh with per-texel Lafortune parameters, ray traced with Warp.

A radiance model (``ModelLayout`` kind "radiance") renders its per-texel radiance L, looked up
the same way, with no light (frames with or without one; the light is ignored).

:class:`Renderer` uploads the mesh (BVH), the parameter grid and the layout once per
(mesh, parameter grid, layout, device) and then renders any number of views with
:meth:`Renderer.render` / :meth:`Renderer.render_frame`. The per-pixel radiance is the shared
shading of :mod:`texstream.render.shading`, so renderer and fit cannot disagree (see
:mod:`texstream.render.kernels`).

Imports only numpy, warp and texstream.core. The parameter layout (the fit's
``texstream.render.layout.ModelLayout``) and capture.json's frames and lights are read by their
attributes, so the renderer sits below both.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import warp as wp

from texstream.core.errors import ConfigError, InputError
from texstream.render.camera import pinhole_camera
from texstream.render.kernels import render_kernel
from texstream.render.mesh import SurfaceMesh
from texstream.render.shading import LIGHT_DIRECTIONAL, LIGHT_NONE, LIGHT_POINT, SHADOW_EPS_REL


@dataclasses.dataclass
class RenderResult:
    """One rendered view.

    Attributes:
        radiance: (H, W, 3) float32 linear radiance (no exposure applied), 0 off the object
            (a radiance model: its L, in photo value / exposure units).
        mask: (H, W) bool, True where a primary ray hit the mesh.
        depth: (H, W) float32 camera-space Z (OpenCV axes, world units) of the hit, 0 off the object.
        face: (H, W) int32 index of the hit face, -1 off the object.
    """

    radiance: np.ndarray
    mask: np.ndarray
    depth: np.ndarray
    face: np.ndarray


class Renderer:
    """Ray-traced renderer of one textured mesh on one device.

    Args:
        mesh: a :class:`SurfaceMesh` with per-vertex ``uvs`` (and ``normals``; computed when absent).
        params: parameter grid (H, W, P) float (numpy, cast to float32) or a Warp array2d
            (H * W, P) float32 already on ``device``; row = y * W + x with row 0 at the top of the
            texture (capture/conventions.py). Padding texels must already hold copies of their
            chart neighbours (TexelBake.fill_padding) so bilinear lookups do not bleed.
        layout: the parameter column layout (a ``ModelLayout``; read: ``n_params`` (P must equal it),
            ``n_lobes``, ``anisotropic``, ``view_terms``, ``is_radiance``, ``kind`` and, where it has one, the
            ambient radiance's first column ``ambient_offset``).
        device: Warp device, "cpu" or "cuda:N".
        tex_size: (W, H) of the texel grid; required only when ``params`` is a Warp array.
        shadows: trace shadow rays (cast shadows); off gives local shading only.
    """

    def __init__(self, mesh: SurfaceMesh, params, layout, device: str = "cpu",
                 tex_size: tuple[int, int] | None = None, shadows: bool = True):
        if mesh.uvs is None:
            raise InputError("the mesh has no UVs", fix="build an atlas first (texstream atlas) or use a procedural mesh")
        if mesh.n_faces == 0:
            raise InputError("the mesh has no faces", fix="check the mesh file")
        self.device = wp.get_device(device)
        if getattr(layout, "room", False):  # the room light drawn as the ambient radiance it makes (layout.py)
            if isinstance(params, wp.array):
                raise ConfigError("a room-light model renders from a parameter grid", fix="pass the (H, W, P) grid")
            layout, params = layout.rendered(params)
        self.layout = layout
        self.shadows = bool(shadows)
        if isinstance(params, wp.array):
            if tex_size is None:
                raise ConfigError("tex_size=(W, H) is required when params is a Warp array")
            self.tex_w, self.tex_h = int(tex_size[0]), int(tex_size[1])
            if params.ndim != 2 or params.shape != (self.tex_w * self.tex_h, layout.n_params) or params.dtype != wp.float32:
                raise ConfigError(f"params array is {params.shape} {params.dtype}, expected "
                                  f"({self.tex_w * self.tex_h}, {layout.n_params}) float32")
            self.params = params
        else:
            p = np.asarray(params)
            if p.ndim != 3 or p.shape[2] != layout.n_params:
                raise ConfigError(f"params grid has shape {p.shape}, expected (H, W, {layout.n_params})")
            if not np.all(np.isfinite(p)):
                raise InputError("params grid holds NaN or Inf", fix="fill every texel (fill_padding)")
            self.tex_h, self.tex_w = int(p.shape[0]), int(p.shape[1])
            self.params = wp.array(np.ascontiguousarray(p.reshape(-1, layout.n_params), dtype=np.float32),
                                   dtype=wp.float32, device=self.device)
        if self.tex_w < 2 or self.tex_h < 2:
            raise ConfigError(f"texel grid {self.tex_w}x{self.tex_h} is too small for bilinear lookup",
                              fix="use at least 2x2 texels")

        v = np.asarray(mesh.vertices, dtype=np.float32)
        self.points = wp.array(v, dtype=wp.vec3, device=self.device)
        self.indices = wp.array(np.asarray(mesh.faces, dtype=np.int32).reshape(-1), dtype=wp.int32, device=self.device)
        self.normals = wp.array(np.asarray(mesh.vertex_normals(), dtype=np.float32), dtype=wp.vec3, device=self.device)
        self.uvs = wp.array(np.asarray(mesh.uvs, dtype=np.float32), dtype=wp.vec2, device=self.device)
        self.mesh = wp.Mesh(points=self.points, indices=self.indices)
        self.shadow_eps = float(SHADOW_EPS_REL * max(mesh.bbox_diagonal(), 1e-12))
        self._size: tuple[int, int] | None = None

    def _outputs(self, width: int, height: int) -> None:
        if self._size == (width, height):
            return
        shape = (height, width)
        self._radiance = wp.empty(shape, dtype=wp.vec3, device=self.device)
        self._mask = wp.empty(shape, dtype=wp.uint8, device=self.device)
        self._depth = wp.empty(shape, dtype=wp.float32, device=self.device)
        self._face = wp.empty(shape, dtype=wp.int32, device=self.device)
        self._size = (width, height)

    def render(self, R, t, fx: float, fy: float, cx: float, cy: float, width: int, height: int,
               light) -> RenderResult:
        """Render one view.

        Args:
            R: (3, 3) world-to-camera rotation, OpenCV axes.
            t: (3,) world-to-camera translation.
            fx, fy, cx, cy: pinhole intrinsics in pixels (capture convention, centres at +0.5).
            width, height: image size in pixels.
            light: a point or directional light (a capture.json ``Light``: ``type``, ``position`` or
                ``direction``, ``intensity``); ignored (may be None) for a radiance model.

        Returns:
            A :class:`RenderResult` of numpy arrays.
        """
        radiance, mask = self.render_on_device(R, t, fx, fy, cx, cy, width, height, light)
        height, width = radiance.shape
        return RenderResult(radiance=radiance.numpy().reshape(height, width, 3).astype(np.float32, copy=True),
                            mask=mask.numpy().astype(bool),
                            depth=self._depth.numpy().copy(),
                            face=self._face.numpy().copy())

    def render_on_device(self, R, t, fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                         light) -> tuple[wp.array, wp.array]:
        """:meth:`render`'s launch alone: the (height, width) radiance and coverage mask left on the device, in
        buffers the next render overwrites (a scorer that compares them there copies nothing back)."""
        if light is None and not self.layout.is_radiance:
            raise InputError(f"the frame has no light, which a {self.layout.kind} model needs to render",
                             fix="give every frame a point or directional light, or render a radiance model")
        width, height = int(width), int(height)
        self._outputs(width, height)
        cam = pinhole_camera(R, t, fx, fy, cx, cy, width, height)
        if self.layout.is_radiance:
            cam.light_kind = int(LIGHT_NONE)  # L itself: no light, cosine or shadow ray
        elif light.type == "point":
            cam.light_kind = int(LIGHT_POINT)
            cam.light_vec = wp.vec3(*np.asarray(light.position, dtype=np.float32))
        elif light.type == "directional":
            cam.light_kind = int(LIGHT_DIRECTIONAL)
            cam.light_vec = wp.vec3(*np.asarray(light.direction, dtype=np.float32))
        else:
            raise InputError(f"light type {light.type!r} is not 'point' or 'directional'")
        if not self.layout.is_radiance:
            cam.light_intensity = wp.vec3(*np.asarray(light.intensity, dtype=np.float32))
        wp.launch(render_kernel, dim=(height, width), device=self.device,
                  inputs=[self.mesh.id, self.points, self.indices, self.normals, self.uvs,
                          self.params, self.tex_w, self.tex_h, self.layout.n_lobes, int(self.layout.anisotropic),
                          int(self.layout.view_terms), int(getattr(self.layout, "ambient_offset", -1)),
                          cam, self.shadow_eps, int(self.shadows)],
                  outputs=[self._radiance, self._mask, self._depth, self._face])
        return self._radiance, self._mask

    def frame_on_device(self, frame) -> tuple[wp.array, wp.array]:
        """:meth:`render_on_device` of a capture.json ``Frame`` (as :meth:`render_frame`)."""
        k = frame.intrinsics
        if not k.is_pinhole:
            raise InputError(f"frame {frame.file_path} has lens distortion", fix="render pinhole frames only")
        return self.render_on_device(frame.R, frame.t, k.fx, k.fy, k.cx, k.cy, k.width, k.height, frame.light)

    def render_frame(self, frame) -> RenderResult:
        """Render the view of a capture.json ``Frame`` (``R``, ``t``, ``intrinsics``, ``light``; a
        radiance model needs no light).

        Lens distortion is not rendered: the frame must be a pinhole camera.
        """
        k = frame.intrinsics
        if not k.is_pinhole:
            raise InputError(f"frame {frame.file_path} has lens distortion", fix="render pinhole frames only")
        return self.render(frame.R, frame.t, k.fx, k.fy, k.cx, k.cy, k.width, k.height, frame.light)
