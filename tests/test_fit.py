"""estimate.fit: recovery of known parameters on a tiny synthetic session, uncertainties."""

from __future__ import annotations

import math

import numpy as np
import pytest
from synth_session import make_session

from estimate.fit import FitSettings, fit_channel, loss_at
from estimate.loss import log_loss, profile_scale
from estimate.problem import load_problem

TRUTH = {"sigma_t": 3.0, "albedo": 0.85, "phase.b1": 3.0, "phase.b2": 0.0, "phase.b3": 0.0}
PHASE = {k: v for k, v in TRUTH.items() if k.startswith("phase.")}
FAST = {"max_iterations": 30, "spp_start": 128, "spp_max": 256, "final_spp": 512, "start_spp": 64, "window": 4,
        "lm_spp": 512}


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    s = make_session(tmp_path_factory.mktemp("f") / "s", {"g": TRUTH}, angles=[30, 60, 120, 150], spp=1024,
                     width=128, scale=2e5)
    return load_problem(s, "g", columns=48)


def test_scale_profiling_and_loss_gradient():
    rng = np.random.default_rng(0)
    model = rng.uniform(0.1, 1.0, (3, 20))
    valid = np.ones_like(model, bool)
    meas = 7.0 * model
    assert profile_scale(meas, model, valid, 1e-2) == pytest.approx(7.0, rel=1e-4)
    _, g = log_loss(meas, model * 1.1, valid, 7.0, 1e-2)
    eps = 1e-6
    d = np.zeros_like(model)
    d[1, 3] = eps
    fd = (log_loss(meas, model * 1.1 + d, valid, 7.0, 1e-2)[0] - log_loss(meas, model * 1.1 - d, valid, 7.0, 1e-2)[0]) / (2 * eps)
    assert g[1, 3] == pytest.approx(fd, rel=1e-5)


def test_recovers_sigma_t_and_albedo(problem):
    est = []
    for seed in (0,):
        r = fit_channel(problem, "exp3", fixed=PHASE, settings=FitSettings(seed=seed, **FAST))
        est.append(r)
        assert set(r.uncertainties) == {"sigma_t", "albedo"}
        assert all(math.isfinite(u) and u > 0 for u in r.uncertainties.values())
        assert r.fitted.shape == problem.measured.shape
        assert r.iterations <= FAST["max_iterations"] and r.spp_schedule[0] == [0, 128]
    for r in est:
        assert r.parameters["sigma_t"] == pytest.approx(3.0, rel=0.25)
        assert abs(r.parameters["albedo"] - 0.85) < 0.1
    # The fit is no worse than a wrong parameter set by far (loss at a clearly wrong point).
    wrong = loss_at(problem, "exp3", {**TRUTH, "sigma_t": 0.7, "albedo": 0.5}, spp=256)["loss"]
    assert est[0].loss < wrong
    # Final loss near the noise floor (the loss at the true parameters, same spp and delta).
    assert est[0].loss < 1.5 * loss_at(problem, "exp3", TRUTH, spp=512)["loss"]


def test_fixed_parameters_stay(problem):
    r = fit_channel(problem, "tthg", start={"sigma_t": 3.0, "albedo": 0.85},
                    fixed={"phase.g_backward": -0.2, "phase.w_forward": 0.95},
                    settings=FitSettings(seed=3, max_iterations=6, spp_start=16, spp_max=16, final_spp=32,
                                         window=3, uncertainties=False, lm_iterations=0))
    assert r.parameters["phase.g_backward"] == -0.2 and r.parameters["phase.w_forward"] == 0.95
    assert r.start["sigma_t"] == 3.0 and r.iterations == 6 and r.stop_reason == "max_iterations"
