"""Model extensions (estimate.extensions): neutral values, image-space operators and their
adjoints, scene extensions in renders, derivatives, and bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimate.beam import BeamProfile
from estimate.errors import ModelParameterError
from estimate.extensions import EXTENSIONS, ImageExtension, get_extension
from estimate.extensions.lens_blur import _weighted_profile, profile_weights, unblurred_y_shape
from estimate.extensions.refractive_boundary import omitted_fraction
from estimate.extensions.sensor_nonlinearity import apply_raw, true_fill
from estimate.forward import ForwardModel
from estimate.geometry import RigGeometry

N_PIX = 24
GEOM = RigGeometry(thickness_mm=1.0, sensor_px=(N_PIX, 1), magnification=0.4, image_center_px=(N_PIX / 2, 0.5))
BEAM = BeamProfile.gaussian(0.3)
BASE = {"sigma_t": 3.0, "albedo": 0.9}

IMAGE_CASES = {
    "lens_blur": {"core_sigma_px": 1.3, "tail_fraction": 0.05, "tail_scale_px": 6.0},
    "stray_light": {"offset": 0.01, "slope_per_mm": 0.002},
    # full well above the test images' values: no pixel sits on the clip's kink
    "sensor_nonlinearity": {"compression": 0.1, "full_well_radiance": 1.5},
}


def test_registry_has_the_stable_names() -> None:
    assert set(EXTENSIONS) == {"refractive_boundary", "lens_blur", "stray_light", "angle_offset",
                               "thickness_error", "beam_halo", "sensor_nonlinearity", "filter_bandwidth"}
    with pytest.raises(ModelParameterError, match="warp_drive"):
        get_extension("warp_drive")


@pytest.mark.parametrize("name", sorted(IMAGE_CASES))
@pytest.mark.parametrize("profile_only", [True, False])
def test_image_extension_neutral_adjoint_and_derivatives(name: str, profile_only: bool) -> None:
    ext = get_extension(name)
    assert issubclass(ext, ImageExtension)
    rng = np.random.default_rng(3)
    shape = (2, 1, 40) if profile_only else (2, 9, 40)
    img = rng.random(shape)
    neutral = {p.name: p.neutral for p in ext.parameters}
    assert np.allclose(ext.apply(img, neutral, pixel_mm=0.04, profile_only=profile_only), img)
    values = IMAGE_CASES[name]
    # adjoint of the linearisation: <J dx, y> = <dx, J^T y>
    dx = rng.normal(size=shape)
    y = rng.normal(size=shape)
    eps = 1e-6
    jdx = (ext.apply(img + eps * dx, values, pixel_mm=0.04, profile_only=profile_only)
           - ext.apply(img - eps * dx, values, pixel_mm=0.04, profile_only=profile_only)) / (2 * eps)
    jty = ext.vjp_input(img, y, values, pixel_mm=0.04, profile_only=profile_only)
    assert float((jdx * y).sum()) == pytest.approx(float((dx * jty).sum()), rel=1e-5)
    # parameter derivatives against a fine central difference
    derivs = ext.param_derivatives(img, values, pixel_mm=0.04, profile_only=profile_only)
    for p in ext.parameters:
        h = 1e-5 * max(1.0, abs(values[p.name]))
        hi, lo = dict(values), dict(values)
        hi[p.name] += h
        lo[p.name] -= h
        fd = (ext.apply(img, hi, pixel_mm=0.04, profile_only=profile_only)
              - ext.apply(img, lo, pixel_mm=0.04, profile_only=profile_only)) / (2 * h)
        assert np.allclose(derivs[p.name], fd, rtol=2e-3, atol=1e-6 * np.abs(fd).max() + 1e-12), p.name


def test_lens_blur_conserves_energy_and_spreads() -> None:
    ext = get_extension("lens_blur")
    img = np.zeros((1, 129, 201))  # the kernels (radius 64 px) fit inside
    img[0, 64, 100] = 1.0
    out = ext.apply(img, IMAGE_CASES["lens_blur"], pixel_mm=0.04, profile_only=False)
    assert out.sum() == pytest.approx(1.0, rel=1e-6)
    assert out[0, 64, 100] < 0.2 and out[0, 64, 130] > 0  # core and long tail
    prof = ext.apply(img[:, 64:65, :], IMAGE_CASES["lens_blur"], pixel_mm=0.04, profile_only=True)
    assert prof.sum() == pytest.approx(1.0, rel=1e-6)


def _separable_scene(width: int = 161) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A compact spot on a faint background, I(x, y) = a(x) g(y): (image (1, 129, W), a, g)."""
    x = np.arange(width)
    a = np.exp(-0.5 * ((x - width / 2) / 5.0) ** 2) + 0.02
    y = np.arange(-64, 65)
    g = np.exp(-0.5 * (y / 4.0) ** 2)
    return (g[:, None] * a[None, :])[None], a, g


def test_lens_blur_profile_with_the_recorded_y_shape_matches_the_2d_blur() -> None:
    ext = get_extension("lens_blur")
    values = {"core_sigma_px": 1.5, "tail_fraction": 0.02, "tail_scale_px": 20.0}
    full, a, g = _separable_scene()
    truth = ext.apply(full, values, pixel_mm=0.04, profile_only=False)[:, 64, :]
    row = a[None, None, :]
    h_true = np.broadcast_to((g / g[64])[None, :, None], (1, 129, a.size)).copy()
    # The recording is the blurred image: rows of a taller scene, so the +-64 rows around
    # the profile row hold the light blurred in from beyond them.
    y = np.arange(-128, 129)
    tall = np.exp(-0.5 * (y / 4.0) ** 2)[None, :, None] * a[None, None, :]
    blurred = ext.apply(tall, values, pixel_mm=0.04, profile_only=False)[0]
    assert np.allclose(blurred[128], truth[0], rtol=1e-6)
    h_rec = (blurred[64:193] / blurred[128])[None]
    lsf = ext.apply(row, values, pixel_mm=0.04, profile_only=True)[:, 0, :]
    shaped = ext.apply(row, values, pixel_mm=0.04, profile_only=True, y_shape=h_rec)[:, 0, :]
    as_recorded = _weighted_profile(row[:, 0], profile_weights(values, h_rec, recorded=False), False)
    # The LSF treats the spot as constant along y: too bright wherever the blur mixes rows.
    assert np.max(np.abs(lsf / truth - 1)) > 0.05
    # The recorded shape is the blurred spot's, too wide: 1.3 % too bright at the peak. Deblurred
    # along y it is within 0.4 % (the regularisation's price).
    assert np.max(np.abs(as_recorded / truth - 1)) > 0.01
    assert np.max(np.abs(shaped / truth - 1)) < 4e-3
    # With the unblurred image's own shape the profile blur is exact: the core is separable,
    # and the tail's line spread is the marginal of the very truncated 2D kernel (the
    # untruncated Lorentzian was up to 0.2 % off here, and 1-7 % in the bench's shoulders).
    exact = _weighted_profile(row[:, 0], profile_weights(values, h_true, recorded=False), False)
    assert np.max(np.abs(exact / truth - 1)) < 1e-10
    # An image constant along y: the 2D blur's row is the LSF's, exactly.
    flat_scene = np.broadcast_to(a[None, None, :], (1, 129, a.size))
    assert np.allclose(ext.apply(flat_scene, values, pixel_mm=0.04, profile_only=False)[:, 64, :], lsf,
                       rtol=1e-10, atol=0)
    # A recording without y structure (h = 1) deblurs to h = 1: exactly the LSF.
    flat = ext.apply(row, values, pixel_mm=0.04, profile_only=True, y_shape=np.ones((1, 129, a.size)))
    assert np.allclose(flat[:, 0, :], lsf, rtol=1e-9, atol=1e-15)


