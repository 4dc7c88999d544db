"""An env_diffuse model folder read back (eval, export, report, viewer, ``texstream relight``).

It renders under its estimated light (eval, the report's held-out views) or any other SH light
(:meth:`EnvDiffuseModel.relit_renderer`); exports a lit glTF (base colour = albedo, metallic 0, roughness 1,
no specular layer) with the estimated environment as a latitude-longitude EXR beside it.
"""

from __future__ import annotations

import base64
from pathlib import Path

import numpy as np

from texstream.capture.imageio import read_image
from texstream.core.errors import InputError
from texstream.fit.models.env_diffuse.light_file import read_light
from texstream.fit.models.env_diffuse.model import ENV_MAP_SIZE, EnvDiffuseRenderer, lit_radiance
from texstream.fit.models.previews import read_shader, rgb_scaled
from texstream.fit.models.registry import ExportMaterial, FittedModel, ViewerModel
from texstream.geometry.bake import TexelBake
from texstream.geometry.mesh_io import load_mesh
from texstream.render import sh

FIX = "re-run `texstream fit --model env_diffuse` to rewrite the model folder"


class EnvDiffuseModel(FittedModel):
    """Albedo (H, W, 3) and transfer vectors (H, W, 9) per atlas texel, and the SH light (9, 3) of the photos."""

    relightable = True

    def __init__(self, folder: Path, mesh, manifest: dict, covered, albedo, transfer, light):
        super().__init__("env_diffuse", folder, mesh, manifest, covered)
        self.albedo, self.transfer, self.light = albedo, transfer, light

    def renderer(self, device: str = "cpu"):
        return self.relit_renderer(self.light, device)

    def relit_renderer(self, light: np.ndarray, device: str = "cpu"):
        """Frame -> (image x exposure, coverage) under the SH light ``light`` (9, 3)."""
        return EnvDiffuseRenderer(self.mesh, self.albedo, self.transfer, light, device).render

    def export_material(self, cfg) -> ExportMaterial:
        clipped = int((self.albedo.max(axis=-1)[self.covered] > 1.0).sum())
        env = np.maximum(sh.latlong_from_sh(self.light, *ENV_MAP_SIZE), 0.0).astype(np.float32)
        return ExportMaterial(np.clip(self.albedo, 0.0, 1.0), clipped=clipped, label="basecolor", name="env_diffuse",
                              extras={"light_sh": [[float(v) for v in r] for r in self.light],
                                      "light_gauge": (self.manifest.get("light") or {}).get("gauge")},
                              environment=env)

    def report_maps(self, save, seen) -> None:
        img, s = rgb_scaled(self.albedo)
        save("albedo", img, f"albedo (RGB, divided by {s:.4g}, the 99th percentile; sRGB)")
        img, s = rgb_scaled(lit_radiance(self.albedo, self.transfer, self.light))
        save("radiance", img, f"the albedo lit by the estimated light (divided by {s:.4g}; sRGB)")
        img, s = rgb_scaled(np.repeat(np.clip(self.transfer[..., :1] / sh.sh9_basis(np.zeros(3))[0], 0, None), 3, 2))
        save("ambient_visibility", img, "ambient visibility: the transfer's constant term over the unoccluded one "
             f"(1: the texel sees the whole hemisphere; divided by {s:.4g}; sRGB)")
        img, s = rgb_scaled(np.maximum(sh.latlong_from_sh(self.light, *ENV_MAP_SIZE), 0.0))
        save("environment", img, f"the estimated environment, latitude-longitude, +z up (divided by {s:.4g}; sRGB)")

    def report_relit_lights(self) -> list[tuple[str, np.ndarray]]:
        return [(f"the estimated light turned {deg} deg about +z", rotated_about_z(self.light, deg))
                for deg in (90, 180)]

    def report_facts(self) -> list[tuple[str, str]]:
        lt = self.manifest.get("light") or {}
        gauge = lt.get("gauge") or {}
        return [("model", "env_diffuse: albedo under an order-2 SH environment light"),
                ("light", f"{lt.get('source')}" + (f", {gauge.get('materials')} shared materials" if
                                                   gauge.get("materials") else "")),
                ("ambiguities", gauge.get("why", gauge.get("fixed", "")))]

    def viewer(self) -> ViewerModel:
        grid = np.concatenate([self.albedo, self.transfer], axis=-1).astype(np.float32)
        return ViewerModel(grid, read_shader(Path(__file__).parent), lit=True, data=viewer_light(self.light, self.mesh),
                           note="Relightable diffuse model under its estimated environment light (the albedo lit "
                                "through each texel's transfer with self-occlusion); moving the light turns the "
                                "environment about +z by the light's azimuth around the object, its intensity "
                                "scales it; `texstream relight` renders it under any light.")


