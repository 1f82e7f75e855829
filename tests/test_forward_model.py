"""The Mitsuba forward model of the rig (estimate.forward) against the independent numpy
references of tests/reference_mc.py (same frame and angle conventions)."""

from __future__ import annotations

import gc
import math

import numpy as np
import pytest
from reference_mc import (
    hg_eval,
    hg_sample,
    isotropic_eval,
    mc_slab_profile,
    single_scattering_profile,
)

from estimate.beam import BeamProfile
from estimate.errors import ModelParameterError
from estimate.forward import ForwardModel
from estimate.geometry import RigGeometry

N_PIX = 32
PITCH = 0.05  # mm in object space
BEAM_R = 0.3  # 1/e^2 radius of the reference's Gaussian beam (unit power)


def _geometry(n_pix: int = N_PIX, pitch: float = PITCH, thickness: float = 1.0) -> RigGeometry:
    # One-row sensor whose row is centred on y = 0 and whose pixels are centred like
    # reference_mc.pixel_centers (x = (i - (n-1)/2) * pitch).
    return RigGeometry(thickness_mm=thickness, sensor_px=(n_pix, 1), pixel_um=20.0,
                       magnification=0.02 / pitch, image_center_px=(n_pix / 2, 0.5))


def _model(phase: str = "exp0", **kw) -> ForwardModel:
    thickness = kw.pop("thickness", 1.0)
    return ForwardModel(_geometry(thickness=thickness), BeamProfile.gaussian(BEAM_R), phase=phase, **kw)


@pytest.fixture(scope="module")
def single_model() -> ForwardModel:
    return _model("exp0", max_depth=2)  # depth 2 = exactly the single-scattered light


@pytest.mark.parametrize("engine", ["camera", "light"])
@pytest.mark.parametrize("sigma_t", [0.5, 3.0])
def test_single_scattering_matches_analytic(single_model: ForwardModel, sigma_t: float, engine: str) -> None:
    """Both engines against the closed form. The light engine's depth counts collisions (one:
    single scattering), and its per-pixel noise is largest where few paths get there (back-lit
    at 65 deg, sigma_t 3: the light that scatters near the front face has crossed e^-7 of the
    slab), so its pixels are held to their mean and a wider band."""
    model = single_model if engine == "camera" else _model("exp0", max_depth=1, engine="light")
    spp, rtol = (65536, 0.06) if engine == "camera" else (32768, 0.15)
    angles = [35.0, 70.0, 115.0, 155.0]
    prof = model.render_profiles({"sigma_t": sigma_t, "albedo": 0.7}, angles, spp=spp, seed=3)
    for k, phi in enumerate(angles):
        ref = single_scattering_profile(sigma_t, 0.7, 1.0, isotropic_eval, phi, BEAM_R, PITCH, N_PIX, PITCH)
        assert prof[k].sum() == pytest.approx(ref.sum(), rel=0.01), phi
        bright = ref > 0.2 * ref.max()
        assert np.allclose(prof[k][bright], ref[bright], rtol=rtol), phi
        assert np.mean(prof[k][bright] / ref[bright]) == pytest.approx(1.0, abs=0.015), phi
        # where the reference is dark the render is dark too (orientation, beam position)
        assert prof[k][ref < 1e-6 * ref.max()].sum() < 1e-3 * prof[k].sum(), phi


def test_optically_thin_slab_is_single_scattering() -> None:
    """sigma_t d = 0.02: the whole profile (all orders) is the single-scattering one."""
    # A wide beam and pixels, so that many camera rays meet the beam (variance).
    model = ForwardModel(_geometry(pitch=0.1), BeamProfile.gaussian(1.0), phase="exp0")
    angles = [40.0, 140.0]
    prof = model.render_profiles({"sigma_t": 0.02, "albedo": 0.2}, angles, spp=2**18, seed=4)
    for k, phi in enumerate(angles):
        ref = single_scattering_profile(0.02, 0.2, 1.0, isotropic_eval, phi, 1.0, 0.1, N_PIX, 0.1)
        assert prof[k].sum() == pytest.approx(ref.sum(), rel=0.01), phi