def test_the_recorded_y_shape_deblurs_to_the_unblurred_spot() -> None:
    values = {"core_sigma_px": 2.5, "tail_fraction": 0.0, "tail_scale_px": 20.0}
    y = np.arange(-64, 65)
    # A 3.75 px spot under a 2.5 px core reads sqrt(3.75^2 + 2.5^2) = 4.51 px wide.
    h_rec = np.exp(-0.5 * y ** 2 / (3.75 ** 2 + 2.5 ** 2))[None, :, None].repeat(3, axis=2)
    h = unblurred_y_shape(values, h_rec)
    assert np.max(np.abs(h[0, :, 0] - np.exp(-0.5 * (y / 3.75) ** 2))) < 0.02
    assert h[0, 64, 0] == pytest.approx(1.0)
    # No blur: the recording is the image.
    assert np.array_equal(unblurred_y_shape({**values, "core_sigma_px": 0.0}, h_rec), h_rec)
    # A profile row in a dark gap three rows wide is not a blurred maximum: the column keeps
    # its recorded shape rather than dividing by a deblurred centre at or below zero.
    dip = np.full((1, 129, 1), 4.0)
    dip[0, 63:66, 0] = 1.0
    assert np.array_equal(unblurred_y_shape(values, dip), dip)


def test_lens_blur_with_y_shape_adjoint_and_derivatives() -> None:
    ext = get_extension("lens_blur")
    values = IMAGE_CASES["lens_blur"]
    rng = np.random.default_rng(8)
    img = rng.random((2, 1, 40))
    h = rng.uniform(0.0, 1.5, (2, 129, 40))
    x = rng.normal(size=img.shape)
    c = rng.normal(size=img.shape)
    # linear in the image: <B x, c> = <x, B^T c>
    bx = ext.apply(x, values, pixel_mm=0.04, profile_only=True, y_shape=h)
    btc = ext.vjp_input(img, c, values, pixel_mm=0.04, profile_only=True, y_shape=h)
    assert float((bx * c).sum()) == pytest.approx(float((x * btc).sum()), rel=1e-10)
    derivs = ext.param_derivatives(img, values, pixel_mm=0.04, profile_only=True, y_shape=h)
    for p in ext.parameters:
        step = 1e-5 * max(1.0, abs(values[p.name]))
        hi, lo = dict(values), dict(values)
        hi[p.name] += step
        lo[p.name] -= step
        fd = (ext.apply(img, hi, pixel_mm=0.04, profile_only=True, y_shape=h)
              - ext.apply(img, lo, pixel_mm=0.04, profile_only=True, y_shape=h)) / (2 * step)
        assert np.allclose(derivs[p.name], fd, rtol=2e-3, atol=1e-6 * np.abs(fd).max() + 1e-12), p.name
    with pytest.raises(ValueError, match="y_shape"):
        ext.apply(img, values, pixel_mm=0.04, profile_only=True, y_shape=h[:1])


def test_the_true_fill_solves_the_merged_fill() -> None:
    g = np.linspace(0.0, 1.0, 11)
    for c in (0.0, 0.06, 0.12, 0.3):
        gm = g * (1.0 - c * g) ** 2
        assert np.allclose(true_fill(c, gm), g, atol=1e-9), c
    # A merged fill no true fill <= 1 explains at this compression: capped, finite.
    assert true_fill(0.3, np.array([0.9]))[0] == pytest.approx(1.0, abs=1e-12)


def test_sensor_nonlinearity_raw_and_hdr() -> None:
    x = np.linspace(0, 100_000, 11)
    y = apply_raw(x, 0.2, 100_000.0)
    assert y[0] == 0 and y[-1] == pytest.approx(80_000.0)
    assert np.all(np.diff(y) > 0)
    with pytest.raises(ModelParameterError, match="compression"):
        apply_raw(x, 0.4, 100_000.0)
    ext = get_extension("sensor_nonlinearity")
    prof = np.array([[[0.1, 0.5, 1.0, 2.0]]])
    out = ext.apply(prof, {"compression": 0.1, "full_well_radiance": 1.0}, pixel_mm=0.04, profile_only=True)
    assert out[0, 0, 0] == pytest.approx(0.1 * (1 - 0.1 * 0.01))
    assert out[0, 0, 3] == pytest.approx(2.0 * 0.9)


def test_refractive_boundary_bound_on_omitted_reflections() -> None:
    assert omitted_fraction(30.0, 1.45) < 1e-5
    assert omitted_fraction(150.0, 1.6) < 1e-4


@pytest.fixture(scope="module")
def base_model() -> ForwardModel:
    return ForwardModel(GEOM, BEAM, phase="exp1")


