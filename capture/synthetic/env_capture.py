"""A synthetic scene photographed under one environment light (``texstream synth SCENE --env NAME|FILE``).

The object is Lambertian: each texel keeps its scene material's diffuse ``rho_d`` (the lobes are dropped), and
its outgoing radiance is

    L_o = rho_d * sum over the environment's lat-long pixels w of V(w) L(w) max(0, n.w) d_omega(w)

(= albedo / pi * integral V L max(0, n.w) dw with albedo = pi rho_d: render/sh.py's diffuse radiance), with V
the visibility of the environment from the texel: a ray from the texel along w that hits the mesh is blocked
(self-occlusion; no interreflection: blocked light is lost, as an ambient-occlusion-aware model assumes). The
environment is integrated on an ``env_grid`` x 2 ``env_grid`` block average of the map (32 x 64: 2,048
directions, half of them above a texel's horizon), by a Warp kernel, one thread per texel. The photos are the
renderer's radiance model (render/renderer.py) looking up these per-texel radiances, so they are
view-independent and the frames carry no light (the lighting is unknown to the fit).

Ground truth (``ground_truth/`` beside the scene's usual files; the parameter maps are the diffuse layout's
``rho_d.exr``): ``albedo.exr`` (pi rho_d), ``radiance.exr`` (L_o per texel), ``environment.exr`` (the map at
its full resolution), ``environment_sh.json`` (its order-2 SH projection, render/sh.py's convention, and its
SH-9 irradiance truncation error) and ``sh_transfer.npz`` (the texels' occluded transfer vectors T_k =
(1/pi) sum V max(0, n.w) Y_k(w) d_omega over the same grid: albedo * T . L_sh is the SH-9 relit radiance
under any light, the ceiling of an order-2 relightable model).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import warp as wp
from texstream.capture.imageio import read_image, write_image
from texstream.capture.synthetic import environments
from texstream.core.errors import ConfigError
from texstream.core.outputs import read_json, write_json_atomic
from texstream.geometry.mesh_io import write_npz_atomic
from texstream.render import sh
from texstream.render.layout import ModelLayout
from texstream.render.shading import SHADOW_EPS_REL

ENV_FILES = {"albedo": "albedo.exr", "radiance": "radiance.exr", "environment": "environment.exr",
             "environment_sh": "environment_sh.json", "sh_transfer": "sh_transfer.npz"}


@wp.kernel(enable_backward=False)
def _texel_environment_kernel(mesh: wp.uint64, positions: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3),
                              face_normals: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3),
                              radiance_omega: wp.array(dtype=wp.vec3), omega: wp.array(dtype=wp.float32),
                              eps: float, irradiance: wp.array(dtype=wp.vec3), transfer: wp.array2d(dtype=wp.float32)):
    """Per texel: irradiance sum V L max(0, n.w) d_omega and the SH transfer (1/pi) sum V max(0, n.w) Y_k d_omega.

    Rays start ``eps`` off the texel's face, on the side the direction leaves by (as the renderer's shadow
    rays), so a ray cannot re-hit its own triangle; a direction above the shading normal's horizon but below
    the face's enters the surface and is blocked, as it would be on the real (smooth) object."""
    t = wp.tid()
    p = positions[t]
    n = normals[t]
    ng = face_normals[t]
    e = wp.vec3(0.0)
    for k in range(dirs.shape[0]):
        w = dirs[k]
        c = wp.dot(n, w)
        if c <= 0.0:
            continue
        side = 1.0
        if wp.dot(ng, w) < 0.0:
            side = -1.0
        hit = wp.mesh_query_ray(mesh, p + ng * (eps * side), w, 1.0e30)
        if hit.result:
            continue
        e = e + radiance_omega[k] * c
        for j in range(9):
            transfer[t, j] = transfer[t, j] + c * omega[k] * sh.sh9_basis_component(w, j, wp.float32(1.0)) / wp.pi
    irradiance[t] = e


