"""The model choice's options that `texstream run` declares at its top level are ModelChoiceConfig's: the same
names, defaults, choices and ranges, and they reach the fit stage's choice (the run used to copy them by hand)."""

import dataclasses

from texstream.fit.stages.choice import ModelChoiceConfig
from texstream.pipelines.run import RunConfig, run_choice_options


def _fields(cls) -> dict:
    return {f.name: f for f in dataclasses.fields(cls)}


def test_the_runs_choice_options_match_the_choices_own():
    run, choice = _fields(RunConfig), _fields(ModelChoiceConfig)
    shared = set(run) & set(choice)
    assert shared >= {"second_lobe", "second_lobe_min_constrained", "lfm", "lfm_min_gain_db", "relightable",
                      "relightable_margin_db"}
    for name in shared:
        a, b = run[name], choice[name]
        assert a.default == b.default, name
        for key in ("choices", "min", "max"):
            assert a.metadata.get(key) == b.metadata.get(key), (name, key)


def test_the_runs_values_reach_the_fit_stages_choice():
    cfg = RunConfig(second_lobe=False, lfm="never", relightable=True, relightable_margin_db=2.5)
    options = run_choice_options(cfg)
    choice = dataclasses.replace(cfg.fit.choice, **options)
    assert (choice.second_lobe, choice.lfm, choice.relightable, choice.relightable_margin_db) == (False, "never", True,
                                                                                                    2.5)
    assert set(options) <= set(_fields(ModelChoiceConfig))
