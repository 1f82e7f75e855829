"""Fitting phase-function models to tables in the log domain."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimate.errors import DataError, ModelParameterError
from estimate.mie import MieSettings, mie_mono
from estimate.phase_exponential import ExponentialPhase
from estimate.phase_fit import (
    PAPER_MODELS,
    fit_model,
    fit_models,
    parse_model,
    parse_models,
    sad,
)
from estimate.phase_hg import HenyeyGreenstein, TwoTermHG
from estimate.phase_polynomial import PolynomialPhase
from estimate.phase_table import PhaseTable

THETA = np.linspace(0.0, 180.0, 361)
MU = np.cos(np.radians(THETA))
S361 = MieSettings(n_theta=361)


def _table(p: np.ndarray, label: str = "synthetic") -> PhaseTable:
    return PhaseTable(theta_deg=THETA, p=np.asarray(p, dtype=float), g=float("nan"), label=label)


def test_model_names_are_parsed_strictly() -> None:
    assert parse_model("exp7").degree == 7 and parse_model("EXP7").kind == "exp"
    assert parse_model("poly0").name == "poly0"
    assert [m.name for m in parse_models("poly7,hg,tthg,exp1,hg")] == ["poly7", "hg", "tthg", "exp1"]
    assert [m.name for m in parse_models(PAPER_MODELS)] == list(PAPER_MODELS)
    for bad in ("exp", "expx", "exp 3", "hg2", "mie", "exp1.5", "legendre3", "exp21"):
        with pytest.raises(ModelParameterError):
            parse_model(bad)
    with pytest.raises(ModelParameterError, match=">= 0"):
        parse_model("exp-1")
    with pytest.raises(ModelParameterError, match="empty"):
        parse_models("exp3,,hg")


def test_exp_fit_recovers_an_exponential_phase_function() -> None:
    truth = ExponentialPhase([3.0, -1.0, 0.5])
    r = fit_model(_table(truth.eval(MU)), "exp3")
    assert r.ok and r.sad < 1e-5
    np.testing.assert_allclose(r.params["b"], truth.full_coeffs(), atol=1e-6)
    # a peaked vMF (b_1 in the hundreds) too
    vmf = ExponentialPhase.von_mises_fisher(250.0)
    r1 = fit_model(_table(vmf.eval(MU)), "exp1")
    assert r1.params["b"][1] == pytest.approx(250.0, rel=1e-6)


def test_exp_fit_is_normalised_and_its_sad_is_what_it_says() -> None:
    t = mie_mono(0.5, S361)
    r = fit_model(t, "exp5")
    e = r.phase
    assert isinstance(e, ExponentialPhase)
    assert e.b0 == pytest.approx(r.params["b"][0])
    assert r.sad == pytest.approx(sad(r.log_eval(t.mu), t.log_p), rel=1e-12)
    # no other normalised degree-5 function nearby does better: perturb each coefficient
    for i in range(1, 6):
        for h in (-1e-3, 1e-3):
            b = np.array(r.params["b"][1:])
            b[i - 1] += h * max(1.0, abs(b[i - 1]))
            alt = ExponentialPhase(b)
            assert sad(alt.log_eval(t.mu), t.log_p) >= r.sad - 1e-6


def test_hg_and_tthg_fits_recover_their_parameters() -> None:
    r = fit_model(_table(HenyeyGreenstein(0.83).eval(MU)), "hg")
    assert r.params["g"] == pytest.approx(0.83, abs=1e-6) and r.sad < 1e-3
    truth = TwoTermHG(0.92, -0.35, 0.85)
    r2 = fit_model(_table(truth.eval(MU)), "tthg")
    assert r2.sad < 0.05
    assert (r2.params["g1"], r2.params["g2"], r2.params["w"]) == pytest.approx((0.92, -0.35, 0.85), abs=1e-3)


def test_polynomial_fit_and_failure_on_forward_peak() -> None:
    truth = PolynomialPhase([0.01, 0.03, 0.005])
    r = fit_model(_table(truth.eval(MU)), "poly3")
    assert r.ok and r.sad < 1e-6
    np.testing.assert_allclose(r.params["a"], truth.full_coeffs(), atol=1e-8)
    # a strongly forward-peaked Mie function: every polynomial start is <= 0 somewhere
    t = mie_mono(2.0, S361)
    for m in ("poly3", "poly5", "poly7"):
        f = fit_model(t, m)
        assert f.sad is None and not f.ok and "<= 0" in f.message
        assert f.to_json()["sad"] is None
        with pytest.raises(ModelParameterError):
            f.log_eval(MU)


def test_paper_claims_small_and_large_particles() -> None:
    small = {f.model: f.sad for f in fit_models(mie_mono(0.1, S361), ["hg", "tthg", "exp1", "exp3", "exp7", "poly3"])}
    # small particles scatter forward and backward: single-lobe HG and vMF fit poorly
    assert small["exp3"] < small["hg"] / 5 and small["exp3"] < small["exp1"] / 5
    assert small["exp7"] < small["tthg"] and small["poly3"] is not None
    big = {f.model: f.sad for f in fit_models(mie_mono(5.0, S361), ["hg", "tthg", "exp7", "exp1", "poly7"])}
    assert big["poly7"] is None
    assert big["exp7"] < big["hg"] and big["exp7"] < big["tthg"]
    assert big["tthg"] <= big["hg"] + 1e-6
    assert big["exp1"] > big["hg"]       # vMF is the worst forward model


def test_fit_rejects_bad_tables_and_names() -> None:
    p = HenyeyGreenstein(0.5).eval(MU)
    p[10] = 0.0
    with pytest.raises(DataError):
        fit_model(_table(p), "exp3")
    with pytest.raises(ModelParameterError):
        fit_model(_table(HenyeyGreenstein(0.5).eval(MU)), "spline3")


def test_degree_zero_models_are_isotropic() -> None:
    t = _table(np.full(MU.size, 1 / (4 * math.pi)))
    for m in ("exp0", "poly0"):
        r = fit_model(t, m)
        assert r.sad == pytest.approx(0.0, abs=1e-9)
