"""What the automatic model choice does when the capture calls for a radiance model (one fixed, unknown
lighting): radiance and view-dependent radiance fitted and judged on a validation split of the fitted photos
(fit/stages/choice.py), then light field mapping where view dependence matters."""

from __future__ import annotations

from texstream.fit.models.registry import Candidate


def candidates(capture, cfg) -> list[Candidate]:
    return [Candidate("radiance", "radiance"), Candidate("view_radiance", "view_radiance")]


def lfm_decision(score: dict, mode: str = "auto", min_gain_db: float = 0.5) -> tuple[tuple, str]:
    """Whether light field mapping joins the candidates, given the validation pooled PSNR (dB, or None)
    of the radiance and view_radiance fits: ((), reason) or (("lfm",), reason). ``mode`` "auto" fits
    it when view dependence matters (view_radiance at least ``min_gain_db`` above radiance), "always"
    and "never" override (ModelChoiceConfig.lfm)."""
    if mode == "never":
        return (), "light field mapping not fitted: run option lfm = never"
    if mode == "always":
        return ("lfm",), "light field mapping fitted too: run option lfm = always"
    r, v = score.get("radiance"), score.get("view_radiance")
    if r is None or v is None:
        return (), "light field mapping not fitted: no validation score to tell whether view dependence matters"
    gain = v - r
    if gain >= min_gain_db:
        return ("lfm",), (f"view dependence matters (view_radiance {gain:+.2f} dB over radiance on the validation photos, "
                          f">= lfm_min_gain_db {min_gain_db:g}): light field mapping fitted too")
    return (), (f"view dependence does not matter enough for light field mapping (view_radiance {gain:+.2f} dB over "
                f"radiance on the validation photos, < lfm_min_gain_db {min_gain_db:g})")


def escalate(score: dict | None, cfg) -> tuple[list[Candidate], str]:
    """Light field mapping as a further candidate (:func:`lfm_decision` under ``cfg.choice``); with ``score``
    None, the phrase for the plan's log line."""
    mode = cfg.choice.lfm
    if score is None:
        return [], {"auto": " (and light field mapping if view dependence matters)",
                    "always": " and light field mapping", "never": ""}[mode]
    kinds, why = lfm_decision(score, mode, cfg.choice.lfm_min_gain_db)
    return [Candidate(k, k) for k in kinds], why
