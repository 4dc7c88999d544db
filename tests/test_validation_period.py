"""The validation split of few fitted photos: two validation photos wherever two thirds stay fitted, so the choices
of materials, ambient term and model judge on photos they did not fit instead of falling back unjudged to their
most flexible model (per-texel lobes of 10 flash photos predicted an unseen view at 16 dB where diffuse gave 41)."""

import pytest

from texstream.fit.common.inputs import validation_period
from texstream.fit.models.per_texel.lobes import validation_split


@pytest.mark.parametrize("n, period", [(100, 8), (16, 8), (15, 7), (10, 5), (9, 4), (6, 3), (5, 8), (2, 8)])
def test_the_period_keeps_two_validation_photos_where_it_can(n, period):
    assert validation_period(n, 8) == period


@pytest.mark.parametrize("n", range(1, 40))
def test_the_split_has_two_validation_photos_and_two_thirds_fitted_from_six_photos(n):
    train, val = validation_split(n, 8)
    assert sorted(train + val) == list(range(n))
    if n >= 6:
        assert len(val) >= 2 and len(train) >= 2 * n / 3 - 1e-9  # the period is at least 3
    else:
        assert not val  # too few: the choices say so and keep their default
    if n >= 16:
        assert val == [i for i in range(n) if i % 8 == 7]  # the configured period, unchanged
