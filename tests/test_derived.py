"""Derived quantities (sigma_a, sigma_s', g, ...) and their propagated uncertainties."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimate.derived import DERIVED_UNITS, derived_quantities


def test_values_follow_the_definitions():
    d = derived_quantities("hg", {"sigma_t": 2.0, "albedo": 0.9, "phase.g": 0.5})
    assert set(d) == set(DERIVED_UNITS)
    assert d["sigma_s"]["value"] == pytest.approx(1.8)
    assert d["sigma_a"]["value"] == pytest.approx(0.2)
    assert d["g"]["value"] == pytest.approx(0.5, abs=1e-9)
    assert d["sigma_s_reduced"]["value"] == pytest.approx(0.9)
    assert d["transport_albedo"]["value"] == pytest.approx(0.9 / 1.1)
    assert all(v["uncertainty"] is None for v in d.values())


def test_exponential_phase_g_is_the_phase_objects_mean_cosine():
    from estimate.phase_exponential import ExponentialPhase

    p = {"sigma_t": 3.0, "albedo": 0.95, "phase.b1": 3.0, "phase.b2": 1.0, "phase.b3": 0.5}
    d = derived_quantities("exp3", p)
    assert d["g"]["value"] == pytest.approx(ExponentialPhase([3.0, 1.0, 0.5]).g, rel=1e-12)


def test_uncertainties_match_sampling_the_covariance():
    """Linear propagation against the spread of the quantities over seeded draws from the
    covariance (small errors, so the linearisation holds), correlations included: sigma_t
    and g anti-correlated as on thick slabs make sigma_s' tighter than either."""
    params = {"sigma_t": 6.0, "albedo": 0.9, "phase.g": 0.6}
    sd = np.array([0.3, 0.004, 0.02])
    corr = np.array([[1.0, 0.2, 0.95], [0.2, 1.0, 0.1], [0.95, 0.1, 1.0]])
    cov = corr * np.outer(sd, sd)
    names = list(params)
    d = derived_quantities("hg", params, {a: {b: float(cov[i, j]) for j, b in enumerate(names)}
                                         for i, a in enumerate(names)})
    rng = np.random.default_rng(7)
    draws = rng.multivariate_normal([params[n] for n in names], cov, size=20000)
    samples = {
        "sigma_a": draws[:, 0] * (1 - draws[:, 1]),
        "sigma_s_reduced": draws[:, 0] * draws[:, 1] * (1 - draws[:, 2]),
        "g": draws[:, 2],
    }
    for k, s in samples.items():
        assert d[k]["uncertainty"] == pytest.approx(float(np.std(s)), rel=0.05), k
    rel_sr = d["sigma_s_reduced"]["uncertainty"] / d["sigma_s_reduced"]["value"]
    assert rel_sr < sd[0] / params["sigma_t"]
    assert math.isfinite(d["transport_albedo"]["uncertainty"])


def test_fixed_parameters_contribute_no_uncertainty():
    params = {"sigma_t": 2.0, "albedo": 0.9, "phase.g": 0.5}
    d = derived_quantities("hg", params, {"sigma_t": {"sigma_t": 0.01}})
    assert d["sigma_a"]["uncertainty"] == pytest.approx(0.1 * 0.1)
    assert d["g"]["uncertainty"] == 0.0


@pytest.mark.parametrize("w", [1.0, 0.999999, 0.0])
def test_a_parameter_at_the_end_of_its_range_is_differenced_inside_it(w):
    """A two-lobe fit with its forward weight at (or a hair below) 1: the difference for g
    stays inside [0, 1], where the phase function is defined, and still gives the slope
    (g = w g_f + (1 - w) g_b, so dg/dw = g_f - g_b)."""
    params = {"sigma_t": 2.0, "albedo": 0.9, "phase.g_forward": 0.8, "phase.g_backward": -0.2,
              "phase.w_forward": w}
    d = derived_quantities("tthg", params, {"phase.w_forward": {"phase.w_forward": 0.01 ** 2}})
    assert d["g"]["value"] == pytest.approx(w * 0.8 - (1 - w) * 0.2, abs=1e-9)
    assert d["g"]["uncertainty"] == pytest.approx(0.01 * 1.0, rel=1e-6)