@pytest.mark.parametrize("engine", ["camera", "light"])
def test_multiple_scattering_albedo_one_matches_mcml_reference(engine: str) -> None:
    """Albedo 1, index-matched, forward-peaked: the whole profile (all orders) against the
    photon Monte Carlo whose R + T + A = 1 bookkeeping tests/test_reference_mc.py checks."""
    model = _model("hg", engine=engine)
    params = {"sigma_t": 4.0, "albedo": 1.0, "phase.g": 0.5}
    for phi in (30.0, 150.0):
        prof = model.render_profiles(params, [phi], spp=4096, seed=5)[0]
        ref, _, _ = mc_slab_profile(4.0, 1.0, 1.0, hg_sample(0.5), hg_eval(0.5), phi, BEAM_R, PITCH,
                                     N_PIX, PITCH, n_photons=200_000, seed=7)
        assert prof.sum() == pytest.approx(ref.sum(), rel=0.03), phi
        bright = ref > 0.3 * ref.max()
        assert np.allclose(prof[bright], ref[bright], rtol=0.08), phi


def test_refractive_boundary_n1_equals_index_matched() -> None:
    params = {"sigma_t": 3.0, "albedo": 0.9}
    angles = [30.0, 150.0]
    base = _model("exp0").render_profiles(params, angles, spp=4096, seed=6)
    refr = _model("exp0", extensions=["refractive_boundary"]).render_profiles(
        {**params, "refractive_boundary.n": 1.0}, angles, spp=4096, seed=6)
    for k in range(2):
        assert refr[k].sum() == pytest.approx(base[k].sum(), rel=0.02)
        bright = base[k] > 0.3 * base[k].max()
        assert np.allclose(refr[k][bright], base[k][bright], rtol=0.08)


def test_refractive_boundary_n145_matches_mcml_reference() -> None:
    model = _model("hg", extensions=["refractive_boundary"])
    # next-event rays end inside the medium there: sigma_t by finite differences
    assert model.derivative_kind("sigma_t") == "fd"
    params = {"sigma_t": 6.0, "albedo": 0.9, "phase.g": 0.5, "refractive_boundary.n": 1.45}
    for phi in (30.0, 150.0):
        prof = model.render_profiles(params, [phi], spp=8192, seed=8)[0]
        ref, _, _ = mc_slab_profile(6.0, 0.9, 1.0, hg_sample(0.5), hg_eval(0.5), phi, BEAM_R, PITCH,
                                     N_PIX, PITCH, n_index=1.45, n_photons=200_000, seed=9)
        assert prof.sum() == pytest.approx(ref.sum(), rel=0.03), phi
        # 4-pixel bins (the render's per-pixel noise at this spp is several percent)
        pb, rb = prof.reshape(-1, 4).sum(axis=1), ref.reshape(-1, 4).sum(axis=1)
        bright = rb > 0.3 * rb.max()
        assert np.allclose(pb[bright], rb[bright], rtol=0.08), phi