def texel_environment(mesh, bake, env_grid: np.ndarray, device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """((H, W, 3) occluded irradiance, (H, W, 9) occluded SH transfer) of every covered texel of ``bake`` under a
    lat-long map ``env_grid`` (its pixels are the integration directions); 0 on texels off the surface."""
    sel = bake.covered.reshape(-1)
    if not sel.any():
        raise ConfigError("the texture has no covered texel to light", fix="check the mesh's UVs")
    face_n = mesh.face_normals()[bake.face.reshape(-1)[sel]]
    shade_n = bake.normal.reshape(-1, 3)[sel].astype(np.float64)
    face_n = np.where((np.sum(face_n * shade_n, axis=1) < 0)[:, None], -face_n, face_n)  # winding-proof
    dirs, omega = sh.latlong_directions(env_grid.shape[0], env_grid.shape[1])
    dirs, omega = dirs.reshape(-1, 3), omega.reshape(-1)
    lo = np.asarray(env_grid, np.float64).reshape(-1, 3) * omega[:, None]
    dev = wp.get_device(device)
    wmesh = wp.Mesh(points=wp.array(np.asarray(mesh.vertices, np.float32), dtype=wp.vec3, device=dev),
                    indices=wp.array(np.asarray(mesh.faces, np.int32).reshape(-1), dtype=wp.int32, device=dev))
    n_sel = int(sel.sum())
    irr = wp.zeros(n_sel, dtype=wp.vec3, device=dev)
    tr = wp.zeros((n_sel, 9), dtype=wp.float32, device=dev)

    def arr(a, dtype):
        return wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=dtype, device=dev)

    wp.launch(_texel_environment_kernel, dim=n_sel, device=dev,
              inputs=[wmesh.id, arr(bake.position.reshape(-1, 3)[sel], wp.vec3), arr(shade_n, wp.vec3),
                      arr(face_n, wp.vec3), arr(dirs, wp.vec3), arr(lo, wp.vec3), arr(omega, wp.float32),
                      float(SHADOW_EPS_REL * max(mesh.bbox_diagonal(), 1e-12))],
              outputs=[irr, tr])
    h, w = bake.height, bake.width
    irradiance, transfer = np.zeros((h * w, 3)), np.zeros((h * w, 9))
    irradiance[sel], transfer[sel] = irr.numpy(), tr.numpy()
    return irradiance.reshape(h, w, 3), transfer.reshape(h, w, 9)


@dataclasses.dataclass
class EnvLighting:
    """A scene lit by an environment: what the photos render and what the ground truth keeps.

    Attributes:
        name: the environment's name (built-in) or file stem.
        env: (h, w, 3) the map at full resolution (as written to environment.exr).
        grid: (g, 2g, 3) its block average the texels were lit by.
        coeffs: (9, 3) SH-9 projection of ``env`` (render/sh.py).
        sh_error: :func:`environments.irradiance_sh_error` of ``env``.
        layout: the ground truth's layout (diffuse: rho_d only).
        params: (H, W, 3) rho_d, padding filled.
        radiance: (H, W, 3) float32 outgoing radiance per texel, padding filled (the photos' texture).
        transfer: (H, W, 9) occluded SH transfer, padding filled.
        frames: the scene's frames without lights.
    """

    name: str
    env: np.ndarray
    grid: np.ndarray
    coeffs: np.ndarray
    sh_error: dict
    layout: ModelLayout
    params: np.ndarray
    radiance: np.ndarray
    transfer: np.ndarray
    frames: list

    @property
    def render_layout(self) -> ModelLayout:
        """The photos are a view-independent radiance texture."""
        return ModelLayout(kind="radiance")

    def manifest(self) -> dict:
        return {"name": self.name, "files": dict(ENV_FILES), "map_size": list(self.env.shape[:2]),
                "integration_grid": list(self.grid.shape[:2]), "sh_irradiance_error": self.sh_error,
                "albedo": "albedo.exr = pi * rho_d (the scene materials' diffuse part; lobes dropped)",
                "shading": "radiance = rho_d * sum V L max(0, n.w) d_omega over the grid; no interreflection"}

    def write(self, gt: Path) -> None:
        """The environment's ground-truth files into ``gt`` (ENV_FILES)."""
        write_image(gt / ENV_FILES["albedo"], (math.pi * self.params[..., 0:3]).astype(np.float32), bits=32)
        write_image(gt / ENV_FILES["radiance"], self.radiance, bits=32)
        environments.write_environment(gt / ENV_FILES["environment"], self.env)
        write_json_atomic(gt / ENV_FILES["environment_sh"], sh_json(self.name, self.coeffs, self.sh_error))
        write_npz_atomic(gt / ENV_FILES["sh_transfer"], transfer=self.transfer.astype(np.float32))


