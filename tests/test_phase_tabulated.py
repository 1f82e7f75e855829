"""The tabulated phase function (the simulated bench's Mie truth): normalisation, g,
interpolation and its refusals; rendered by both engines the same as the function it
tabulates."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimate.beam import BeamProfile
from estimate.errors import ModelParameterError
from estimate.forward import ForwardModel
from estimate.geometry import RigGeometry
from estimate.light_paths import LightPaths
from estimate.mie import PAPER_SETTINGS, mie_poly
from estimate.mitsuba_phase import tabulated_phase_dict
from estimate.phase_exponential import ExponentialPhase
from estimate.phase_table import PhaseTable
from estimate.phase_tabulated import TabulatedPhase

B = [3.0, 1.0, 0.5]


def _exp_table(b=B, n: int = 1801) -> tuple[ExponentialPhase, PhaseTable]:
    ep = ExponentialPhase(b)
    th = np.linspace(0.0, 180.0, n)
    return ep, PhaseTable(theta_deg=th, p=ep.eval(np.cos(np.radians(th))), g=0.0, label="exp")


def _sphere_integral(tp: TabulatedPhase, f=lambda mu: 1.0) -> float:
    # An independent quadrature: Gauss-Legendre in theta on panels that split each of the
    # table's intervals (the interpolant has kinks at its entries, smooth between them).
    x, w = np.polynomial.legendre.leggauss(8)
    per = max(1, 1024 // (tp.nodes - 1))
    edges = np.linspace(0.0, math.pi, per * (tp.nodes - 1) + 1)
    total = 0.0
    for a, b in zip(edges[:-1], edges[1:]):
        th = 0.5 * (b - a) * x + 0.5 * (a + b)
        mu = np.cos(th)
        total += 0.5 * (b - a) * float(np.sum(w * tp.eval(mu) * f(mu) * np.sin(th)))
    return 2.0 * math.pi * total


def test_normalised_over_the_sphere_with_the_tables_g():
    ep, table = _exp_table()
    tp = TabulatedPhase.from_table(table)
    assert _sphere_integral(tp) == pytest.approx(1.0, abs=1e-6)
    assert tp.g == pytest.approx(_sphere_integral(tp, lambda mu: mu), abs=1e-6)
    # The exponential function it tabulates, at and between the table's angles.
    mu = np.cos(np.radians(np.linspace(0.0, 180.0, 7919)))
    assert np.max(np.abs(tp.log_eval(mu) - np.log(ep.eval(mu)))) < 1e-4


def test_mie_table_keeps_its_g_and_its_values():
    mie = mie_poly(0.5, 0.1, PAPER_SETTINGS)
    tp = TabulatedPhase.from_table(mie)
    assert tp.g == pytest.approx(mie.g, abs=1e-4)
    assert np.allclose(tp.log_eval(mie.mu), np.log(mie.p), atol=1e-4)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-5.0, 5.0), min_size=2, max_size=40), st.floats(-50.0, 50.0))
def test_any_log_table_is_normalised_whatever_its_offset(log_p, offset):
    tp = TabulatedPhase.normalised(np.asarray(log_p) + offset)
    assert _sphere_integral(tp) == pytest.approx(1.0, rel=1e-5)
    assert np.allclose(tp.log_p - tp.log_p[0], np.asarray(log_p) - log_p[0])


@pytest.mark.parametrize("theta,p,match", [
    (np.linspace(0.0, 170.0, 18), np.ones(18), "span 0 to 180"),
    (np.linspace(5.0, 180.0, 18), np.ones(18), "span 0 to 180"),
    (np.linspace(0.0, 180.0, 19), np.r_[np.ones(18), 0.0], "positive"),
    (np.linspace(0.0, 180.0, 19), np.r_[np.ones(18), np.nan], "positive"),
])
def test_refuses_a_table_it_cannot_render(theta, p, match):
    with pytest.raises(ModelParameterError, match=match):
        TabulatedPhase.from_table(PhaseTable(theta_deg=theta, p=p, g=0.0))


def test_table_and_phase_name_go_together():
    _, table = _exp_table()
    tp = TabulatedPhase.from_table(table)
    geo = RigGeometry(thickness_mm=1.0, magnification=0.3, profile_columns=(240, 272))
    beam = BeamProfile.gaussian(0.5)
    with pytest.raises(ModelParameterError, match="table"):
        ForwardModel(geo, beam, phase="table", engine="light")
    with pytest.raises(ModelParameterError, match="table"):
        ForwardModel(geo, beam, phase="exp3", engine="light", phase_table=tp)
    with pytest.raises(ModelParameterError, match="table"):
        LightPaths(geo, "exp3", None, table=tp)
    with pytest.raises(ModelParameterError):
        tabulated_phase_dict([0.0])


@pytest.mark.parametrize("engine", ["light", "camera"])
def test_engines_render_a_tabulated_function_as_the_function_itself(engine):
    """Same seed, same random numbers: the tabulated exp3 and exp3 itself give the same
    profiles to the table's interpolation error (both engines sample by an inverse CDF of
    the same density), front and back lit."""
    _, table = _exp_table()
    tp = TabulatedPhase.from_table(table)
    geo = RigGeometry(thickness_mm=1.0, magnification=0.3, profile_columns=(240, 272))
    beam = BeamProfile.gaussian(0.5)
    base = {"sigma_t": 2.0, "albedo": 0.9}
    exp = ForwardModel(geo, beam, phase="exp3", engine=engine)
    tab = ForwardModel(geo, beam, phase="table", engine=engine, phase_table=tp)
    assert tab.parameter_names == ["sigma_t", "albedo"]
    a = exp.render_profiles({**base, **{f"phase.b{i}": v for i, v in enumerate(B, start=1)}}, [30.0, 150.0],
                            spp=256, seed=3)
    b = tab.render_profiles(base, [30.0, 150.0], spp=256, seed=3)
    assert np.all(np.isfinite(b)) and b.max() > 0
    assert np.max(np.abs(a - b)) < 2e-4 * a.max()
    # A different function is told apart at the same seed.
    _, other = _exp_table([2.0, 1.0, 0.5])
    c = ForwardModel(geo, beam, phase="table", engine=engine,
                     phase_table=TabulatedPhase.from_table(other)).render_profiles(base, [30.0, 150.0], spp=256, seed=3)
    assert np.max(np.abs(a - c)) > 0.02 * a.max()
