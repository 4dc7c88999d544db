"""A Lafortune SBRDF model folder read back (eval, export, report, viewer)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from texstream.capture.imageio import linear_to_srgb, read_image
from texstream.core.devices import resolve_device
from texstream.fit.common.highlights import CLASS_NAMES
from texstream.fit.models.lafortune.export import bake_fill_source, lafortune_material
from texstream.fit.models.per_texel.folder import PerTexelModel, load_per_texel
from texstream.fit.models.previews import read_shader, rgb_scaled
from texstream.fit.models.registry import ExportMaterial, FittedModel, ViewerModel


class LafortuneModel(PerTexelModel):
    """Diffuse rho_d plus Lafortune lobes per texel (a diffuse model: no lobes)."""

    def export_material(self, cfg) -> ExportMaterial:
        mat = lafortune_material(self.grid, self.layout, self.covered, cfg.roughness,
                                 fill_source=bake_fill_source(self.folder), device=resolve_device(cfg.device))
        lay, grid = self.layout.rendered(self.grid)  # the room light: its radiance pi rho_d T.L, baked per texel
        if lay.ambient:  # the room's light, the same from every view: an emissive term for viewers
            o = lay.ambient_offset
            mat.emissive = np.maximum(grid[..., o:o + 3], 0.0).astype(np.float32)
        return mat

    def report_maps(self, save, seen) -> None:
        grid, lay = self.grid, self.layout
        save("rho_d", linear_to_srgb(np.clip(np.pi * grid[..., 0:3], 0, 1)),
             "diffuse albedo pi * rho_d (RGB, clipped to 1; sRGB)")
        for j in range(lay.n_lobes):
            o = lay.lobe_offset(j)
            img, s = rgb_scaled(grid[..., o:o + 3])
            save(f"lobe{j}_rho_s", img, f"lobe {j} specular albedo rho_s (RGB, 1/sr, divided by {s:.4g}; sRGB)")
            names = ["c_x", "c_y", "c_z"] if lay.anisotropic else ["c_xy", "c_z"]
            for k, cname in enumerate(names):
                col = grid[..., o + 3 + k]
                if np.ptp(col) == 0:
                    continue  # held constant (the scale gauge, or c_z of a Phong lobe): said in the layout table
                save(f"lobe{j}_{cname}", col, f"lobe {j} coefficient {cname}", cmap="viridis")
            n = grid[..., o + lay.lobe_stride - 1]
            save(f"lobe{j}_n", np.log10(np.maximum(n, 1e-6)), f"lobe {j} exponent n (log10)", cmap="viridis",
                 colorbar_label="log10 n")
        if lay.ambient or lay.room:
            drawn_lay, drawn = lay.rendered(grid)
            o = drawn_lay.ambient_offset
            img, s = rgb_scaled(drawn[..., o:o + 3])
            what = "the global SH room light's radiance pi rho_d T.L" if lay.room else "ambient radiance A"
            save("ambient", img, f"{what}, the room's light (RGB, photo value / exposure, divided by {s:.4g}; sRGB)")
        if (self.folder / "highlights.png").is_file():  # the fit's highlight diagnostic (fit/common/highlights.py)
            save("highlights", read_image(self.folder / "highlights.png", channels=3, linear=False),
                 "highlights the photos show against lobes the model has: " + ", ".join(CLASS_NAMES))

    def report_facts(self) -> list[tuple[str, str]]:
        rows = super().report_facts()
        amb = self.manifest.get("ambient")
        if isinstance(amb, dict):
            rows.append(("ambient term", f"{amb.get('chosen')} ({amb.get('mode')}): {amb.get('reason')}"))
            if isinstance(amb.get("room"), dict):
                rows.append(("room light", "order-2 SH, mean radiance (RGB) "
                             + ", ".join(f"{v:.4g}" for v in amb["room"]["mean_radiance"])
                             + f"; {len(amb['room']['trace'])} alternation rounds"))
        if isinstance(self.manifest.get("highlights"), dict):
            rows.append(("highlights", self.manifest["highlights"].get("line", "")))
        return rows

    def viewer(self) -> ViewerModel:
        lay, grid = self.layout.rendered(self.grid)  # the room light drawn as the ambient radiance it makes
        return ViewerModel(grid, read_shader(Path(__file__).parent), lit=True,
                           data={"uniforms": {"u_nlobes": int(lay.n_lobes), "u_aniso": int(bool(lay.anisotropic)),
                                              "u_ambient": int(lay.ambient_offset)}})


def load(model_dir: Path, manifest: dict) -> FittedModel:
    return load_per_texel(LafortuneModel, "lafortune", model_dir, manifest)
