"""What the automatic model choice does when the capture calls for a reflectance model (a known light per
photo): Lafortune, diffuse and (with one lobe configured) two-lobe Lafortune, judged on a validation split of
the fitted photos, so a specular lobe is kept only where it generalises. The two-lobe candidate is fitted only
where the one-lobe fit says the photos can support a second lobe (:func:`second_lobe_supported`)."""

from __future__ import annotations

from texstream.fit.models.registry import Candidate

TWO_LOBES = "lafortune_2lobes"


def candidates(capture, cfg) -> list[Candidate]:
    out = [Candidate("lafortune", "lafortune"), Candidate("diffuse", "diffuse")]
    if cfg.choice.second_lobe and cfg.fit.lobes == 1:
        out.append(Candidate(TWO_LOBES, "lafortune", {"lobes": 2}, label="the two-lobe Lafortune",
                             supported=second_lobe_supported))
    return out


def second_lobe_supported(fitted: dict, cfg) -> str | None:
    """None when the one-lobe Lafortune fit (``fitted["lafortune"]``, a fit summary) lets a second lobe be
    fitted, else why not. A second lobe is a finer shape of the same highlight: only texels whose photos pin
    the first lobe down (the materials' constrained texels, materials.texel_uncertainty) can pin a second one,
    the rest borrow their material's lobes whatever their own. Below ``choice.second_lobe_min_constrained``
    (0.3) of the seen texels the second lobe is a guess on most texels. Measured: the README demo's ornament,
    971 of 9,580 (10%), its two-lobe model 31.7 dB on the validation photos against the one-lobe model's 46.7
    (left out, it saves a third of the run); a sphere of a broad sheen and a sharp highlight, 1,811 of 2,016
    (90%), its two-lobe model 42.5 dB against 24.4 (fitted and kept, 49.3 dB held out). Without the one-lobe
    fit's evidence (materials off, too few photos to split) it is fitted."""
    need = cfg.choice.second_lobe_min_constrained
    one = fitted.get("lafortune")
    unc = ((one or {}).get("materials") or {}).get("uncertainty") or {}
    if need <= 0 or not unc.get("seen_texels"):
        return None
    share = unc["constrained_texels"] / unc["seen_texels"]
    if share >= need:
        return None
    return (f"the one-lobe fit's photos constrain the lobe of {unc['constrained_texels']:,} of "
            f"{unc['seen_texels']:,} seen texels ({100 * share:.1f}% < second_lobe_min_constrained {100 * need:g}%), "
            "too few to pin a second lobe down")
