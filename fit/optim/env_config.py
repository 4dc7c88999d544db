"""Options of the relightable diffuse model under one unknown environment light (``--model env_diffuse``,
fit/models/env_diffuse): a module without kernels, so that every fit's config (fit/optim/fitter.py
``FitConfig.env``) reads them; the CLI spells them ``--env.<name>``."""

from __future__ import annotations

import dataclasses

from texstream.core.config import option

SCALE_GAUGES = ("mean_albedo", "light_mean")
COLOUR_GAUGES = ("light", "albedo")


@dataclasses.dataclass
class EnvDiffuseConfig:
    """The env_diffuse model: per-texel albedo under an order-2 SH environment light (render/sh.py)."""

    light: str = option("", "fix the light instead of estimating it: a latitude-longitude environment map (EXR / HDR, "
                            "linear, render/sh.py's convention: row 0 the zenith +z) or a JSON file "
                            "{\"sh\": [[r, g, b] x 9]}; empty: the light is estimated with the albedo")
    materials: int = option(0, "shared materials through which the light is estimated (the albedo of a material's "
                               "texels is one colour while the light is fitted); 0: automatic, 1 to max_materials, "
                               "the fewest after which one more lowers the residual by less than material_gain",
                            min=0, max=16)
    max_materials: int = option(4, "materials = 0: the most tried", min=1, max=16)
    material_gain: float = option(0.1, "materials = 0: a further material must lower the shared-albedo residual by "
                                        "at least this fraction", min=0.0, max=1.0)
    merge_log_distance: float = option(0.15, "materials whose albedos differ by less than this in every channel's "
                                             "log (0.15: 16%) are merged when texels are relabelled", min=0.0)
    robust_log: float = option(0.1, "the light's fit down-weights texels whose own albedo (under the light of the "
                                     "round before) is off their material's: Cauchy weight 1 / (1 + (q / this)^2), q "
                                     "the largest log-ratio over the channels (0.1: a texel 10% off counts half); "
                                     "0: every texel by its sample count", min=0.0)
    material_weight_power: float = option(2.0, "the light's fit weights each material by (v_min / v_k)^this, v_k "
                                                "its texels' mean squared log-misfit to its albedo: materials whose "
                                                "albedo drifts over the object steer the light less (1: the "
                                                "maximum-likelihood weighting; 0: every material alike)", min=0.0)
    edge_neighbours: int = option(8, "a texel any of whose this many nearest texels (on the surface) is of another "
                                     "material is left out of the light's fit: the photos blend colours across "
                                     "material edges; 0: every texel", min=0, max=64)
    slope_consensus: bool = option(True, "after the fit, the light's dipole is moved so that most materials' albedos "
                                         "(3 or more materials, texels off their edges) hold no slope along x, y, z: "
                                         "one material's drift is not taken for the light (solve.py)")
    relabel_rounds: int = option(4, "rounds of (light and material albedos, then each texel moved to the material "
                                    "nearest its own albedo under that light)", min=1, max=50)
    light_passes: int = option(300, "alternation passes (material albedos given the light, the light given them) "
                                    "per round at most", min=1)
    rel_tol: float = option(1e-9, "a round stops when a pass lowers the objective by less than this, relative",
                            min=0.0)
    light_ridge: float = option(1e-6, "ridge on the light's bands 1 and 2, relative to the normal equations' mean "
                                      "diagonal: directions no texel faces stay near the mean light", min=0.0)
    albedo_prior: float = option(0.01, "each texel's albedo is pulled toward its material's by this weight, in "
                                       "units of an average texel's data (samples x squared shading): a texel in "
                                       "the dark (no light reaches it) takes its material's albedo", min=0.0)
    scale: str = option("mean_albedo", "the albedo-light scale the photos cannot tell (a x s, L / s fit alike): "
                                       "mean_albedo fixes the seen texels' mean albedo (over texels and channels) "
                                       "at scale_value; light_mean fixes the environment's mean radiance over the "
                                       "sphere (L[0] x 0.2821, the mean over channels) at scale_value",
                        choices=SCALE_GAUGES)
    scale_value: float = option(0.5, "the value the scale option fixes", min=1e-9)
    white: str = option("light", "the colour the photos cannot tell (per channel, a_c x g_c and L_c / g_c fit "
                                 "alike): light makes the environment's mean colour grey (L[0] equal over "
                                 "channels), albedo makes the seen texels' mean albedo grey", choices=COLOUR_GAUGES)
    directions: int = option(256, "ray directions per texel for the transfer vectors with visibility "
                                  "(geometry/sh_transfer.py; rounded up to a square)", min=1, max=65536)
    occlusion: bool = option(True, "the transfer vectors see the mesh's self-occlusion (concavities are not taken "
                                   "for dark albedo); off: the unoccluded closed form's sampling")