def test_renders_are_reproducible_and_seeded(single_model: ForwardModel) -> None:
    p = {"sigma_t": 2.0, "albedo": 0.8}
    a = single_model.render_profiles(p, [40.0, 120.0], spp=64, seed=11)
    b = single_model.render_profiles(p, [40.0, 120.0], spp=64, seed=11)
    c = single_model.render_profiles(p, [40.0, 120.0], spp=64, seed=12)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_renders_queued_behind_one_another_are_those_made_one_at_a_time(monkeypatch) -> None:
    """`render_profiles_many` (the coarse start's candidates, each traced while the previous
    one's kernels run) gives every render's numbers bit for bit, image-space extensions
    included; the exponential phase plugin, told its coefficients instead of reading them
    back from the device, builds the same sampling table."""
    model = _model("exp3", extensions=("lens_blur",))
    angles = [30.0, 75.0, 140.0]
    requests = [({"sigma_t": 2.0, "albedo": 0.8, "phase.b1": 1.0}, 4),
                ({"sigma_t": 4.5, "albedo": 0.6, "phase.b1": 3.0, "phase.b3": -0.4, "lens_blur.core_sigma_px": 2.0}, 4),
                ({"sigma_t": 1.0, "albedo": 0.95, "phase.b2": 0.7}, 9)]
    many = model.render_profiles_many(requests, angles, spp=16)
    one = [model.render_profiles(p, angles, spp=16, seed=s) for p, s in requests]
    assert len(many) == 3 and all(np.array_equal(a, b) for a, b in zip(many, one))
    assert not np.array_equal(many[0], many[1])
    plugin = type(model._bundle(len(angles)).exp_phase)
    monkeypatch.setattr(plugin, "announce", lambda self, b: None)     # read back from the device
    read_back = [model.render_profiles(p, angles, spp=16, seed=s) for p, s in requests]
    assert all(np.array_equal(a, b) for a, b in zip(read_back, one))
    assert model.render_profiles_many([], angles, spp=16) == []
    with pytest.raises(ModelParameterError, match="seed"):
        model.render_profiles_many([(requests[0][0], -1)], angles, spp=16)
    with pytest.raises(ModelParameterError, match="2 coefficients announced for a phase function of degree 3"):
        monkeypatch.undo()
        model._bundle(len(angles)).exp_phase.announce([0.1, 0.2])


def test_new_angles_and_parameters_reuse_compiled_kernels() -> None:
    import drjit as dr

    # Dr.Jit fuses whatever is still queued (lazy work an earlier test left behind) into the
    # next kernel it launches; such a fused kernel is new to the cache whatever the render
    # does (seen in CI: one 5948-op miss, and after an eval of the queue first, once more a
    # 5898-op miss in session 26 on a loaded machine). So two different warm-up renders go
    # first; the render that is checked is the third, the steady state of a fit's loop.
    dr.eval()
    dr.sync_thread()
    model = _model("exp3")
    model.render_profiles({"sigma_t": 2.0, "albedo": 0.8, "phase.b1": 1.0}, [30.0, 60.0, 120.0], spp=16, seed=1)
    model.render_profiles({"sigma_t": 2.5, "albedo": 0.7, "phase.b1": 0.5, "phase.b3": 0.2},
                          [35.0, 70.0, 140.0], spp=16, seed=3)
    dr.eval()
    dr.sync_thread()
    dr.kernel_history()  # drain
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        model.render_profiles({"sigma_t": 3.0, "albedo": 0.6, "phase.b1": -2.0, "phase.b3": 0.5},
                              [25.0, 80.0, 160.0], spp=16, seed=2)
        history = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    jit = [k for k in history if str(k.get("type", "")).endswith("JIT")]
    assert jit, "no kernel launched"
    assert all(k.get("cache_hit") for k in jit), [k.get("operation_count") for k in jit if not k.get("cache_hit")]


def test_albedo_and_phase_gradients_match_finite_differences() -> None:
    model = _model("exp3", max_depth=16)
    p = {"sigma_t": 2.0, "albedo": 0.8, "phase.b1": 1.5, "phase.b2": 0.5, "phase.b3": 0.2}
    angles = [40.0, 140.0]
    cot = np.random.default_rng(0).random((2, N_PIX)) + 0.5
    grads = model.vjp(p, angles, cot, spp=4096, seed=13)

    def fd(name: str, h: float) -> float:
        vals = []
        for sign in (-1, 1):
            q = dict(p)
            q[name] += sign * h
            vals.append((model.render_profiles(q, angles, spp=8192, seed=14) * cot).sum())
        return (vals[1] - vals[0]) / (2 * h)

    assert grads["albedo"] == pytest.approx(fd("albedo", 0.05), rel=0.03)
    assert grads["phase.b1"] == pytest.approx(fd("phase.b1", 0.3), rel=0.15, abs=0.02 * abs(grads["albedo"]))


