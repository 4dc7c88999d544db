"""The model choice's stop for the LFM candidate's validation fit (fit/models/lfm/fit.py ``can_still_win``,
``CannotWin``): the bound on the score it can still reach, and the streaming fit ending at the check where the
bound falls below the score to beat (the scores scripted: rendering is the run's, tests/test_pipelines_run_lfm.py)."""

from __future__ import annotations

import pytest

from texstream.fit.models.lfm.fit import STOP_FIRST_CHECK, STOP_MARGIN_DB, CannotWin, can_still_win
from texstream.fit.models.lfm.problem import LFMConfig, fit_lfm

from test_fit_lfm import tiny_problem

TEMPLE = [(10, 19.587), (15, 19.692), (20, 19.821), (25, 19.814), (30, 19.834), (35, 19.862), (40, 19.901),
          (45, 19.897), (50, 19.907)]
"""the temple's LFM validation fit (K=1, the run's 50 iterations): validation pooled PSNR at every objective read
(benchmarks/lfm_choice_profile.py on the registered temple, 2-core CPU); view_radiance's 20.20 dB to beat"""
DINO = [(10, 22.958), (15, 23.005), (20, 22.792), (25, 22.905), (30, 22.916), (35, 22.910), (40, 22.861),
        (45, 22.905), (50, 22.907)]
"""the dino's, likewise; view_radiance's 23.25 dB to beat"""


def first_stop(points, target):
    """(iteration, bound) of the first check at which the fit cannot win, None if it never stops."""
    for k in range(3, len(points) + 1):
        hope, bound = can_still_win(points[:k], 50, target)
        if not hope:
            return points[k - 1][0], bound
    return None


def test_the_bound_is_the_last_score_rising_at_the_better_recent_rate():
    assert can_still_win(TEMPLE[:2], 50, 99.0) == (True, float("inf"))  # two points: no rate to trust yet
    hope, bound = can_still_win(TEMPLE[:3], 50, 20.20)  # 0.026 dB an iteration for 30 more
    assert hope and bound == pytest.approx(19.821 + 30 * (19.821 - 19.692) / 5)
    hope, bound = can_still_win(TEMPLE[:4], 50, 20.20)  # a dip, the better rate (the one before it) kept
    assert hope and bound == pytest.approx(19.814 + 25 * (19.821 - 19.692) / 5)
    hope, bound = can_still_win(TEMPLE[:5], 50, 20.20)  # two slow stretches: 19.91 at most, below view_radiance
    assert not hope and bound == pytest.approx(19.834 + 20 * (19.834 - 19.814) / 5)
    # within the margin of the target it goes on; falling scores give no gain (the bound is the last score)
    assert can_still_win(TEMPLE[:5], 50, bound + STOP_MARGIN_DB * 0.99)[0]
    assert can_still_win([(10, 20.0), (15, 19.9), (20, 19.8)], 50, 20.1) == (False, 19.8)


def test_on_the_measured_fits_the_stop_comes_early_and_the_bound_holds():
    """The temple stops at 30 of 50 iterations, the dino at 35 (its score falls 0.21 dB between two checks: the
    margin waits that out); each bound is at least where the fit to its cap ended, so the choice is unchanged."""
    for points, target, at in ((TEMPLE, 20.20, 30), (DINO, 23.25, 35)):
        iteration, bound = first_stop(points, target)
        assert iteration == at and bound >= points[-1][1]
    assert first_stop(TEMPLE, 19.95) is None  # a score to beat it gets within the margin of: fitted to its cap


class Scripted(CannotWin):
    """Scores from a table by iteration, no rendering."""

    def __init__(self, target_db, cap, scores):
        super().__init__(target_db, cap, None, [], [], None)
        self.scripted = scores

    def score(self, G, H) -> float:
        return self.scripted[len(self.points)]


def test_the_streaming_fit_ends_at_the_check_where_it_cannot_win(device):
    """Checks from STOP_FIRST_CHECK at every read (sync_every 5): flat scores far below the target end the fit at
    the third check; a target the rate can reach lets it run to its cap. rel_tol 0: only the stop ends it early."""
    cfg = LFMConfig(terms=1, view_res=4, iterations=40, rel_tol=0.0, sync_every=5, laplacian=0.1)
    stop = Scripted(30.0, cfg.iterations, [20.0, 20.1, 20.1, 20.1, 20.1, 20.1])
    res = fit_lfm(tiny_problem(device, cfg)[0], stop=stop)
    assert res.iterations == STOP_FIRST_CHECK + 10 and res.trace[-1]["iteration"] == res.iterations
    assert "stopped at iteration 20 of 40" in stop.stopped and len(stop.points) == 3
    reach = Scripted(20.5, cfg.iterations, [20.0, 20.1, 20.2, 20.3, 20.4, 20.5])  # 0.02 dB an iteration
    res = fit_lfm(tiny_problem(device, cfg)[0], stop=reach)
    assert res.iterations == cfg.iterations and reach.stopped is None
    assert [i for i, _ in reach.points] == [10, 15, 20, 25, 30, 35]  # none at the cap: the fit ends there anyway


def test_the_unseen_texels_show_their_nearest_seen_texel_s_diffuse_term():
    """``seen_sources``: every texel no photo sees takes the diffuse term of the seen texel nearest to it (a brute
    force nearest neighbour agrees), seen ones keep their own; computed once, it fills any parameters alike (the
    stop's renderer and the model folder), as filling from scratch does. Nothing to fill: None."""
    import types

    import numpy as np

    from texstream.fit.models.lfm.fit import filled_params, seen_sources
    from texstream.fit.models.lfm.problem import LFMParams

    rng = np.random.default_rng(3)
    geom = types.SimpleNamespace(texel_pos=rng.uniform(size=(200, 3)))
    seen = rng.uniform(size=200) > 0.4
    sources = seen_sources(geom, seen)
    d = np.linalg.norm(geom.texel_pos[:, None] - geom.texel_pos[None, seen], axis=2)
    expected = np.where(seen, np.arange(200), np.flatnonzero(seen)[d.argmin(axis=1)])
    assert np.array_equal(sources, expected)
    params = LFMParams(rng.uniform(size=(200, 3)), np.zeros((1, 1, 3)), np.zeros((1, 1, 1, 3)))
    filled = filled_params(params, geom, seen, sources)
    assert np.array_equal(filled.diffuse, filled_params(params, geom, seen).diffuse)
    assert np.array_equal(filled.diffuse, params.diffuse[expected])
    assert seen_sources(geom, np.ones(200, bool)) is None and seen_sources(geom, np.zeros(200, bool)) is None
