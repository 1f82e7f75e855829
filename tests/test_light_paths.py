"""The light engine (estimate.light_paths, `ForwardModel(engine="light")`) against the
independent numpy references of tests/reference_mc.py (its single-scattering and all-orders
checks are in tests/test_forward_model.py, beside the camera engine's), against the camera engine, and its
score-function derivatives against finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest
from reference_mc import hg_eval, hg_sample, isotropic_eval, mc_slab_profile, single_scattering_profile

import estimate.light_paths as light_paths
from estimate.beam import BeamProfile
from estimate.errors import ModelParameterError
from estimate.forward import ForwardModel
from estimate.geometry import RigGeometry
from estimate.light_paths import LightPaths, SourceTables

N_PIX = 32
PITCH = 0.05  # mm in object space
BEAM_R = 0.3  # 1/e^2 radius of the references' Gaussian beam (unit power)


def _geometry(n_pix: int = N_PIX, pitch: float = PITCH, thickness: float = 1.0) -> RigGeometry:
    # As tests/test_forward_model.py: one row centred on y = 0, pixels like reference_mc's.
    return RigGeometry(thickness_mm=thickness, sensor_px=(n_pix, 1), pixel_um=20.0,
                       magnification=0.02 / pitch, image_center_px=(n_pix / 2, 0.5))


def _model(phase: str = "exp0", engine: str = "light", **kw) -> ForwardModel:
    return ForwardModel(_geometry(), BeamProfile.gaussian(BEAM_R), phase=phase, engine=engine, **kw)


def _region_sums(stack: np.ndarray, ref: np.ndarray, lo: float, hi: float) -> np.ndarray:
    sel = (ref > lo * ref.max()) & (ref <= hi * ref.max())
    return stack[..., sel].sum(axis=-1)


@pytest.mark.parametrize("phase,params,exts", [
    ("exp3", {"phase.b1": 3.0, "phase.b2": 1.0, "phase.b3": 0.5}, ()),
    ("tthg", {"phase.g_forward": 0.7, "phase.g_backward": -0.3, "phase.w_forward": 0.8}, ()),
    ("hg", {"phase.g": 0.6, "beam_halo.fraction": 0.05, "beam_halo.sigma_mm": 0.5}, ("beam_halo",)),
])
def test_light_and_camera_engines_agree(phase: str, params: dict, exts: tuple) -> None:
    """The exponential plugin's, the two-lobe blend's and the halo's conventions as the camera
    engine has them: the profiles' peak and shoulder sums agree within their Monte Carlo errors."""
    geo = RigGeometry(thickness_mm=1.0, magnification=0.3, profile_columns=(232, 280))
    beam = BeamProfile.gaussian(0.5)
    p = {"sigma_t": 2.0, "albedo": 0.9, **params}
    angles = [30.0, 150.0]
    light = ForwardModel(geo, beam, phase=phase, extensions=exts, engine="light")
    camera = ForwardModel(geo, beam, phase=phase, extensions=exts)
    lt = np.array([light.render_profiles(p, angles, spp=2048, seed=s) for s in range(4)])
    cm = np.array([camera.render_profiles(p, angles, spp=4096, seed=s) for s in range(6)])
    for k, phi in enumerate(angles):
        ref = lt[:, k].mean(axis=0)
        for lo, hi in ((0.3, 2.0), (0.03, 0.3)):
            a, b = _region_sums(lt[:, k], ref, lo, hi), _region_sums(cm[:, k], ref, lo, hi)
            se = math.sqrt(a.var(ddof=1) / a.size + b.var(ddof=1) / b.size)
            assert abs(a.mean() - b.mean()) < max(4.0 * se, 0.005 * a.mean()), (phi, lo)
            assert abs(a.mean() / b.mean() - 1.0) < 0.04, (phi, lo)