def test_one_sided_jacobians_average_to_the_central_one_and_turn_at_a_bound() -> None:
    """With common random numbers, a forward and a backward difference against the same
    seed's render average to exactly the central difference; at the upper bound of albedo
    the forward difference steps down instead (and the backward one up at sigma_t's lower)."""
    model = _model("exp3", max_depth=16)
    p = {"sigma_t": 2.0, "albedo": 0.8, "phase.b1": 1.5, "phase.b2": 0.5, "phase.b3": 0.2}
    angles = [40.0, 140.0]
    names = ["sigma_t", "albedo", "phase.b1"]
    steps = {"sigma_t": 0.1, "albedo": 0.05, "phase.b1": 0.3}
    base = model.render_profiles(p, angles, spp=64, seed=5)
    central = model.jacobian(p, angles, names, spp=64, seed=5, steps=steps)
    fwd = model.jacobian(p, angles, names, spp=64, seed=5, steps=steps, base_profiles=base)
    bwd = model.jacobian(p, angles, names, spp=64, seed=5, steps=steps, base_profiles=base, backward=True)
    for n in names:
        assert np.abs(fwd[n] - bwd[n]).max() > 1e-6 * np.abs(central[n]).max()   # not the same difference
        np.testing.assert_allclose(0.5 * (fwd[n] + bwd[n]), central[n], rtol=1e-9,
                                   atol=1e-12 * np.abs(central[n]).max())
    # At albedo's upper bound (1) a forward step is impossible: it steps down, as the backward one.
    top = {**p, "albedo": 1.0}
    base_top = model.render_profiles(top, angles, spp=64, seed=5)
    up = model.jacobian(top, angles, ["albedo"], spp=64, seed=5, steps=steps, base_profiles=base_top)
    down = model.jacobian(top, angles, ["albedo"], spp=64, seed=5, steps=steps, base_profiles=base_top,
                          backward=True)
    np.testing.assert_allclose(up["albedo"], down["albedo"], rtol=1e-12)
    assert np.all(np.isfinite(up["albedo"])) and up["albedo"].sum() > 0    # more albedo, more light
    # Near sigma_t's lower bound (0, open) a backward step turns up instead.
    thin = {**p, "sigma_t": 1e-9}
    base_thin = model.render_profiles(thin, angles, spp=64, seed=5)
    back = model.jacobian(thin, angles, ["sigma_t"], spp=64, seed=5, steps={"sigma_t": 0.1},
                          base_profiles=base_thin, backward=True)
    fwd_thin = model.jacobian(thin, angles, ["sigma_t"], spp=64, seed=5, steps={"sigma_t": 0.1},
                              base_profiles=base_thin)
    np.testing.assert_allclose(back["sigma_t"], fwd_thin["sigma_t"], rtol=1e-12)


def test_sigma_t_gradient_matches_analytic_single_scattering(single_model: ForwardModel) -> None:
    angles = [40.0, 140.0]
    cot = np.random.default_rng(1).random((2, N_PIX)) + 0.5
    p = {"sigma_t": 2.0, "albedo": 0.8}
    grads = single_model.vjp(p, angles, cot, spp=8192, seed=15)

    def ref(st: float) -> np.ndarray:
        return np.array([single_scattering_profile(st, 0.8, 1.0, isotropic_eval, a, BEAM_R, PITCH, N_PIX, PITCH)
                         for a in angles])

    h = 0.01
    expected = ((ref(2 + h) - ref(2 - h)) * cot).sum() / (2 * h)
    assert single_model.derivative_kind("sigma_t") == "ad"
    assert grads["sigma_t"] == pytest.approx(expected, rel=0.05)
    assert grads["albedo"] == pytest.approx((ref(2.0) * cot).sum() / 0.8, rel=0.02)


def test_geometry_pixel_mapping() -> None:
    g = RigGeometry(thickness_mm=1.2, magnification=0.5)
    assert g.pixel_mm == pytest.approx(0.04)
    w = g.profile_window()
    assert (w.col0, w.col1, w.row0, w.row1) == (0, 512, 256, 257)
    x = g.pixel_x_mm(g.window((255, 257)))
    assert x == pytest.approx([-0.02, 0.02])


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: RigGeometry(thickness_mm=0.0), "thickness_mm"),
        (lambda: RigGeometry(thickness_mm=-1.0), "thickness_mm"),
        (lambda: RigGeometry(thickness_mm=1.0, magnification=float("nan")), "magnification"),
        (lambda: _model("exp2", extensions=["fog"]), "fog"),
        (lambda: _model("poly3"), "poly3"),
    ],
)
def test_bad_construction_is_refused(make, match: str) -> None:
    with pytest.raises(ModelParameterError, match=match):
        make()


