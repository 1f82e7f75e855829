"""estimate.phase_degree: the rule that picks the exponential function's degree.

The fits and the renders are replaced by stand-ins with given chi^2 per seed pair, so the
tests see the rule alone: nested warm starts, the BIC margin and its standard error, and
the stop after `PATIENCE` degrees that do not gain, and the close calls decided again over
more seed pairs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import pytest

from estimate import phase_degree
from estimate.errors import ModelParameterError
from estimate.phase_degree import (
    BIC_MARGIN,
    CLOSE_SEEDS,
    EVAL_RENDER_RATIO,
    EVAL_SEEDS,
    EVAL_SPP_MAX_FACTOR,
    MAX_DEGREE,
    PATIENCE,
    Metric,
    choose_degree,
    comparison_spp,
)

PIXELS = 400


@dataclass
class FakeFit:
    model: str
    parameters: dict[str, float]
    scale_mode: str = "calibrated"
    fixed: dict[str, float] = field(default_factory=dict)
    reduced_chi2: float = 1.0
    loss_unbiased: float = 1.0
    time_s: float = 0.0

    @property
    def free(self) -> list[str]:
        return [k for k in self.parameters if k not in self.fixed]


FINAL_SPP = 1024


def _run(chi2_by_degree: dict[int, list[float]], monkeypatch, renders: list | None = None,
         ratio: float = float("nan"), spps: list | None = None, **kw):
    """choose_degree with fits that take their start and chi^2 that come from the table (per
    seed pair, repeated when the table is shorter than the pairs asked for); `renders` gets
    (degree, first pair, pairs) of every comparison render, `spps` (degree, spp). The render
    variance over the HDR variance is `ratio` at 2 x `FINAL_SPP` and falls as 1 / spp."""
    starts: list[tuple[str, dict | None]] = []

    def fit(phase: str, start):
        starts.append((phase, None if start is None else dict(start)))
        m = int(phase[3:])
        p = {"sigma_t": 2.0, "albedo": 0.9, **{f"phase.b{i}": 0.1 * i for i in range(1, m + 1)}}
        return FakeFit(phase, p)

    def chi2(problem, res, settings, *, seeds, extensions, metric=None, first=0, spp=None):
        row = chi2_by_degree[int(res.model[3:])]
        if renders is not None:
            renders.append((int(res.model[3:]), first, seeds))
        at = metric.spp if metric is not None else (spp or 2 * settings.final_spp)
        if spps is not None:
            spps.append((int(res.model[3:]), at))
        return ([row[k % len(row)] for k in range(first, first + seeds)],
                metric or phase_degree.Metric(np.ones((2, 1)), np.ones(2), at, ratio * 2 * settings.final_spp / at))

    monkeypatch.setattr(phase_degree, "degree_chi2", chi2)
    problem = SimpleNamespace(valid=np.ones((2, PIXELS // 2), bool))
    return choose_degree(problem, SimpleNamespace(final_spp=FINAL_SPP), fit=fit, **kw), starts


def _flat(value: float, jitter: float = 0.0, n: int = 4) -> list[float]:
    return [value + jitter * (-1) ** k for k in range(n)]


def test_a_degree_that_removes_a_large_misfit_is_kept_and_the_search_stops_after_two_that_do_not(monkeypatch):
    # exp4 removes 450 of chi^2 (the near-Rayleigh phase's mu^4 term); exp5 and exp6 a unit or two.
    table = {3: _flat(3600.0, 3.0), 4: _flat(3150.0, 3.0), 5: _flat(3148.0, 3.0), 6: _flat(3147.0, 3.0),
             7: _flat(3000.0)}
    choice, starts = _run(table, monkeypatch)
    assert choice.chosen == 4
    assert [s.degree for s in choice.steps] == [3, 4, 5, 6]      # exp7 never fitted: PATIENCE = 2
    assert PATIENCE == 2 and "in a row" in choice.stopped
    assert [s.accepted for s in choice.steps] == [True, True, False, False]
    ln = math.log(PIXELS)
    assert choice.steps[1].gain == pytest.approx(450.0 - ln)
    assert choice.steps[2].gain == pytest.approx(2.0 - ln)      # against exp4, the best so far
    # Nested warm starts: each degree from the one before, its new coefficient at 0.
    assert starts[0] == ("exp3", None)
    assert starts[1][0] == "exp4" and starts[1][1]["phase.b4"] == 0.0
    assert starts[1][1]["phase.b3"] == pytest.approx(0.3) and starts[1][1]["sigma_t"] == 2.0
    assert starts[2][0] == "exp5" and starts[2][1]["phase.b5"] == 0.0 and starts[2][1]["phase.b4"] == pytest.approx(0.4)
    assert choice.fit.model == "exp4"
    d = choice.to_dict()
    assert d["chosen"] == 4 and len(d["steps"]) == 4 and d["pixels"] == PIXELS


def test_a_model_that_already_holds_the_phase_stays_at_degree_3(monkeypatch):
    # Each higher degree lowers chi^2 by about one per parameter (noise fitted): the BIC rises.
    table = {3: _flat(400.0, 2.0), 4: _flat(399.0, 2.0), 5: _flat(398.5, 2.0)}
    choice, _ = _run(table, monkeypatch)
    assert choice.chosen == 3 and [s.degree for s in choice.steps] == [3, 4, 5]
    assert all(s.gain < 0 for s in choice.steps[1:])


def test_a_gain_within_the_render_noise_of_the_comparison_is_not_taken(monkeypatch):
    ln = math.log(PIXELS)
    # exp4's mean gain is 15 beyond the BIC penalty, above the margin of 10, but the seed
    # pairs scatter by +-20: twice its standard error (20) more than covers it. (The four
    # pairs alone: no close call is rendered again.)
    table = {3: [500.0, 500.0, 500.0, 500.0], 4: [485.0 - ln + 20, 485.0 - ln - 20, 485.0 - ln + 20, 485.0 - ln - 20],
             5: _flat(500.0), 6: _flat(500.0)}
    choice, _ = _run(table, monkeypatch, close_seeds=EVAL_SEEDS)
    step = choice.steps[1]
    assert step.gain == pytest.approx(15.0) and step.gain > BIC_MARGIN
    assert step.gain_se == pytest.approx(40.0 / math.sqrt(3) / 2.0)
    assert not step.accepted and choice.chosen == 3
    # The same mean gain with quiet seed pairs is taken.
    table[4] = _flat(485.0 - ln)
    choice, _ = _run(table, monkeypatch)
    assert choice.steps[1].accepted and choice.chosen == 4


def _pairs(values: list[float]) -> list[float]:
    return [float(v) for v in values]


def test_a_close_call_is_rendered_again_at_more_seed_pairs_and_decided_on_all_of_them(monkeypatch):
    ln = math.log(PIXELS)
    rng = np.random.default_rng(5)
    # exp4 truly gains 60 (beyond its one parameter's penalty). Its first four pairs happen to
    # scatter by +-50 (gain 60 +- 29 s.e. under a bar of 68: a close call); its other twelve
    # scatter by +-10 as the render noise does.
    first4 = [440.0 - ln + 50, 440.0 - ln - 50, 440.0 - ln + 50, 440.0 - ln - 50]
    rest = list(440.0 - ln + 10.0 * rng.standard_normal(CLOSE_SEEDS - EVAL_SEEDS))
    table = {3: _flat(500.0), 4: _pairs(first4 + rest), 5: _flat(500.0), 6: _flat(500.0)}
    renders: list = []
    choice, _ = _run(table, monkeypatch, renders=renders, close_seeds=EVAL_SEEDS)
    assert not choice.steps[1].accepted and choice.steps[1].gain_pairs == EVAL_SEEDS
    renders.clear()
    lines: list[str] = []
    choice, _ = _run(table, monkeypatch, renders=renders, log=lines.append)
    step = choice.steps[1]
    assert step.gain_pairs == CLOSE_SEEDS and step.accepted and choice.chosen == 4
    # The terminal says which call was decided over more pairs.
    assert "over 16 seed pairs (a close call) (better)" in lines[1] and "close call" not in lines[2]
    d = np.asarray(table[3] * 4) - np.asarray(table[4]) - ln
    assert step.gain == pytest.approx(d.mean()) and step.gain_se == pytest.approx(d.std(ddof=1) / 4.0)
    # Both degrees of the close call got the missing pairs, from the fifth on; exp5 and exp6,
    # far from the bar, were compared at the four pairs alone.
    assert (3, EVAL_SEEDS, CLOSE_SEEDS - EVAL_SEEDS) in renders and (4, EVAL_SEEDS, CLOSE_SEEDS - EVAL_SEEDS) in renders
    assert [r for r in renders if r[0] in (5, 6)] == [(5, 0, EVAL_SEEDS), (6, 0, EVAL_SEEDS)]
    assert [s.gain_pairs for s in choice.steps] == [0, CLOSE_SEEDS, EVAL_SEEDS, EVAL_SEEDS]
    assert len(choice.steps[0].chi2_adjusted_seeds) == CLOSE_SEEDS
    assert "16 seed pairs" in choice.describe() and choice.to_dict()["steps"][1]["gain_pairs"] == CLOSE_SEEDS


def test_a_clear_gain_or_loss_is_not_rendered_again(monkeypatch):
    table = {3: _flat(3600.0, 3.0), 4: _flat(3150.0, 3.0), 5: _flat(3148.0, 3.0), 6: _flat(3300.0, 3.0)}
    renders: list = []
    choice, _ = _run(table, monkeypatch, renders=renders)
    assert renders == [(m, 0, EVAL_SEEDS) for m in (3, 4, 5, 6)]
    assert choice.chosen == 4


def test_a_degree_after_one_that_gains_little_is_still_tried(monkeypatch):
    # The forward-peaked d 0.5 um media: exp4 follows the peak little better than exp3, exp5
    # much better. One miss does not stop the search.
    table = {3: _flat(5000.0), 4: _flat(4995.0), 5: _flat(4000.0), 6: _flat(3990.0), 7: _flat(3700.0)}
    choice, _ = _run(table, monkeypatch)
    assert [s.degree for s in choice.steps] == [3, 4, 5, 6, 7]
    assert choice.chosen == 7 and "reached exp7" in choice.stopped
    assert [s.accepted for s in choice.steps] == [True, False, True, False, True]


def test_a_higher_degree_limit_lets_a_phase_that_keeps_gaining_go_on(monkeypatch):
    # The d 0.5 um forward peak: every degree takes more of it. At the default limit the search
    # ends at exp7; with `max_degree` 10 (`rig estimate --degree-max 10`) it goes on, and still
    # stops after two degrees in a row that gain nothing.
    table = {m: _flat(5000.0 - 300.0 * min(m - 3, 5)) for m in range(3, 13)}
    default, _ = _run(table, monkeypatch)
    assert default.chosen == MAX_DEGREE == 7 and "reached exp7" in default.stopped
    higher, _ = _run(table, monkeypatch, max_degree=10)
    assert higher.chosen == 8 and [s.degree for s in higher.steps] == [3, 4, 5, 6, 7, 8, 9, 10]
    assert "in a row" in higher.stopped


def test_degree_range_seed_count_and_start_are_checked(monkeypatch):
    with pytest.raises(ModelParameterError, match="degrees 5..4"):
        _run({}, monkeypatch, min_degree=5, max_degree=4)
    with pytest.raises(ModelParameterError, match="at least 2"):
        _run({}, monkeypatch, seeds=1)
    with pytest.raises(ModelParameterError, match="start 'above': choose from below, own"):
        _run({}, monkeypatch, start_from="above")
    with pytest.raises(ModelParameterError, match="at most 0 spp: use a positive number"):
        _run({}, monkeypatch, max_spp=0)


def test_own_starts_fit_every_degree_from_the_estimators_start_and_the_rule_is_unchanged(monkeypatch):
    table = {3: _flat(3600.0, 3.0), 4: _flat(3150.0, 3.0), 5: _flat(3148.0, 3.0), 6: _flat(3147.0, 3.0)}
    below, _ = _run(table, monkeypatch)
    own, starts = _run(table, monkeypatch, start_from="own")
    assert starts == [("exp3", None), ("exp4", None), ("exp5", None), ("exp6", None)]
    assert own.chosen == below.chosen == 4
    assert [s.accepted for s in own.steps] == [s.accepted for s in below.steps]
    assert own.to_dict()["start_from"] == "own" and below.to_dict()["start_from"] == "below"


def test_a_gain_that_only_the_pairing_makes_significant_is_checked_over_more_pairs(monkeypatch):
    # The first four pairs scatter by +-130 for either degree, but exp4 happens to follow exp3
    # closely on them: the paired error (about 16) takes a gain of about 145, the unpaired one
    # (about 80) does not. Over all sixteen the pairs disagree: exp4 gains about 30 +- 40.
    ln = math.log(PIXELS)
    head = [2994.0, 2880.0, 3174.0, 3108.0]   # exp3's first four pairs
    diffs = [140.0, 113.0, 185.0, 168.0] + [150.0, -150.0] * 6
    exp3 = head * 4
    table = {3: exp3, 4: [a - d for a, d in zip(exp3, diffs)], 5: _flat(exp3[0] + 500), 6: _flat(exp3[0] + 500)}
    choice, _ = _run(table, monkeypatch, close_seeds=EVAL_SEEDS)
    step = choice.steps[1]
    assert step.accepted and step.gain == pytest.approx(np.mean(diffs[:4]) - ln)
    assert step.gain - 2.0 * step.gain_se > BIC_MARGIN             # paired: significant
    renders: list = []
    choice, _ = _run(table, monkeypatch, renders=renders)
    step = choice.steps[1]
    assert (4, EVAL_SEEDS, CLOSE_SEEDS - EVAL_SEEDS) in renders and step.gain_pairs == CLOSE_SEEDS
    assert step.gain == pytest.approx(np.mean(diffs) - ln) and not step.accepted and choice.chosen == 3


CAP = EVAL_SPP_MAX_FACTOR * FINAL_SPP


@pytest.mark.parametrize(("ratio", "max_spp", "expected"), [
    (12.47, CAP, 32768),                   # d 0.3 um / sigma_t 2 at 16384 spp: 0.78 at 32768
    (3.0, CAP, 8192),                      # 3 -> 1.5 -> 0.75
    (EVAL_RENDER_RATIO, CAP, 2048),        # already at the ratio: no more spp
    (0.2, CAP, 2048),                      # a recording noisier than the renders (1024-spp truths)
    (100.0, 4096, 4096),                   # the cap
    (100.0, 6000, 4096),                   # ... which a doubling does not pass
    (100.0, 1000, 2048),                   # a cap below the first spp does not lower it
    (float("nan"), CAP, 2048),             # no pixel in use: nothing to scale by
])
def test_comparison_spp_doubles_until_the_renders_are_as_quiet_as_the_recording(ratio, max_spp, expected):
    assert comparison_spp(Metric(np.ones((1, 1)), np.ones(1), 2 * FINAL_SPP, ratio), max_spp) == expected


def test_a_recording_quieter_than_the_renders_is_compared_at_more_spp(monkeypatch):
    table = {3: _flat(3600.0, 3.0), 4: _flat(3150.0, 3.0), 5: _flat(3148.0, 3.0), 6: _flat(3147.0, 3.0)}
    spps: list = []
    lines: list[str] = []
    choice, _ = _run(table, monkeypatch, ratio=12.47, spps=spps, log=lines.append)
    # The first degree is rendered at 2 x the final spp, found 12.5 x the recording's variance,
    # and rendered again at 32768 spp; the metric made there carries every later degree.
    assert spps == [(3, 2048), (3, 32768), (4, 32768), (5, 32768), (6, 32768)]
    assert choice.spp == 32768 and choice.render_ratio_first == pytest.approx(12.47)
    assert choice.render_ratio == pytest.approx(12.47 / 16)
    assert "12.5 x the recording's: comparing at 32768 spp" in lines[0]
    assert "compared at 32768 spp" in choice.describe() and choice.to_dict()["spp"] == 32768
    assert choice.chosen == 4
    # Capped: every degree at the first spp, the same choice.
    spps.clear()
    capped, _ = _run(table, monkeypatch, ratio=12.47, spps=spps, max_spp=2048)
    assert spps == [(m, 2048) for m in (3, 4, 5, 6)] and capped.spp == 2048 and capped.chosen == 4