@pytest.mark.parametrize("eta", [1.0, 1.4])
def test_scores_match_finite_differences(eta: float) -> None:
    """One pass's score images against central differences of renders at many paths; with a
    refractive index the camera's connection carries the back face's reflection too."""
    geo = RigGeometry(thickness_mm=1.0, magnification=0.3, profile_columns=(240, 272))
    beam = BeamProfile.gaussian(0.5)
    model = ForwardModel(geo, beam, phase="tthg", engine="light")
    lp = LightPaths(geo, "tthg", model.mi)
    values = model.validate({"sigma_t": 2.0, "albedo": 0.8, "phase.g_forward": 0.6, "phase.g_backward": -0.2,
                             "phase.w_forward": 0.7})
    window = geo.window()
    names = ["sigma_t", "albedo", "phase.g_forward", "phase.g_backward", "phase.w_forward"]
    n = 400_000

    def render(v: dict, seed: int, scores: tuple = ()) -> tuple[float, dict]:
        img, d = lp.render(v, [40.0, 140.0], window, n, seed, beam=beam, thickness_mm=1.0, eta=eta, scores=scores)
        return float(np.array(img).sum()), {k: float(np.array(x).sum()) for k, x in d.items()}

    score = {k: np.mean([render(values, s, tuple(names))[1][k] for s in range(3)]) for k in names}
    for name in names:
        h = 0.05
        fd = np.mean([(render({**values, name: values[name] + h}, 100 + s)[0]
                       - render({**values, name: values[name] - h}, 200 + s)[0]) / (2 * h) for s in range(3)])
        total = render(values, 300)[0]
        # Independent renders: the difference's error is about 2e-3 of the total over 2h.
        assert score[name] == pytest.approx(fd, abs=0.03 * abs(fd) + 3e-3 * total / h), name


def test_forward_model_vjp_and_jacobian_use_the_same_scores() -> None:
    geo = RigGeometry(thickness_mm=1.0, magnification=0.3, profile_columns=(232, 280))
    exts = ("lens_blur", "stray_light", "filter_bandwidth", "angle_offset", "beam_halo")
    fm = ForwardModel(geo, BeamProfile.gaussian(0.5), phase="exp2", extensions=exts, engine="light")
    assert fm.derivative_kind("beam_halo.fraction") == "fd"   # the halo moves the paths' starts
    assert fm.derivative_kind("sigma_t") == "ad"
    p = fm.validate({"sigma_t": 2.0, "albedo": 0.9, "phase.b1": 2.0, "phase.b2": 0.5, "lens_blur.core_sigma_px": 1.2,
                     "stray_light.offset": 1e-3, "filter_bandwidth.spread": 0.3, "angle_offset.delta_deg": 1.0,
                     "beam_halo.fraction": 0.02})
    angles = [30.0, 150.0]
    lin = fm.linearize(p, angles, spp=256, seed=4)
    # the same paths (float32 sums in another order: 1e-7)
    np.testing.assert_allclose(lin.profiles, fm.render_profiles(p, angles, spp=256, seed=4), rtol=1e-5)
    cot = np.random.default_rng(0).normal(size=lin.profiles.shape)
    grads = lin.vjp(cot, base_profiles=lin.profiles)
    names = ["sigma_t", "albedo", "phase.b1", "filter_bandwidth.spread", "lens_blur.core_sigma_px",
             "stray_light.offset", "angle_offset.delta_deg", "beam_halo.fraction"]
    jac = fm.jacobian(p, angles, names, spp=256, seed=4, base_profiles=lin.profiles)
    for name in names:
        # the same paths; float32 sums in another order (1e-7) against a contraction that cancels
        scale = float(np.sum(np.abs(jac[name] * cot)))
        assert grads[name] == pytest.approx(float(np.sum(jac[name] * cot)), abs=1e-4 * scale + 1e-12), name
    with pytest.raises(RuntimeError, match="already"):
        lin.vjp(cot)


def test_paths_in_chunks_render_the_same(monkeypatch) -> None:
    model = _model("hg")
    p = {"sigma_t": 3.0, "albedo": 0.9, "phase.g": 0.4}
    whole = model.render_profiles(p, [30.0, 150.0], spp=64, seed=2)
    monkeypatch.setattr(light_paths, "CHUNK_PATHS", 1000)
    parts = model.render_profiles(p, [30.0, 150.0], spp=64, seed=2)
    np.testing.assert_allclose(parts, whole, rtol=1e-5, atol=1e-7 * whole.max())
    other = model.render_profiles(p, [30.0, 150.0], spp=64, seed=3)
    assert not np.allclose(other, whole)