@pytest.mark.parametrize(
    ("params", "match"),
    [
        ({"sigma_t": -1.0}, "sigma_t"),
        ({"sigma_t": 0.0}, "sigma_t"),
        ({"albedo": float("nan")}, "albedo"),
        ({"albedo": 1.5}, "albedo"),
        ({"phase.b4": 1.0}, "phase.b4"),
        ({"refractive_boundary.n": 0.9}, "refractive_boundary.n"),
        ({"lens_blur.core_sigma_px": 1.0}, "lens_blur"),
    ],
)
def test_bad_parameters_are_refused(single_model: ForwardModel, params: dict, match: str) -> None:
    model = single_model
    if "refractive_boundary.n" in params:
        model = _model("exp0", extensions=["refractive_boundary"])
    with pytest.raises(ModelParameterError, match=match.replace(".", r"\.")):
        model.render_profiles(params, [30.0], spp=4, seed=0)


def test_bad_call_arguments_are_refused(single_model: ForwardModel) -> None:
    with pytest.raises(ModelParameterError, match="angle"):
        single_model.render_profiles({}, [float("nan")], spp=4)
    with pytest.raises(ModelParameterError, match="spp"):
        single_model.render_profiles({}, [30.0], spp=0)
    with pytest.raises(ModelParameterError, match="cotangent"):
        single_model.vjp({}, [30.0], np.ones((2, N_PIX)), spp=4)


def test_full_frame_band_has_spot_on_the_profile_row() -> None:
    g = RigGeometry(thickness_mm=1.0, sensor_px=(24, 24), magnification=0.4)
    model = ForwardModel(g, BeamProfile.disk(0.2), phase="exp0")
    img = model.render({"sigma_t": 3.0, "albedo": 0.9}, [150.0], rows=(0, 24), columns=(0, 24), spp=64, seed=1)[0]
    assert img.shape == (24, 24)
    rows = img.sum(axis=1)
    assert abs(int(np.argmax(rows)) + 0.5 - 12) <= 1.5  # the beam is centred on the image centre
    assert math.isfinite(float(img.sum())) and img.sum() > 0


@pytest.mark.parametrize("phi", [30.0, 150.0])
def test_albedo_one_index_matched_conserves_energy(phi: float) -> None:
    """Reflected + transmitted = incident: with albedo 1 every photon that interacts leaves
    the slab, so the scattered flux through a sphere around it (an `irradiancemeter`, the
    same beam emitter and integrator as the model) is P (1 - exp(-sigma_t d / |cos phi|));
    the unscattered part of the beam is the rest."""
    from estimate.mitsuba_env import init_mitsuba

    mi = init_mitsuba("llvm_ad_mono")
    T = mi.ScalarTransform4f
    d, hw, rs, sigma_t = 1.0, 4.0, 6.0, 1.0
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "rig_prbvolpath", "max_depth": 1000, "rr_depth": 1000},
        "slab": {"type": "cube", "to_world": T().translate([0, 0, -d / 2]).scale([hw, hw, d / 2]),
                 "bsdf": {"type": "null"},
                 "interior": {"type": "homogeneous", "sigma_t": sigma_t, "albedo": 1.0,
                              "phase": {"type": "exponential_phase", "degree": 2, "b1": 1.5, "b2": 0.5}}},
        "beam": {"type": "collimated_beam", "angle_deg": phi, "thickness": d},
        "meter": {"type": "sphere", "radius": rs, "flip_normals": True, "bsdf": {"type": "null"},
                  "sensor": {"type": "irradiancemeter",
                             "film": {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"},
                                      "pixel_format": "luminance"}}},
    })
    scene.emitters()[0].set_profile(BeamProfile.gaussian(0.5, power=1.0))
    # the meter reports the mean irradiance over the sphere: flux = value * area
    flux = np.array([float(np.array(mi.render(scene, sensor=scene.sensors()[0], spp=2**20, seed=s)).ravel()[0])
                     for s in range(4)]) * 4 * math.pi * rs**2
    expected = 1.0 - math.exp(-sigma_t * d / abs(math.cos(math.radians(phi))))
    stderr = flux.std(ddof=1) / math.sqrt(flux.size)
    assert stderr < 0.02 * expected
    assert abs(flux.mean() - expected) < max(4 * stderr, 0.01 * expected)


