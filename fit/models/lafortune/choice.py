"""What the automatic model choice does when the capture calls for a reflectance model (a known light per
photo): Lafortune, diffuse and (with one lobe configured) two-lobe Lafortune fitted and judged on the held-out
photos, so a specular lobe is kept only where it generalises."""

from __future__ import annotations

from texstream.fit.models.registry import Candidate

TWO_LOBES = "lafortune_2lobes"


def candidates(capture, cfg) -> list[Candidate]:
    out = [Candidate("lafortune", "lafortune"), Candidate("diffuse", "diffuse")]
    if cfg.choice.second_lobe and cfg.fit.lobes == 1:
        out.append(Candidate(TWO_LOBES, "lafortune", {"lobes": 2}, label="the two-lobe Lafortune"))
    return out