def test_same_seed_renders_the_same_image_and_scores() -> None:
    """The pixels' sums are kept in double precision: the threads' order of adding shows in
    the 16th digit, not, as with single-precision sums, the 7th (which made the fixed-seed
    Levenberg-Marquardt take different steps from the same point in different runs)."""
    geo = RigGeometry(thickness_mm=1.0, magnification=0.3, profile_columns=(240, 272))
    model = ForwardModel(geo, BeamProfile.gaussian(0.5), phase="exp3", engine="light")
    p = {"sigma_t": 2.0, "albedo": 0.9, "phase.b1": 2.0, "phase.b2": 0.5, "phase.b3": 0.2}
    names = ["sigma_t", "albedo", "phase.b2"]
    # Enough paths (6 x 4096 x 32) for several threads to add to each pixel: with the sums
    # in single precision three such renders differed by up to 3e-8 of the peak.
    angles = [15.0, 45.0, 75.0, 105.0, 135.0, 165.0]
    runs = [(model.render_profiles(p, angles, spp=4096, seed=4),
             model.jacobian(p, angles, names, spp=4096, seed=4)) for _ in range(3)]
    first, jac = runs[0]
    for prof, j in runs[1:]:
        np.testing.assert_allclose(prof, first, rtol=1e-12, atol=1e-13 * np.abs(first).max())
        for n in names:
            np.testing.assert_allclose(j[n], jac[n], rtol=1e-12, atol=1e-13 * np.abs(jac[n]).max())


def test_source_tables_sample_the_bilinear_map() -> None:
    """The start's u follows the marginal of the map's bilinear surface, and the conditional
    share of v over the whole line is 1: a light render's power equals the map's."""
    rng = np.random.default_rng(1)
    prof = BeamProfile.centered(rng.uniform(0.0, 1.0, (7, 9)), 0.1)
    t = SourceTables.from_profile(prof)
    u = np.linspace(t.u_lo, t.u_lo + (t.e.shape[1] - 1) * t.pitch, 4001)
    v = np.linspace(t.v_lo, t.v_lo + (t.e.shape[0] - 1) * t.pitch, 4001)
    surface = prof.lookup(u[None, :], v[:, None])
    assert t.power == pytest.approx(np.trapezoid(np.trapezoid(surface, v, axis=0), u), rel=1e-4)

    from estimate.mitsuba_env import init_mitsuba

    mi = init_mitsuba()
    lp = LightPaths(_geometry(), "exp0", mi)
    tables, dev = lp._source(prof)
    xi = mi.Float(rng.random(200_000).astype(np.float32))
    us, i, a = lp._sample_u(tables, dev, xi)
    hist, edges = np.histogram(np.array(us), bins=40, range=(u[0], u[-1]), density=True)
    centres = 0.5 * (edges[1:] + edges[:-1])
    marginal = np.interp(centres, u, np.trapezoid(surface, v, axis=0)) / t.power
    assert np.allclose(hist, marginal, atol=0.06 * marginal.max())
    whole = lp._v_mass(tables, dev, i, a, mi.Bool(False), mi.Float(0.0), mi.Float(1.0), mi.Float(-50.0),
                       mi.Float(50.0))
    assert np.allclose(np.array(whole), 1.0, atol=1e-5)