def test_neutral_extensions_leave_the_render_unchanged(base_model: ForwardModel) -> None:
    names = ["lens_blur", "stray_light", "angle_offset", "thickness_error", "beam_halo", "sensor_nonlinearity",
             "filter_bandwidth"]
    full = ForwardModel(GEOM, BEAM, phase="exp1", extensions=names)
    a = base_model.render_profiles({**BASE, "phase.b1": 1.0}, [40.0, 140.0], spp=256, seed=2)
    b = full.render_profiles({**BASE, "phase.b1": 1.0}, [40.0, 140.0], spp=256, seed=2)
    assert np.allclose(a, b, rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("name", sorted(n for n, e in EXTENSIONS.items() if e.neutral_is_identity))
@pytest.mark.parametrize("others", [(), ("stray_light",)])
def test_an_extension_said_to_be_an_identity_at_neutral_renders_bit_for_bit_as_without_it(name, others) -> None:
    """The screening shares one render as the secant base of every candidate that declares
    `neutral_is_identity` (`estimate.diagnose._screen`): at its neutral values such a model
    must render exactly what the model without it renders at the same seed, also with the
    beam map imaged through the lens (where a lens blur renders) and beside another effect."""
    _, frame = _camera_map({"core_sigma_px": 1.5, "tail_fraction": 0.02, "tail_scale_px": 20.0})
    p = {**BASE, "phase.b1": 1.0, **({"stray_light.offset": 0.001} if others else {})}
    for beam in (BEAM, frame):
        without = ForwardModel(GEOM, beam, phase="exp1", extensions=list(others))
        with_it = ForwardModel(GEOM, beam, phase="exp1", extensions=[*others, name])
        a = without.render_profiles(p, [40.0, 140.0], spp=32, seed=4)
        b = with_it.render_profiles(p, [40.0, 140.0], spp=32, seed=4)
        assert np.array_equal(a, b), (name, others, beam is frame)


@pytest.mark.parametrize("name", ["refractive_boundary"])
def test_a_scene_extension_that_samples_differently_at_neutral_does_not_claim_identity(name) -> None:
    """An index-matched boundary still draws its reflection decision: at neutral it agrees
    with the model without it only in the mean, so its screening secants need their own
    base render."""
    assert not EXTENSIONS[name].neutral_is_identity
    p = {**BASE, "phase.b1": 1.0}
    a = ForwardModel(GEOM, BEAM, phase="exp1").render_profiles(p, [40.0, 140.0], spp=32, seed=4)
    b = ForwardModel(GEOM, BEAM, phase="exp1", extensions=[name]).render_profiles(p, [40.0, 140.0], spp=32, seed=4)
    assert not np.array_equal(a, b)


def test_angle_offset_shifts_every_angle(base_model: ForwardModel) -> None:
    model = ForwardModel(GEOM, BEAM, phase="exp1", extensions=["angle_offset"])
    a = model.render_profiles({**BASE, "angle_offset.delta_deg": 4.0}, [40.0, 140.0], spp=256, seed=3)
    b = base_model.render_profiles(BASE, [44.0, 144.0], spp=256, seed=3)
    assert np.allclose(a, b, rtol=1e-5, atol=1e-9)


def test_thickness_error_scales_the_slab() -> None:
    model = ForwardModel(GEOM, BEAM, phase="exp1", extensions=["thickness_error"])
    thick = ForwardModel(RigGeometry(thickness_mm=1.25, sensor_px=(N_PIX, 1), magnification=0.4,
                                     image_center_px=(N_PIX / 2, 0.5)), BEAM, phase="exp1")
    a = model.render_profiles({**BASE, "thickness_error.e": 0.25}, [140.0], spp=2048, seed=4)
    b = thick.render_profiles(BASE, [140.0], spp=2048, seed=4)
    c = model.render_profiles(BASE, [140.0], spp=2048, seed=4)
    assert a.sum() == pytest.approx(b.sum(), rel=0.01)
    assert abs(a.sum() - c.sum()) > 0.05 * c.sum()  # back-lit: a thicker slab transmits less


def test_beam_halo_adds_light_and_its_gradient_matches_fd() -> None:
    model = ForwardModel(GEOM, BEAM, phase="exp1", extensions=["beam_halo"])
    p = {**BASE, "beam_halo.fraction": 0.05, "beam_halo.sigma_mm": 1.0}
    angles = [40.0, 140.0]
    with_halo = model.render_profiles(p, angles, spp=1024, seed=5)
    without = model.render_profiles({**p, "beam_halo.fraction": 0.0}, angles, spp=1024, seed=5)
    assert with_halo.sum() > without.sum()
    cot = np.random.default_rng(4).random((2, N_PIX))
    grads = model.vjp(p, angles, cot, spp=1024, seed=5)
    h = 0.01
    hi = model.render_profiles({**p, "beam_halo.fraction": 0.06}, angles, spp=1024, seed=5)
    lo = model.render_profiles({**p, "beam_halo.fraction": 0.04}, angles, spp=1024, seed=5)
    fd = ((hi - lo) * cot).sum() / (2 * h)
    assert grads["beam_halo.fraction"] == pytest.approx(fd, rel=0.03)
    hs = model.render_profiles({**p, "beam_halo.sigma_mm": 1.1}, angles, spp=1024, seed=5)
    ls = model.render_profiles({**p, "beam_halo.sigma_mm": 0.9}, angles, spp=1024, seed=5)
    fd_s = ((hs - ls) * cot).sum() / 0.2
    assert grads["beam_halo.sigma_mm"] == pytest.approx(fd_s, rel=0.1, abs=0.05 * abs(fd))


def test_image_parameters_in_vjp_and_jacobian() -> None:
    names = ["lens_blur", "stray_light", "sensor_nonlinearity"]
    model = ForwardModel(GEOM, BEAM, phase="exp1", extensions=names)
    p = {**BASE, "phase.b1": 1.0, "lens_blur.core_sigma_px": 1.0, "lens_blur.tail_fraction": 0.02,
         "stray_light.offset": 0.001, "sensor_nonlinearity.compression": 0.05,
         "sensor_nonlinearity.full_well_radiance": 0.05}
    angles = [40.0, 140.0]
    cot = np.random.default_rng(5).random((2, N_PIX))
    grads = model.vjp(p, angles, cot, spp=256, seed=6, fd_parameters=False)
    jac = model.jacobian(p, angles, ["stray_light.offset", "lens_blur.tail_fraction",
                                     "sensor_nonlinearity.compression"], spp=256, seed=6)
    for name, j in jac.items():
        assert grads[name] == pytest.approx(float((j * cot).sum()), rel=1e-3, abs=1e-9), name
    # the offset passes through the (compressive) sensor: slightly less than sum(cot)
    assert 0.8 * cot.sum() < grads["stray_light.offset"] <= cot.sum() * (1 + 1e-9)


def test_forward_model_blurs_profiles_with_the_recorded_y_shape() -> None:
    angles = [40.0, 140.0]
    rng = np.random.default_rng(9)
    shape = {a: rng.uniform(0.2, 1.0, (129, N_PIX)) for a in angles}
    plain = ForwardModel(GEOM, BEAM, phase="exp1", extensions=["lens_blur", "stray_light"])
    shaped = ForwardModel(GEOM, BEAM, phase="exp1", extensions=["lens_blur", "stray_light"],
                          profile_y_shape=shape)
    p = {**BASE, "phase.b1": 1.0, "lens_blur.core_sigma_px": 1.2, "lens_blur.tail_fraction": 0.05,
         "lens_blur.tail_scale_px": 5.0, "stray_light.offset": 0.001}
    material = {k: v for k, v in p.items() if not k.startswith(("lens_blur.", "stray_light."))}
    unblurred = ForwardModel(GEOM, BEAM, phase="exp1").render(material, angles, spp=64, seed=2)
    ext = get_extension("lens_blur")
    h = np.stack([shape[a] for a in angles])
    want = ext.apply(unblurred, ext.values(p), pixel_mm=GEOM.pixel_mm, profile_only=True, y_shape=h)[:, 0, :] + 0.001
    got = shaped.render_profiles(p, angles, spp=64, seed=2)
    assert np.allclose(got, want, rtol=1e-6, atol=1e-12)
    assert not np.allclose(got, plain.render_profiles(p, angles, spp=64, seed=2), rtol=1e-3)
    # an angle without a recorded shape gets h = 1, i.e. the line-spread function
    assert np.allclose(shaped.render_profiles(p, [75.0], spp=64, seed=2),
                       plain.render_profiles(p, [75.0], spp=64, seed=2), rtol=1e-9, atol=1e-15)
    # gradients of the blur's parameters agree with the model's own Jacobian
    cot = rng.random((2, N_PIX))
    grads = shaped.vjp(p, angles, cot, spp=64, seed=2, fd_parameters=False)
    jac = shaped.jacobian(p, angles, ["lens_blur.core_sigma_px", "lens_blur.tail_fraction"], spp=64, seed=2)
    for name, j in jac.items():
        assert grads[name] == pytest.approx(float((j * cot).sum()), rel=1e-3, abs=1e-9), name


def test_forward_model_compresses_profiles_with_the_merge_fill() -> None:
    angles = [40.0, 140.0]
    rng = np.random.default_rng(10)
    fill = {a: rng.uniform(0.0, 0.9, N_PIX) for a in angles}
    exts = ["stray_light", "sensor_nonlinearity"]
    filled = ForwardModel(GEOM, BEAM, phase="exp1", extensions=exts, profile_merge_fill=fill)
    p = {**BASE, "phase.b1": 1.0, "stray_light.offset": 0.001, "sensor_nonlinearity.compression": 0.04}
    material = {k: v for k, v in p.items() if not k.startswith(("stray_light.", "sensor_nonlinearity."))}
    plain = ForwardModel(GEOM, BEAM, phase="exp1").render_profiles(material, angles, spp=64, seed=2)
    g = np.stack([fill[a] for a in angles])
    got = filled.render_profiles(p, angles, spp=64, seed=2)
    assert np.allclose(got, (plain + 0.001) * (1.0 - 0.04 * true_fill(0.04, g)), rtol=1e-9, atol=1e-15)
    # an angle without a fill: every angle takes the full-well form
    full_well = ForwardModel(GEOM, BEAM, phase="exp1", extensions=exts)
    assert np.allclose(filled.render_profiles(p, [40.0, 75.0], spp=64, seed=2),
                       full_well.render_profiles(p, [40.0, 75.0], spp=64, seed=2), rtol=1e-12, atol=1e-15)
    # the compression's gradient agrees with the model's Jacobian and with -I d(c g(c))/dc
    cot = rng.random((2, N_PIX))
    grads = filled.vjp(p, angles, cot, spp=64, seed=2, fd_parameters=False)
    jac = filled.jacobian(p, angles, ["sensor_nonlinearity.compression", "stray_light.offset"], spp=64, seed=2)
    h = 1e-6
    dcg = ((0.04 + h) * true_fill(0.04 + h, g) - (0.04 - h) * true_fill(0.04 - h, g)) / (2 * h)
    assert np.all(dcg > g)   # the true fill grows with the compression
    assert np.allclose(jac["sensor_nonlinearity.compression"], -(plain + 0.001) * dcg, rtol=1e-4, atol=1e-12)
    for name, j in jac.items():
        assert grads[name] == pytest.approx(float((j * cot).sum()), rel=1e-5, abs=1e-12), name


def _camera_map(blur: dict[str, float] | None) -> tuple[BeamProfile, BeamProfile]:
    """A Gaussian beam (sigma 0.15 mm) sampled at GEOM's pixels, and the map a calibration
    frame gives of it: blurred by the lens's PSF, marked as imaged through the lens."""
    from scipy import signal

    from estimate.extensions.lens_blur import psf_2d

    true = BeamProfile.gaussian(0.3, pitch_mm=GEOM.pixel_mm)
    e = true.irradiance
    if blur is not None:
        e = signal.fftconvolve(e, psf_2d(blur), mode="same")
    n = e.shape[0]
    frame = BeamProfile.from_camera_image(e[::-1, :], GEOM.pixel_mm, ((n - 1) / 2, (n - 1) / 2))
    return true, frame


def test_deblurring_a_map_imaged_through_the_lens_restores_the_beam() -> None:
    from estimate.extensions.lens_blur import psf_2d

    blur = {"core_sigma_px": 1.5, "tail_fraction": 0.02, "tail_scale_px": 20.0}
    true, frame = _camera_map(blur)
    assert frame.through_lens and not true.through_lens
    assert frame.rms_width_mm() > 1.1 * true.rms_width_mm()  # the calibration frame reads wider
    back = frame.deblurred(psf_2d(blur))
    assert not back.through_lens and back.shape == frame.shape
    assert np.all(back.irradiance >= 0)
    # the crop lost the glare that fell outside it (1.2 % here); the beam it came from is restored
    assert frame.power() < 0.99 * true.power() and back.power() == pytest.approx(true.power(), rel=2e-3)
    assert back.rms_width_mm() == pytest.approx(true.rms_width_mm(), rel=0.02)
    peak = np.unravel_index(np.argmax(true.irradiance), true.shape)
    assert back.irradiance[peak] == pytest.approx(true.irradiance[peak], rel=0.03)
    # no blur: the map itself
    delta = psf_2d({"core_sigma_px": 0.0, "tail_fraction": 0.0, "tail_scale_px": 20.0})
    assert np.allclose(frame.deblurred(delta).irradiance, frame.irradiance, rtol=1e-9, atol=1e-12)
    with pytest.raises(ModelParameterError, match="odd square"):
        frame.deblurred(np.ones((4, 4)) / 16)


@pytest.mark.parametrize(("blur", "noise", "crop"), [
    ({"core_sigma_px": 1.5, "tail_fraction": 0.02, "tail_scale_px": 20.0}, 5e-5, 50),
    # the light bench's lens_blur-2 and its calibration map's noise (session 72)
    ({"core_sigma_px": 2.5, "tail_fraction": 0.05, "tail_scale_px": 20.0}, 1.5e-4, 58),
])
def test_deblurring_a_noisy_cropped_map_adds_no_halo(blur: dict[str, float], noise: float, crop: int) -> None:
    """The glare beyond the calibration crop and the map's pixel noise: neither may come
    back as light around the beam (a halo the diagnosis would then have to explain)."""
    from scipy import signal

    from estimate.extensions.lens_blur import psf_2d

    pitch, n = 0.0666667, 241
    x = (np.arange(n) - n // 2) * pitch
    xx, yy = np.meshgrid(x, x)
    beam = np.exp(-0.5 * (xx ** 2 + yy ** 2) / 0.25 ** 2)
    c, h = n // 2, crop // 2
    inner = (slice(c - h, c + h), slice(c - h, c + h))
    blurred = signal.fftconvolve(beam, psf_2d(blur), mode="same")[inner]
    noisy = blurred + np.random.default_rng(3).normal(0.0, noise * blurred.max(), blurred.shape)
    r = np.hypot(xx[inner], yy[inner])

    def beyond_1mm(e: np.ndarray) -> float:
        return float(e[r > 1.0].sum() / beam.sum())

    true_share = beyond_1mm(beam[inner])                    # 0.04 %
    assert beyond_1mm(blurred) > 15 * true_share               # the glare (0.7 % and more)
    clean = BeamProfile(blurred, pitch, 0.0, 0.0, through_lens=True).deblurred(psf_2d(blur))
    back = BeamProfile(np.clip(noisy, 0.0, None), pitch, 0.0, 0.0, through_lens=True).deblurred(psf_2d(blur))
    assert beyond_1mm(clean.irradiance) < 1.1 * true_share
    assert np.all(back.irradiance >= 0)
    # Wiener with zero padding left 6x the truth in the first case (0.23 %); clipping the
    # solution's negative samples 1.9x and 4.8x here (the positive half of its noise); their
    # deficit taken from their neighbours instead, 1.1x and 1.25x.
    assert beyond_1mm(back.irradiance) < 1.4 * true_share
    assert clean.power() == pytest.approx(beam.sum() * pitch ** 2, rel=1e-3)
    assert back.power() == pytest.approx(beam.sum() * pitch ** 2, rel=3e-4)   # clipped: +0.03 %, +0.17 %
    assert back.rms_width_mm() == pytest.approx(0.25, rel=5e-3)


def test_a_map_made_non_negative_keeps_its_sum_and_leaves_no_floor() -> None:
    """Zero-mean noise around a beam: made non-negative, the far field keeps about its true
    (zero) sum instead of the positive half of the noise, and the total is unchanged."""
    from estimate.beam import _nonnegative_locally

    rng = np.random.default_rng(0)
    x = rng.normal(0.0, 1.0, (58, 58))
    x[20:38, 20:38] += 50.0
    y = _nonnegative_locally(x)
    assert np.all(y >= 0) and y.sum() == pytest.approx(x.sum(), rel=1e-12)
    far = np.ones(x.shape, bool)
    far[12:46, 12:46] = False
    clipped_floor = float(np.clip(x[far], 0.0, None).sum())     # about 0.4 per sample
    assert abs(float(y[far].sum()) - float(x[far].sum())) < 0.15 * clipped_floor
    # under the beam the deficit is a small share of what is there
    assert y[24:34, 24:34].sum() == pytest.approx(x[24:34, 24:34].sum(), rel=0.02)


def test_a_model_with_lens_blur_lights_the_slab_with_the_map_deblurred() -> None:
    """A calibration frame images the beam through the same lens: a model that blurs the
    slab's image must not light it with the blurred map too, or the blur acts twice."""
    blur = {"core_sigma_px": 1.5, "tail_fraction": 0.02, "tail_scale_px": 20.0}
    _, frame = _camera_map(blur)
    exts = ["lens_blur", "stray_light"]
    model = ForwardModel(GEOM, frame, phase="exp1", extensions=exts)
    assert model.deblurs_beam and model.derivative_kind("lens_blur.core_sigma_px") == "fd"
    assert model.acts_in_image("lens_blur.tail_fraction") and not model.acts_in_image("sigma_t")
    p = {**BASE, "phase.b1": 1.0, **{f"lens_blur.{k}": v for k, v in blur.items()}, "stray_light.offset": 0.001}
    angles = [40.0, 140.0]
    from estimate.extensions.lens_blur import psf_2d

    plain_map = BeamProfile(frame.irradiance, frame.pitch_mm, frame.u0_mm, frame.v0_mm)
    by_hand = ForwardModel(GEOM, plain_map.deblurred(psf_2d(blur)), phase="exp1", extensions=exts)
    assert not by_hand.deblurs_beam
    got = model.render_profiles(p, angles, spp=64, seed=2)
    assert np.allclose(got, by_hand.render_profiles(p, angles, spp=64, seed=2), rtol=1e-6, atol=1e-12)
    # without blur the map is used as it is
    p0 = {**p, "lens_blur.core_sigma_px": 0.0, "lens_blur.tail_fraction": 0.0}
    base = ForwardModel(GEOM, plain_map, phase="exp1", extensions=["stray_light"])
    assert np.allclose(model.render_profiles(p0, angles, spp=64, seed=2),
                       base.render_profiles({k: v for k, v in p0.items() if not k.startswith("lens_blur.")},
                                            angles, spp=64, seed=2), rtol=1e-6, atol=1e-12)
    # the blur's derivatives include its action on the map: rendered differences, and the
    # reverse-mode gradient agrees with them
    names = ["lens_blur.core_sigma_px", "lens_blur.tail_fraction"]
    jac = model.jacobian(p, angles, names, spp=64, seed=2)
    image_only = by_hand.jacobian(p, angles, names, spp=64, seed=2)
    for n in names:
        assert not np.allclose(jac[n], image_only[n], rtol=0.05), n
    cot = np.random.default_rng(4).random((2, N_PIX))
    grads = model.vjp(p, angles, cot, spp=64, seed=2)
    for n in names:
        assert grads[n] == pytest.approx(float((jac[n] * cot).sum()), rel=1e-6), n
    # the map and the sensor must share their pixel for the PSF to apply to both
    coarse = BeamProfile(frame.irradiance, 2 * frame.pitch_mm, frame.u0_mm, frame.v0_mm, through_lens=True)
    with pytest.raises(ModelParameterError, match="pitch"):
        ForwardModel(GEOM, coarse, phase="exp1", extensions=exts).render_profiles(p, angles, spp=4, seed=0)


def test_the_light_engine_blurs_the_profile_row_along_y_by_lighting_the_slab_with_the_core_blurred_map() -> None:
    """The slab does not change along y, so an image row lit by the map blurred along v by
    the blur's core is the image blurred along y by the core: the light engine's profile row
    of a lens blur model equals the centre row of the rows around it blurred in 2D by the
    core, exactly (the same paths: blurring along v leaves the map's marginal in u, where
    the paths start, as it is). No y-shape is read for it."""
    from scipy import signal

    from estimate.extensions.lens_blur import psf_2d

    geom = RigGeometry(thickness_mm=1.0, sensor_px=(N_PIX, 33), magnification=0.4, image_center_px=(N_PIX / 2, 16.5))
    assert geom.pixel_mm == GEOM.pixel_mm
    blur = {"core_sigma_px": 1.2, "tail_fraction": 0.0, "tail_scale_px": 20.0}
    _, frame = _camera_map(blur)
    model = ForwardModel(geom, frame, phase="exp1", extensions=["lens_blur"], engine="light")
    assert model.core_blur_in_scene
    assert not ForwardModel(geom, frame, phase="exp1", extensions=["lens_blur"]).core_blur_in_scene  # camera engine
    p = {**BASE, "phase.b1": 1.0, **{f"lens_blur.{k}": v for k, v in blur.items()}}
    angles = [40.0, 140.0]
    row = model.render_profiles(p, angles, spp=64, seed=2)
    lit = model.beam_for(model.validate(p), single_row=True)
    flat = model.beam_for(model.validate(p))
    assert lit.power() == pytest.approx(flat.power(), rel=1e-9) and lit.irradiance.shape[0] > flat.irradiance.shape[0]
    y0, r = geom.profile_window().row0, 6
    plain = ForwardModel(geom, flat, phase="exp1", engine="light")
    rows = plain.render({**BASE, "phase.b1": 1.0}, angles, rows=(y0 - r, y0 + r + 1), spp=64, seed=2)
    want = signal.fftconvolve(rows, psf_2d(blur)[None], mode="same", axes=(-2, -1))[:, r, :]
    assert np.abs(row - want).max() <= 1e-5 * want.max()
    # the rows of a taller window are blurred in 2D in the image, lit by the map itself
    tall = model.render(p, angles, rows=(y0 - r, y0 + r + 1), spp=64, seed=2)
    assert np.abs(tall[:, r, :] - want).max() <= 1e-5 * want.max()


def test_with_the_core_in_the_scene_the_profile_weights_keep_the_core_line_spread_and_the_tail_on_the_image() -> None:
    """`core_in_scene`: the row holds I(x', y0) E_G[h] already, so the core's weight is its
    line spread alone and the tail's is divided by E_G[h]: applied to that row, the weights
    give what the weights without it give applied to I(x', y0)."""
    from estimate.extensions.lens_blur import core_line_spread

    rng = np.random.default_rng(5)
    values = {"core_sigma_px": 1.5, "tail_fraction": 0.05, "tail_scale_px": 8.0}
    radius = 64
    dy = np.arange(-radius, radius + 1)[:, None]
    widths = rng.uniform(3.0, 9.0, size=(2, 1, 40))
    h = np.exp(-0.5 * (dy[None] / widths) ** 2)          # unblurred y-shapes, (N, 2 R + 1, W)
    row = rng.uniform(0.5, 2.0, size=(2, 40))            # I(x', y0)
    core = core_line_spread(values, radius)
    lit = row * np.einsum("d,ndw->nw", core, h)          # the row lit by the core-blurred map
    plain = _weighted_profile(row, profile_weights(values, h, recorded=False), False)
    in_scene = _weighted_profile(lit, profile_weights(values, h, recorded=False, core_in_scene=True), False)
    assert np.allclose(in_scene, plain, rtol=1e-12, atol=0.0)


def test_screening_renders_the_lens_blur_where_the_map_was_imaged_through_the_lens() -> None:
    from estimate.screening import PROBES, candidate_columns, image_columns

    blur = {"core_sigma_px": 1.5, "tail_fraction": 0.02, "tail_scale_px": 20.0}
    _, frame = _camera_map(blur)
    p = {**BASE, "phase.b1": 1.0}
    angles = [40.0, 140.0]
    model = ForwardModel(GEOM, frame, phase="exp1", extensions=["lens_blur"])
    base = model.render_profiles(p, angles, spp=64, seed=3)
    cols = candidate_columns(model, p, angles, base, ["lens_blur"], spp=64, seed=3)["lens_blur"]
    want = [model.render_profiles({**p, **probe}, angles, spp=64, seed=3) - base for probe in PROBES["lens_blur"]]
    assert len(cols) == 2 and all(np.allclose(c, w, rtol=1e-9, atol=1e-15) for c, w in zip(cols, want))
    # where the map is the beam itself (an analytic map), the blur acts on the base render
    analytic = ForwardModel(GEOM, BEAM, phase="exp1", extensions=["lens_blur"])
    b2 = analytic.render_profiles(p, angles, spp=64, seed=3)
    got = candidate_columns(analytic, p, angles, b2, ["lens_blur"], spp=64, seed=3)["lens_blur"]
    assert all(np.allclose(c, w) for c, w in zip(got, image_columns("lens_blur", b2, GEOM.pixel_mm, None)))


def test_a_band_keeps_the_random_numbers_of_one_wavelength(base_model: ForwardModel) -> None:
    """Every band node is rendered with the render's own random numbers: at spread 0 the
    band model renders the single-wavelength image sample for sample (common random numbers
    with the model without it, as a diagnosis's fixed-seed refits compare them), and at a
    spread its Monte Carlo variance stays about that of one wavelength (independent seeds a
    node gave 0.35 of it, which a fixed-seed refit took for an improvement)."""
    band = ForwardModel(GEOM, BEAM, phase="exp1", extensions=["filter_bandwidth"])
    p = {**BASE, "phase.b1": 1.0}
    angles = [30.0, 150.0]
    np.testing.assert_allclose(band.render_profiles(p, angles, spp=64, seed=5),
                               base_model.render_profiles(p, angles, spp=64, seed=5), rtol=1e-5, atol=0)
    q = {**p, "filter_bandwidth.spread": 0.3}
    # At spread 0 the nodes would render one image three times: one render does.
    assert len(band._bands(band.validate(p))) == 1 and len(band._bands(band.validate(q))) == 3
    a = np.array([band.render_profiles(q, angles, spp=64, seed=s) for s in range(24)])
    b = np.array([base_model.render_profiles(p, angles, spp=64, seed=100 + s) for s in range(24)])
    ratio = float(np.mean(a.var(axis=0, ddof=1)) / np.mean(b.var(axis=0, ddof=1)))
    assert 0.7 < ratio < 1.4


def test_a_filter_spread_changes_the_image_and_has_a_finite_jacobian() -> None:
    # (Spread 0 against one wavelength: test_a_band_keeps_the_random_numbers_of_one_wavelength.)
    model = ForwardModel(GEOM, BEAM, phase="exp1", extensions=["filter_bandwidth"])
    a = model.render_profiles({**BASE, "phase.b1": 1.0}, [40.0], spp=4096, seed=7)
    c = model.render_profiles({**BASE, "phase.b1": 1.0, "filter_bandwidth.spread": 0.5}, [40.0], spp=4096, seed=7)
    assert not np.allclose(a, c)
    jac = model.jacobian({**BASE, "filter_bandwidth.spread": 0.3}, [40.0], ["filter_bandwidth.spread"],
                         spp=512, seed=7)
    assert np.all(np.isfinite(jac["filter_bandwidth.spread"]))


@pytest.mark.parametrize(
    ("ext", "params", "match"),
    [
        ("beam_halo", {"beam_halo.fraction": -0.1}, "beam_halo.fraction"),
        ("beam_halo", {"beam_halo.sigma_mm": 0.0}, "beam_halo.sigma_mm"),
        ("lens_blur", {"lens_blur.tail_fraction": float("nan")}, "lens_blur.tail_fraction"),
        ("stray_light", {"stray_light.offset": -1.0}, "stray_light.offset"),
        ("thickness_error", {"thickness_error.e": -1.0}, "thickness_error.e"),
        ("refractive_boundary", {"refractive_boundary.n": 0.99}, "refractive_boundary.n"),
        ("angle_offset", {"angle_offset.delta_deg": float("nan")}, "angle_offset.delta_deg"),
    ],
)
def test_bad_extension_parameters(ext: str, params: dict, match: str) -> None:
    model = ForwardModel(GEOM, BEAM, phase="exp0", extensions=[ext])
    with pytest.raises(ModelParameterError, match=match.replace(".", r"\.")):
        model.validate(params)


def test_additive_parameters_and_their_columns() -> None:
    """Stray light adds offset + slope * x whatever the scene: its parameters are additive,
    with exact columns and no render, unless a later effect (sensor compression) bends it."""
    model = ForwardModel(GEOM, BEAM, phase="exp1", extensions=["lens_blur", "stray_light"])
    assert model.additive_parameters() == ["stray_light.offset", "stray_light.slope_per_mm"]
    p = {**BASE, "phase.b1": 1.0, "lens_blur.core_sigma_px": 1.0, "stray_light.offset": 0.003}
    cols = model.additive_columns(p, 2)
    jac = model.jacobian(p, [40.0, 140.0], list(cols), spp=64, seed=2)
    for name, c in cols.items():
        assert c.shape == (2, N_PIX)
        assert c == pytest.approx(jac[name], rel=1e-9, abs=1e-12), name
    assert np.allclose(cols["stray_light.offset"], 1.0)
    bent = ForwardModel(GEOM, BEAM, phase="exp1", extensions=["stray_light", "sensor_nonlinearity"])
    assert bent.additive_parameters() == []
    with pytest.raises(ModelParameterError, match="not an additive parameter"):
        bent.additive_columns(p, 2, ["stray_light.offset"])


@pytest.mark.parametrize("c", [0.03, 0.12])
def test_the_merge_fill_reproduces_the_merge_of_a_compressed_bracket(c: float) -> None:
    """A compressing sensor read through a bracket and the HDR merge: the merged radiance is
    L (1 - c g) with g the merge's mean squared fill (`merge_fill_from_rows`, computed from
    the merged image itself), a sawtooth along the profile that no function of L alone
    (the full-well form) follows. At 12 % the clipped wells read below the noise model's
    saturation level: the merge finds their plateau, and the fill replays the merge at the
    level it used (what the stack's record keeps)."""
    from fakes import TEST_SENSOR

    from capture.hdr import MatchedDarks, NoiseModel, merge_hdr
    from drivers.interfaces import ROI, Frame
    from estimate.problem import merge_fill_from_rows

    s = TEST_SENSOR
    noise = NoiseModel.from_sensor(s)
    fw = s.full_well_e
    times = [0.001 * 4 ** k for k in range(7)]
    x = np.arange(300)
    lum = 5e3 + 2e7 * np.exp(-0.5 * ((x - 150) / 20.0) ** 2)     # e-/s, 3.6 decades
    truth = np.tile(lum, (9, 1))                                  # uniform along the column

    def frame(t: float, lit: bool) -> np.ndarray:
        q = np.clip(truth * t, 0.0, fw) if lit else np.zeros_like(truth)
        e = apply_raw(q, c, fw) + s.dark_current_e_per_s * t
        return np.clip(np.rint(e / s.gain_e_per_adu + s.bias_adu), 0, s.adc_max).astype(np.uint16)

    darks = MatchedDarks.from_frames([Frame(frame(t, False), t, True, -20.0, 0, t, ROI()) for t in times
                                      for _ in range(2)], noise)
    res = merge_hdr(np.stack([frame(t, True) for t in times]), times, darks, noise)
    assert (res.saturation_adu == noise.saturation_adu) == (c < 0.05)
    merged = res.radiance.astype(np.float64)
    # From the stack's record of the exposures the merge kept (exact), and, at 3 %, replayed
    # from the merged radiance (the compression too small to move a sample across the level).
    g = merge_fill_from_rows(merged, 4, (0, x.size), times, noise, fw, n_valid=res.n_valid)
    if c < 0.05:
        assert np.array_equal(merge_fill_from_rows(merged, 4, (0, x.size), times, noise, fw), g)
    ratio = merged[4] / lum
    # The extension's model of it: the fill g_m of the merged radiance is that of L (1 - c g),
    # solved for g at the compression (`true_fill`; at 12 % taking g_m as it is was 1.7 % off).
    model = get_extension("sensor_nonlinearity").apply(lum[None], {"compression": c, "full_well_radiance": 1.0},
                                                       pixel_mm=0.04, profile_only=True, merge_fill=g[None])[0]
    assert np.max(np.abs(merged[4] / model - 1.0)) < 1e-3
    assert np.allclose(1.0 - model / lum, c * true_fill(c, g), rtol=1e-12)
    assert 0.0 < g.min() and g.max() < 1.0
    # Not a function of L: a brighter pixel can be less compressed than a dimmer one.
    order = np.argsort(lum)
    loss = (1.0 - ratio)[order]
    assert np.max(np.maximum.accumulate(loss) - loss) > 0.3 * c


@pytest.mark.parametrize("c", [0.06, 0.12])
def test_the_calibration_gain_restores_the_power_of_a_compressed_beam_frame(c: float, tmp_path) -> None:
    """The beam calibration reads its frame through the same compressing sensor: the read
    power is low by about c times the map's mean fill (the bench: 0.73 % at c = 0.06). From
    the calibration's kept light frames `estimate.problem` finds how many exposures its
    merge kept per pixel (`_beam_kept_counts`, the merge's own count and level), and the
    power shares and fills give `calibration_gain`, which restores the true power. Replayed
    from the map alone (no frames), the uncompressed prediction keeps too few exposures
    where the compression pulled a sample below the level, and falls short."""
    from fakes import TEST_SENSOR

    from capture.exr_io import write_frames
    from capture.hdr import MatchedDarks, NoiseModel, merge_hdr
    from drivers.interfaces import ROI, Frame
    from estimate.extensions.base import BeamFill
    from estimate.extensions.sensor_nonlinearity import calibration_gain
    from estimate.problem import _beam_kept_counts, merge_fill_from_rows

    s = TEST_SENSOR
    noise = NoiseModel.from_sensor(s)
    fw = s.full_well_e
    times = [0.2 * 4 ** k for k in range(3)]                       # the bench's beam bracket
    yy, xx = np.mgrid[0:40, 0:48]
    # e-/s; the shortest exposure fills the peak's well to 0.36, as on the bench
    beam = 0.36 * fw / times[0] * np.exp(-0.5 * ((xx - 23.6) ** 2 + (yy - 20.3) ** 2) / 1.6 ** 2)

    def frame(t: float, lit: bool) -> np.ndarray:
        q = np.clip(beam * t, 0.0, fw) if lit else np.zeros_like(beam)
        e = apply_raw(q, c, fw) + s.dark_current_e_per_s * t
        return np.clip(np.rint(e / s.gain_e_per_adu + s.bias_adu), 0, s.adc_max).astype(np.uint16)

    roi = ROI(x=100, y=200, width=48, height=40)
    light = [Frame(frame(t, True), t, False, -20.0, 0, t, roi) for t in times]
    dark = [Frame(frame(t, False), t, True, -20.0, 0, t, roi) for t in times for _ in range(2)]
    res = merge_hdr(np.stack([f.data for f in light]), times, MatchedDarks.from_frames(dark, noise), noise)
    write_frames(tmp_path / "beam_g.npz", light + dark)
    # the map: a crop of the merged frame at full-sensor origin (105, 204)
    read = np.clip(res.radiance.astype(np.float64), 0.0, None)[4:36, 5:43]
    kept = _beam_kept_counts(tmp_path / "beam_g.npz", (105.0, 204.0), read.shape, noise)
    assert kept is not None
    assert np.array_equal(kept[0], res.n_valid[4:36, 5:43]) and kept[1] == res.saturation_adu
    assert _beam_kept_counts(tmp_path / "missing.npz", (105.0, 204.0), read.shape, noise) is None
    assert _beam_kept_counts(tmp_path / "beam_g.npz", (90.0, 204.0), read.shape, noise) is None   # off the frames

    def gain(n_valid: np.ndarray | None) -> tuple[float, BeamFill]:
        nz = noise if n_valid is None else NoiseModel(**{**noise.to_dict(), "saturation_adu": kept[1]})
        fill = np.stack([merge_fill_from_rows(read, j, (0, read.shape[1]), times, nz, fw, n_valid=n_valid)
                         for j in range(read.shape[0])])
        lit = read > 0
        bf = BeamFill(weights=read[lit] / read.sum(), fill=fill[lit])
        return calibration_gain(c, bf), bf

    true_power = beam[4:36, 5:43].sum()
    short = 1.0 - read.sum() / true_power
    assert 0.05 * c < short < 0.5 * c                # c times the map's mean fill
    k, bf = gain(kept[0])
    assert read.sum() * k == pytest.approx(true_power, rel=1e-4)
    # what estimate.problem builds from a calibration: the same fills, and where they came from
    from types import SimpleNamespace

    from estimate.problem import _beam_fill
    built = _beam_fill(noise, SimpleNamespace(full_well_e=fw), read, times, kept)
    assert built is not None and built.source == "kept frames" and built.pixels is read
    assert calibration_gain(c, built) == pytest.approx(k, rel=1e-12)
    replayed = _beam_fill(noise, SimpleNamespace(full_well_e=fw), read, times, None)
    assert replayed is not None and replayed.source == "replayed"
    assert _beam_fill(None, SimpleNamespace(full_well_e=fw), read, times, kept) is None
    if c == 0.06:
        # here the replay misses exposures the compression kept below the level (at 12 % this
        # beam's samples happen to sit clear of it, and the replay comes within 4e-5)
        k_replayed, _ = gain(None)
        assert read.sum() * k_replayed / true_power - 1 < -2e-3
    assert calibration_gain(0.0, bf) == 1.0
    h = 1e-7
    assert (calibration_gain(h, bf) - 1.0) / h == pytest.approx(float(np.sum(bf.weights * bf.fill)), rel=1e-3)


def test_forward_model_scales_by_the_calibration_gain_with_a_beam_fill() -> None:
    """With the beam calibration's fills the compressed model is brighter by
    `calibration_gain(c)` in every window, the compression's gradient carries the gain's
    derivative, and without the compression the fills change nothing."""
    from estimate.extensions.base import BeamFill
    from estimate.extensions.sensor_nonlinearity import calibration_gain

    angles = [40.0, 140.0]
    rng = np.random.default_rng(11)
    fill = {a: rng.uniform(0.0, 0.9, N_PIX) for a in angles}
    w = rng.random(200)
    bf = BeamFill(weights=w / w.sum(), fill=rng.uniform(0.0, 0.7, 200))
    exts = ["sensor_nonlinearity"]
    p = {**BASE, "phase.b1": 1.0, "sensor_nonlinearity.compression": 0.05}
    plain = ForwardModel(GEOM, BEAM, phase="exp1", extensions=exts, profile_merge_fill=fill)
    gained = ForwardModel(GEOM, BEAM, phase="exp1", extensions=exts, profile_merge_fill=fill, beam_fill=bf)
    k = calibration_gain(0.05, bf)
    assert k > 1.0
    assert np.allclose(gained.render_profiles(p, angles, spp=64, seed=2),
                       k * plain.render_profiles(p, angles, spp=64, seed=2), rtol=1e-12, atol=1e-15)
    # a window other than the profile's (full-well form there) carries the gain too
    assert GEOM.window((0, 8), (0, 1)) != GEOM.profile_window()
    assert np.allclose(gained.render(p, angles, spp=16, seed=3, columns=(0, 8), rows=(0, 1)),
                       k * plain.render(p, angles, spp=16, seed=3, columns=(0, 8), rows=(0, 1)), rtol=1e-12, atol=1e-15)
    cot = rng.random((2, N_PIX))
    grads = gained.vjp(p, angles, cot, spp=64, seed=2, fd_parameters=False)
    jac = gained.jacobian(p, angles, ["sensor_nonlinearity.compression"], spp=64, seed=2)
    h = 1e-5
    lo, hi = dict(p), dict(p)
    lo["sensor_nonlinearity.compression"] -= h
    hi["sensor_nonlinearity.compression"] += h
    fd = (gained.render_profiles(hi, angles, spp=64, seed=2) - gained.render_profiles(lo, angles, spp=64, seed=2)) / (2 * h)
    assert np.allclose(jac["sensor_nonlinearity.compression"], fd, rtol=1e-4, atol=1e-12)
    assert grads["sensor_nonlinearity.compression"] == pytest.approx(float((fd * cot).sum()), rel=1e-4)
    off = {**p, "sensor_nonlinearity.compression": 0.0}
    assert np.array_equal(gained.render_profiles(off, angles, spp=64, seed=2),
                          plain.render_profiles(off, angles, spp=64, seed=2))


def test_forward_model_lights_the_slab_with_the_decompressed_beam_map() -> None:
    """With the calibration frame's pixels and fills the model takes the compression out of
    the map at the values' c (its wings were read from fuller wells than its peak): the
    profiles are those of a model lit by that map, the compression becomes a rendered
    (finite-difference) parameter, and at c = 0 nothing changes."""
    from estimate.beam import map_from_pixel_image
    from estimate.extensions.base import BeamFill
    from estimate.extensions.sensor_nonlinearity import decompressed_map

    pitch = GEOM.pixel_mm
    yy, xx = np.mgrid[0:15, 0:15]
    pix = 1e3 * np.exp(-0.5 * ((xx - 7.2) ** 2 + (yy - 6.9) ** 2) / 2.0 ** 2)
    # a sawtooth of fills: the peak read from a short exposure, the wings from longer ones
    r = np.hypot(xx - 7.2, yy - 6.9)
    fill_map = np.where(r < 2.5, 0.15, np.where(r < 5.0, 0.55, 0.3))

    def to_profile(p: np.ndarray) -> BeamProfile:
        return BeamProfile.from_camera_image(map_from_pixel_image(p) / pitch ** 2, pitch, (7.0, 7.0))

    lit = pix > 0
    bf = BeamFill(weights=pix[lit] / pix.sum(), fill=fill_map[lit], pixels=pix, fill_map=fill_map,
                  to_profile=to_profile)
    c = 0.1
    exts = ["sensor_nonlinearity"]
    model = ForwardModel(GEOM, to_profile(pix), phase="exp1", extensions=exts, beam_fill=bf)
    assert model.decompresses_beam and model.derivative_kind("sensor_nonlinearity.compression") == "fd"
    shape = decompressed_map(c, bf)
    assert shape.sum() == pytest.approx(pix.sum(), rel=1e-12)        # the power stays the read one
    assert shape[7, 7] / shape[7, 12] < pix[7, 7] / pix[7, 12]      # the wings come up against the peak
    # the same as a model lit by that map with the power put right in the image (calibration_gain)
    power_only = dataclasses.replace(bf, pixels=None, fill_map=None, to_profile=None)
    lit_by_it = ForwardModel(GEOM, to_profile(shape), phase="exp1", extensions=exts, beam_fill=power_only)
    assert not lit_by_it.decompresses_beam
    p = {**BASE, "phase.b1": 1.0, "sensor_nonlinearity.compression": c}
    angles = [40.0, 140.0]
    assert np.allclose(model.render_profiles(p, angles, spp=64, seed=2),
                       lit_by_it.render_profiles(p, angles, spp=64, seed=2), rtol=1e-5, atol=1e-12)
    off = {**p, "sensor_nonlinearity.compression": 0.0}
    read = ForwardModel(GEOM, to_profile(pix), phase="exp1", extensions=exts, beam_fill=power_only)
    assert np.array_equal(model.render_profiles(off, angles, spp=64, seed=2), read.render_profiles(off, angles, spp=64, seed=2))
    # a rendered column of the compression, and one unlike the image-only column
    jac = model.jacobian(p, angles, ["sensor_nonlinearity.compression"], spp=64, seed=2)["sensor_nonlinearity.compression"]
    image_only = read.jacobian(p, angles, ["sensor_nonlinearity.compression"], spp=64, seed=2)["sensor_nonlinearity.compression"]
    assert np.all(np.isfinite(jac)) and not np.allclose(jac, image_only, rtol=1e-2)


@pytest.mark.parametrize("with_variance", [True, False])
def test_beam_support_leaves_the_dark_noise_out_of_the_map_and_a_real_halo_in(with_variance: bool) -> None:
    """A calibration frame of a 3.75 px beam (the simulated rig's 0.25 mm) in a 46 px crop,
    dark noise of sd 15 against a peak of 2.7e5 (its b filter's): clipped at zero, the noise
    put ~2e-4 of the power beyond 5.5 beam sigmas, where the beam has none; inside the support
    nothing of the beam is lost, and a real halo (1 % of the power, sigma 12 px) stays."""
    from estimate.beam import beam_support, map_from_pixel_image

    rng = np.random.default_rng(70)
    yy, xx = np.mgrid[0:46, 0:46]
    r2 = (xx - 22.6) ** 2 + (yy - 23.1) ** 2
    beam = np.exp(-0.5 * r2 / 3.75 ** 2)
    beam *= 2.7e5 / beam.max()
    halo = 0.01 * beam.sum() * np.exp(-0.5 * r2 / 12.0 ** 2) / (2 * np.pi * 12.0 ** 2)
    sd = 15.0
    far = np.sqrt(r2) > 5.5 * 3.75
    for truth, keeps_halo in ((beam, False), (beam + halo, True)):
        frame = truth + rng.normal(0.0, sd, truth.shape)
        var = np.full(truth.shape, (sd / 2) ** 2) if with_variance else None   # the merge's, half the real noise
        clipped = np.clip(frame, 0.0, None)
        kept = np.where(beam_support(frame, var), clipped, 0.0)
        if not keeps_halo:
            assert clipped[far].sum() / truth.sum() > 5e-5                  # the pedestal
            assert kept[far].sum() / truth.sum() < 1e-6                     # gone
        else:
            # the halo's light inside the crop is kept (its part in the far region, within 5 %)
            assert kept[far].sum() == pytest.approx(truth[far].sum(), rel=0.05)
        assert kept.sum() == pytest.approx(truth.sum(), rel=2e-4)
        assert np.all(map_from_pixel_image(kept) >= 0)
    # a noise-free frame (no negative pixel): everything is support
    assert beam_support(beam).all()