def sh_json(name: str, coeffs: np.ndarray, sh_error: dict | None = None) -> dict:
    """An SH-9 light as JSON: coefficients (9 rows of RGB) with its convention named."""
    out = {"convention": "texstream.render.sh (order 2, 9 x RGB, world +z up)", "name": name,
           "coefficients": np.asarray(coeffs, np.float64).tolist()}
    if sh_error is not None:
        out["sh_irradiance_error"] = sh_error
    return out


def light_scene(sc: dict, mesh, bake, params: np.ndarray, frames: list, env: str, env_grid: int = 32,
                device: str = "cpu") -> EnvLighting:
    """Light a prepared scene by the environment ``env`` (a built-in name or a lat-long map file).

    Args:
        sc: the resolved scene (its ``light`` is replaced by ``environment`` in place, for the manifest).
        mesh, bake: the scene's mesh and texel bake.
        params: the scene's per-texel parameters (only rho_d, the first three columns, is used).
        frames: the scene's frames (their lights are dropped).
        env_grid: rows of the integration grid (columns twice that); the map's sides must be multiples.
    """
    if "room_light" in sc:
        raise ConfigError("a scene with a room light cannot also be lit by an environment",
                          fix="pass --room-light 0 (the environment is all the light there is)")
    full, name = environments.load_environment(env)
    grid = environments.downsample_latlong(full, env_grid, 2 * env_grid)
    rho_d = np.asarray(params[..., 0:3], np.float64)
    irr, transfer = texel_environment(mesh, bake, grid, device)
    radiance = bake.fill_padding(rho_d * irr).astype(np.float32)
    sc.pop("light", None)
    sc["environment"] = {"name": name, "source": str(env), "integration_grid": [env_grid, 2 * env_grid]}
    return EnvLighting(name=name, env=full, grid=grid, coeffs=sh.project_latlong(full),
                       sh_error=environments.irradiance_sh_error(full), layout=ModelLayout(kind="diffuse", n_lobes=0),
                       params=np.ascontiguousarray(params[..., 0:3], dtype=np.float32), radiance=radiance,
                       transfer=bake.fill_padding(transfer).astype(np.float32),
                       frames=[dataclasses.replace(f, light=None) for f in frames])


def load_env_ground_truth(folder) -> dict:
    """The environment ground truth of a capture written with ``--env``: albedo (H, W, 3), radiance (H, W, 3),
    transfer (H, W, 9), coeffs (9, 3), env (h, w, 3) and the manifest's ``environment`` entry."""
    g = Path(folder)
    if (g / "ground_truth").is_dir():
        g = g / "ground_truth"
    man = read_json(g / "manifest.json", what="ground-truth manifest")
    if "environment" not in man:
        raise ConfigError("this synthetic capture was not lit by an environment", g / "manifest.json",
                          "synthesize it with `texstream synth SCENE --env NAME`")
    with np.load(g / ENV_FILES["sh_transfer"]) as z:
        transfer = z["transfer"]
    return {"albedo": read_image(g / ENV_FILES["albedo"], channels=3),
            "radiance": read_image(g / ENV_FILES["radiance"], channels=3), "transfer": transfer,
            "coeffs": np.asarray(read_json(g / ENV_FILES["environment_sh"])["coefficients"], np.float64),
            "env": environments.read_environment(g / ENV_FILES["environment"]), "manifest": man["environment"]}