@pytest.mark.parametrize("n", [1.33, 1.5])
def test_refractive_boundary_matches_mcml_reference(n: float) -> None:
    """Snell and Fresnel on entry, Fresnel reflection (total beyond the critical angle) at
    the faces, and the exit at normal incidence with the back face's reflection: all orders
    against the photon Monte Carlo, and the single-scattered light against its closed form."""
    model = _model("hg", extensions=["refractive_boundary"])
    assert model.derivative_kind("sigma_t") == "ad"   # scores: no prbvolpath limitation here
    params = {"sigma_t": 6.0, "albedo": 0.9, "phase.g": 0.5, "refractive_boundary.n": n}
    for phi in (30.0, 150.0):
        prof = model.render_profiles(params, [phi], spp=8192, seed=8)[0]
        ref, _, _ = mc_slab_profile(6.0, 0.9, 1.0, hg_sample(0.5), hg_eval(0.5), phi, BEAM_R, PITCH,
                                     N_PIX, PITCH, n_index=n, n_photons=200_000, seed=9)
        assert prof.sum() == pytest.approx(ref.sum(), rel=0.015), phi
        pb, rb = prof.reshape(-1, 4).sum(axis=1), ref.reshape(-1, 4).sum(axis=1)
        bright = rb > 0.3 * rb.max()
        assert np.allclose(pb[bright], rb[bright], rtol=0.06), phi
    single = _model("exp0", max_depth=1, extensions=["refractive_boundary"])
    for phi in (30.0, 150.0):
        p1 = single.render_profiles({"sigma_t": 3.0, "albedo": 0.7, "refractive_boundary.n": n}, [phi],
                                    spp=32768, seed=1)[0]
        r1 = single_scattering_profile(3.0, 0.7, 1.0, isotropic_eval, phi, BEAM_R, PITCH, N_PIX, PITCH, n_index=n)
        assert p1.sum() == pytest.approx(r1.sum(), rel=0.01), phi


def test_light_engine_refuses_what_it_does_not_trace() -> None:
    with pytest.raises(ModelParameterError, match="unknown render engine"):
        _model("exp0", engine="photon")
    geo = RigGeometry(thickness_mm=1.0, sensor_px=(8, 100))
    fm = ForwardModel(geo, BeamProfile.gaussian(BEAM_R), phase="exp0", engine="light")
    with pytest.raises(ModelParameterError, match="at most 64 rows"):
        fm.render({"sigma_t": 1.0, "albedo": 0.9}, [30.0], rows=(0, 100), columns=(0, 8), spp=4)
    with pytest.raises(ModelParameterError, match="no power"):
        SourceTables.from_profile(BeamProfile.centered(np.zeros((3, 3)), 0.1))


def test_a_full_window_band_is_lit_around_the_profile_row() -> None:
    """Several rows a window: each vertex adds to every row its share of start positions."""
    g = RigGeometry(thickness_mm=1.0, sensor_px=(24, 24), magnification=0.4)
    model = ForwardModel(g, BeamProfile.disk(0.2), phase="exp0", engine="light")
    img = model.render({"sigma_t": 3.0, "albedo": 0.9}, [150.0], rows=(0, 24), columns=(0, 24), spp=2048, seed=1)[0]
    rows = img.sum(axis=1)
    assert abs(int(np.argmax(rows)) + 0.5 - 12) <= 1.5
    # symmetric in y about the beam's axis (the disk is centred on it), within the noise
    bright = rows[:12] > 0.2 * rows.max()
    np.testing.assert_allclose(rows[:12][bright], rows[12:][::-1][bright], rtol=0.05)


def test_tent_response_keeps_the_light_and_smooths_differences_in_the_angle():
    """The continuous column response (`tent`) splits each vertex between two columns: the same
    light in all, and differences in a parameter that moves every path are less noisy."""
    geo = RigGeometry(thickness_mm=1.0, magnification=0.5, profile_columns=(236, 276))
    beam = BeamProfile.disk(0.3)
    model = ForwardModel(geo, beam, phase="hg", engine="light")
    lp = LightPaths(geo, "hg", model.mi)
    values = model.validate({"sigma_t": 2.0, "albedo": 0.9, "phase.g": 0.6})
    window = geo.window()

    def render(angle: float, seed: int, tent: bool) -> np.ndarray:
        img, _ = lp.render(values, [angle], window, 40 * 512, seed, beam=beam, thickness_mm=1.0, tent=tent)
        return np.array(img, dtype=np.float64)

    box, tent = render(60.0, 1, False), render(60.0, 1, True)
    inner = slice(3, -3)   # away from the window's edges, where the tent sends light outside
    assert tent[inner].sum() == pytest.approx(box[inner].sum(), rel=0.02)
    noise = {}
    for t in (False, True):
        cols = np.array([(render(60.2, s, t) - render(59.8, s, t)) / 0.4 for s in range(4)])
        noise[t] = np.sqrt(np.mean(cols.var(axis=0, ddof=1))) / np.sqrt(np.mean(cols.mean(axis=0) ** 2))
    assert noise[True] < 0.7 * noise[False]