def test_mitsuba_env_refuses_llvm_15_and_16_without_aborting(tmp_path) -> None:
    import subprocess
    import sys

    fake = tmp_path / "libLLVM-15.so.1"
    fake.write_bytes(b"")
    code = ("from estimate.mitsuba_env import init_mitsuba, MitsubaSetupError\n"
            "try:\n    init_mitsuba('llvm_ad_mono')\nexcept MitsubaSetupError as e:\n    print('refused:', e)\n")
    env = {**__import__("os").environ, "DRJIT_LIBLLVM_PATH": str(fake)}
    out = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True, env=env, timeout=60,
                         cwd=str(__import__("pathlib").Path(__file__).resolve().parents[1]))
    assert out.returncode == 0, out.stderr
    assert "refused:" in out.stdout and "LLVM 15" in out.stdout


def test_mitsuba_variant_choice(monkeypatch) -> None:
    from estimate import mitsuba_env

    monkeypatch.setenv("RIG_MITSUBA_VARIANT", "llvm_ad_mono")
    assert mitsuba_env.default_variant() == "llvm_ad_mono"
    monkeypatch.delenv("RIG_MITSUBA_VARIANT")
    assert mitsuba_env.default_variant() in ("llvm_ad_mono", "cuda_ad_mono")
    assert mitsuba_env.find_libllvm() is None or "19" in mitsuba_env.find_libllvm()


def test_models_share_a_few_live_scenes_and_a_dropped_scene_renders_the_same() -> None:
    """Dr.Jit traces a virtual call once for every live instance of its class, so every
    scene alive in the process slows every launch (session 50: a 256-spp bench render
    416 ms alone, 1046 ms beside 40 other models' scenes). The models share a cache of
    `MAX_LIVE_BUNDLES` scenes; one dropped from it is rebuilt and renders the same, and a
    linearization that still holds a dropped scene finishes its adjoint pass on it."""
    import estimate.forward as fw

    model = _model("exp3")
    p = {"sigma_t": 2.0, "albedo": 0.8, "phase.b1": 1.0}
    angles = [40.0, 120.0]
    before = model.render_profiles(p, angles, spp=32, seed=3)
    cot = np.linspace(-1.0, 1.0, before.size).reshape(before.shape)
    ref = model.linearize(p, angles, spp=32, seed=3).vjp(cot, fd_parameters=False)
    lin = model.linearize(p, angles, spp=32, seed=3)
    others = [_model("exp0", max_depth=2) for _ in range(fw.MAX_LIVE_BUNDLES + 2)]
    for o in others:
        o.render_profiles({"sigma_t": 1.0, "albedo": 0.5}, angles, spp=1, seed=0)
    assert fw.live_bundles() <= fw.MAX_LIVE_BUNDLES
    assert len(angles) not in model._bundles           # dropped from the cache ...
    assert lin.vjp(cot, fd_parameters=False) == pytest.approx(ref, rel=1e-4)  # ... but not from `lin`
    assert np.array_equal(model.render_profiles(p, angles, spp=32, seed=3), before)
    assert len(angles) in model._bundles
    # models gone hold no place in the cache
    del others
    gc.collect()
    model.render_profiles(p, angles, spp=1, seed=0)
    assert len(fw._live_bundles) == fw.live_bundles() <= fw.MAX_LIVE_BUNDLES
