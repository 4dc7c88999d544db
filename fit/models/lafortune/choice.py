"""What the automatic model choice does when the capture calls for a reflectance model (a known light per
photo): diffuse, Lafortune and (with one lobe configured) two-lobe Lafortune, judged on a validation split of
the fitted photos, so a specular lobe is kept only where it generalises. Lafortune is fitted only where the
diffuse fit's photos show highlights (:func:`lobes_supported`), the two-lobe candidate only where the one-lobe
fit says the photos can support a second lobe (:func:`second_lobe_supported`)."""

from __future__ import annotations

from texstream.fit.models.registry import Candidate

TWO_LOBES = "lafortune_2lobes"


def candidates(capture, cfg) -> list[Candidate]:
    """Diffuse first (a validation fit, the cheapest), whose photos say whether any lobe has a highlight to explain
    (:func:`lobes_supported`), then Lafortune and the two-lobe Lafortune where the photos support them."""
    out = [Candidate("diffuse", "diffuse"), Candidate("lafortune", "lafortune", supported=lobes_supported)]
    if cfg.choice.second_lobe and cfg.fit.lobes == 1:
        out.append(Candidate(TWO_LOBES, "lafortune", {"lobes": 2}, label="the two-lobe Lafortune",
                             supported=second_lobe_supported))
    return out


def lobes_supported(fitted: dict, cfg) -> str | None:
    """None when the diffuse candidate's fit (``fitted["diffuse"]``) saw highlights on at least
    ``choice.lobe_min_highlight_share`` of its seen texels (model.json ``highlights``: a sample near the mirror
    configuration above the diffuse prediction by 4 of its off-mirror deviations and 10%), else why a lobe has
    nothing to explain. Measured: the README demo's ornament, 3,051 of 9,580 texels (fitted, kept); a 6 MP facade
    of 481,945 seen texels, 0 (its Lafortune fit and materials choice took 140 of the fit stage's 209 s, and
    diffuse was kept, 1.1 dB ahead). Without the diffuse fit's count (no validation split) it is fitted."""
    need = cfg.choice.lobe_min_highlight_share
    report = (fitted.get("diffuse") or {}).get("highlights") or {}
    if need <= 0 or not report.get("seen_texels"):
        return None
    share = report["highlight_texels"] / report["seen_texels"]
    if share >= need:
        return None
    return (f"the diffuse fit's photos show a highlight on {report['highlight_texels']:,} of "
            f"{report['seen_texels']:,} seen texels ({100 * share:.2f}% < lobe_min_highlight_share {100 * need:g}%): "
            "no highlight for a lobe to explain")


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
    no_highlight = lobes_supported(fitted, cfg)
    if no_highlight:  # no lobe at all
        return no_highlight
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