def turned_about_z(light: np.ndarray, radians: float) -> np.ndarray:
    """(9, 3) the SH light turned by ``radians`` about +z, exactly (the viewer's GLSL does the same): the band-1
    and band-2 m = +-1 pairs turn by the angle, the m = +-2 pair by twice it."""
    out = np.array(light, np.float64, copy=True)
    c, s, c2, s2 = np.cos(radians), np.sin(radians), np.cos(2 * radians), np.sin(2 * radians)
    for (ky, kx), (cc, ss) in (((1, 3), (c, s)), ((5, 7), (c, s)), ((4, 8), (c2, s2))):
        out[kx], out[ky] = cc * light[kx] - ss * light[ky], ss * light[kx] + cc * light[ky]
    return out


def viewer_light(light: np.ndarray, mesh) -> dict:
    """The viewer's ``u_shlight`` texture: the 9 SH coefficients (RGB) then the object's centre (the bounding
    box's, where the viewer puts its default light above)."""
    texels = np.zeros((1, 10, 4), np.float32)
    texels[0, :9, :3] = light
    v = np.asarray(mesh.vertices, np.float64)
    texels[0, 9, :3] = 0.5 * (v.min(axis=0) + v.max(axis=0))
    data = base64.b64encode(np.ascontiguousarray(texels, dtype="<f4").tobytes()).decode("ascii")
    return {"textures": [{"name": "u_shlight", "width": 10, "height": 1, "data": data}]}


def load(model_dir: Path, manifest: dict) -> FittedModel:
    d = Path(model_dir)
    for name in ("mesh.obj", "bake.npz", "albedo.exr", "transfer.npz", "light.json"):
        if not (d / name).is_file():
            raise InputError(f"env_diffuse model folder has no {name}", d / name, FIX)
    mesh = load_mesh(d / "mesh.obj").with_normals()
    if mesh.uvs is None:
        raise InputError("mesh has no texture coordinates", d / "mesh.obj", FIX)
    albedo = read_image(d / "albedo.exr", channels=3).astype(np.float64)
    try:
        with np.load(d / "transfer.npz") as z:
            transfer = np.asarray(z["transfer"], np.float64)
    except (OSError, KeyError, ValueError) as e:
        raise InputError(f"transfer.npz is unreadable ({type(e).__name__})", d / "transfer.npz", FIX) from None
    if transfer.shape != (*albedo.shape[:2], sh.SH_COUNT):
        raise InputError(f"transfer.npz holds {transfer.shape}, the albedo map is {albedo.shape[:2]}",
                         d / "transfer.npz", FIX)
    light = read_light(d / "light.json")
    covered = np.asarray(TexelBake.load(d / "bake.npz").covered, bool)
    if covered.shape != albedo.shape[:2] or not covered.any():
        covered = np.ones(albedo.shape[:2], bool)
    return EnvDiffuseModel(d, mesh, manifest, covered, albedo, transfer, light)


def rotated_about_z(light: np.ndarray, degrees: float) -> np.ndarray:
    """(9, 3) the SH light ``light`` turned by ``degrees`` about +z (east): :func:`turned_about_z`."""
    return turned_about_z(light, np.radians(degrees))
