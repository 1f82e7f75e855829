"""HDR merge against the truth, masking, the automatic bracket, and the image files."""

from __future__ import annotations

import numpy as np
import pytest
from fakes import TEST_SENSOR, simulate_frame

from capture.bracket import BracketController, BracketPolicy
from capture.errors import PlanError
from capture.exr_io import read_exr, read_frames, write_exr, write_frames
from capture.hdr import (
    FittedDark,
    MatchedDarks,
    NoiseModel,
    merge_hdr,
    optimal_reference,
    plateau_saturation_adu,
    saturation_mask,
)
from drivers.interfaces import ROI, Frame
from estimate.extensions.sensor_nonlinearity import apply_raw

NOISE = NoiseModel.from_sensor(TEST_SENSOR)
EXPOSURES = [0.001 * 4**k for k in range(6)]


def _darks(rng, shape, exposures=EXPOSURES, n=2, bias_map=None):
    frames = [
        Frame(simulate_frame(rng, 0.0, t, TEST_SENSOR, dark=True, shape=shape, bias_map=bias_map), t, True, -20.0, 0, t, ROI())
        for t in exposures
        for _ in range(n)
    ]
    return MatchedDarks.from_frames(frames, NOISE)


def _stack(rng, truth, exposures=EXPOSURES, bias_map=None):
    return np.stack([simulate_frame(rng, truth, t, TEST_SENSOR, bias_map=bias_map) for t in exposures])


@pytest.fixture(scope="module")
def bands():
    """8 bands of 16 x 128 uniform radiance, 30 .. 2e6 e-/s, with a fixed-pattern bias."""
    rng = np.random.default_rng(11)
    levels = np.logspace(np.log10(30), np.log10(2e6), 8)
    truth = np.repeat(levels, 16)[:, None] * np.ones((1, 128))
    bias_map = TEST_SENSOR.bias_adu + rng.normal(0, 4.0, truth.shape)
    light = _stack(rng, truth, bias_map=bias_map)
    darks = _darks(rng, truth.shape, bias_map=bias_map)
    return levels, truth, light, darks


def _interior(b: int) -> slice:
    return slice(b * 16 + 4, b * 16 + 12)  # away from the bloom at band edges


def test_merge_is_unbiased_and_its_variance_is_calibrated(bands):
    levels, truth, light, darks = bands
    res = merge_hdr(light, EXPOSURES, darks, NOISE)
    assert res.radiance.dtype == np.float32 and res.variance.dtype == np.float32
    assert res.mask.all()
    for b, L in enumerate(levels):
        err = res.radiance[_interior(b)].astype(np.float64) - L
        z = err.mean() / (err.std(ddof=1) / np.sqrt(err.size))
        assert abs(z) < 4.5, (L, z)
        ratio = res.variance[_interior(b)].mean() / err.var(ddof=1)
        assert 0.85 < ratio < 1.15, (L, ratio)


def test_merge_reaches_the_snr_of_the_oracle_estimator(bands):
    levels, truth, light, darks = bands
    res = merge_hdr(light, EXPOSURES, darks, NOISE)
    valid = ~saturation_mask(light, NOISE.saturation_adu, bloom_rows=2)
    oracle = optimal_reference(light, EXPOSURES, darks, NOISE, truth, valid)
    # a naive merge (each pixel from its longest unsaturated exposure) is clearly worse at mid levels
    longest = np.where(valid, np.arange(len(EXPOSURES))[:, None, None], -1).max(axis=0)
    for b, L in enumerate(levels):
        sl = _interior(b)
        rmse = np.sqrt(np.mean((res.radiance[sl] - L) ** 2))
        rmse_opt = np.sqrt(np.mean((oracle[sl] - L) ** 2))
        assert rmse_opt / rmse >= 0.98, (L, rmse_opt / rmse)
    b = 5  # ~1.3e5 e-/s: several exposures unsaturated
    sl = _interior(b)
    i = longest[sl]
    t = np.asarray(EXPOSURES)[i]
    naive = NOISE.gain_e_per_adu * (np.take_along_axis(light[:, sl], i[None], 0)[0] - np.stack([darks.level_adu(x) for x in EXPOSURES])[i, np.arange(8)[:, None], np.arange(128)[None, :]]) / t
    assert np.sqrt(np.mean((naive - levels[b]) ** 2)) > 1.1 * np.sqrt(np.mean((res.radiance[sl] - levels[b]) ** 2))


def test_saturated_samples_are_masked_and_bright_pixels_come_from_short_exposures():
    rng = np.random.default_rng(3)
    truth = np.full((32, 32), 200.0)
    truth[12:20, 12:20] = 1.0e6  # saturates every exposure from 0.256 s (2.6e5 e- > full well)
    light = _stack(rng, truth)
    darks = _darks(rng, truth.shape)
    res = merge_hdr(light, EXPOSURES, darks, NOISE)
    spot = res.radiance[13:19, 13:19]
    sigma = np.sqrt(res.variance[13:19, 13:19])
    assert np.all(res.n_valid[13:19, 13:19] <= 4)
    assert abs(float(np.mean((spot - 1.0e6) / sigma))) < 4 / np.sqrt(spot.size) * 3
    # treating clipped samples as valid underestimates the spot badly
    unmasked = merge_hdr(light, EXPOSURES, darks, NoiseModel(**{**NOISE.to_dict(), "saturation_adu": 70000.0}),
                         detect_plateau=False)
    assert np.mean(unmasked.radiance[13:19, 13:19]) < 0.5e6
    # The ADC's clipped plateau (65 535) lies below 70 000: found by itself, it saves the merge.
    found = merge_hdr(light, EXPOSURES, darks, NoiseModel(**{**NOISE.to_dict(), "saturation_adu": 70000.0}))
    assert found.saturation_adu is not None and 65_500 < found.saturation_adu < 65_535
    assert np.allclose(found.radiance[13:19, 13:19], spot, rtol=1e-6)


def _compressed_stack(rng, truth, c, exposures=EXPOSURES):
    """Raw frames of a sensor whose wells clip at full well and whose response then
    compresses the charge q to q (1 - c (q / FW)^2): its clipped wells read below the
    noise model's saturation level when c > 1 - 0.95 (the headroom)."""
    fw = TEST_SENSOR.full_well_e
    frames = []
    for t in exposures:
        q = rng.poisson(truth * t + TEST_SENSOR.dark_current_e_per_s * t).astype(np.float64)
        q = apply_raw(q, c, fw) + rng.normal(0.0, TEST_SENSOR.read_noise_e, q.shape)
        frames.append(np.clip(np.rint(TEST_SENSOR.bias_adu + q / TEST_SENSOR.gain_e_per_adu), 0, 65535))
    return np.stack(frames).astype(np.uint16)


def test_wells_that_clip_below_the_saturation_level_are_found_by_their_plateau():
    rng = np.random.default_rng(21)
    yy, xx = np.mgrid[0:32, 0:32]
    truth = 200.0 + 1.0e7 * np.exp(-((yy - 16.0) ** 2 + (xx - 16.0) ** 2) / (2 * 4.0 ** 2))
    c = 0.12
    light = _compressed_stack(rng, truth, c)
    darks = _darks(rng, truth.shape)
    clipped_adu = TEST_SENSOR.bias_adu + TEST_SENSOR.full_well_e * (1 - c) / TEST_SENSOR.gain_e_per_adu
    assert clipped_adu < NOISE.saturation_adu, "the fake's clipped wells must hide under the nominal level"
    level = plateau_saturation_adu(light, NOISE)
    assert level is not None and clipped_adu - 60 < level < clipped_adu
    res = merge_hdr(light, EXPOSURES, darks, NOISE)
    assert res.saturation_adu == level
    core = (slice(14, 19), slice(14, 19))
    # What the merge keeps of the core is compressed by at most c (g < 1): within [1 - c, 1].
    ratio = res.radiance[core] / truth[core]
    assert np.all(ratio > 1 - c - 0.02) and np.all(ratio < 1.02), ratio
    # Taking the clipped samples as measurements (the nominal level only) ruins the core.
    blind = merge_hdr(light, EXPOSURES, darks, NOISE, detect_plateau=False)
    assert blind.saturation_adu == NOISE.saturation_adu
    assert np.max(blind.radiance[core] / truth[core]) < 0.6


def test_no_plateau_where_nothing_clipped():
    rng = np.random.default_rng(22)
    # A large flat field at 90 % of the nominal range, in one frame: its top is the extreme of
    # its shot noise (~170 ADU wide), not a pile-up within the read noise.
    span = NOISE.saturation_adu - TEST_SENSOR.bias_adu
    flat = np.full((256, 256), 0.9 * span * TEST_SENSOR.gain_e_per_adu / 0.1)
    assert plateau_saturation_adu(simulate_frame(rng, flat, 0.1, TEST_SENSOR)[None], NOISE) is None
    # A smooth spot whose longest exposure peaks at 90 %: its top is a handful of pixels.
    yy, xx = np.mgrid[0:64, 0:64]
    spot = 0.9 * span * TEST_SENSOR.gain_e_per_adu / EXPOSURES[-1] * np.exp(
        -((yy - 32.0) ** 2 + (xx - 32.0) ** 2) / (2 * 5.0 ** 2))
    light = _stack(rng, spot)
    assert plateau_saturation_adu(light, NOISE) is None
    assert merge_hdr(light, EXPOSURES, _darks(rng, spot.shape), NOISE).saturation_adu == NOISE.saturation_adu
    # Dim frames (top below half the range) never make a plateau, however flat.
    assert plateau_saturation_adu(np.full((2, 16, 16), 20_000, np.uint16), NOISE) is None
    # The ADC's own clip sits above the nominal level: the nominal mask already has it.
    assert plateau_saturation_adu(np.full((2, 16, 16), 65_535, np.uint16), NOISE) is None


def test_bloom_along_columns_is_masked():
    rng = np.random.default_rng(5)
    truth = np.full((40, 9), 2000.0)
    truth[20, 4] = 6.0e5  # one bright pixel: its charge spills up and down column 4 in long exposures
    light = _stack(rng, truth)
    darks = _darks(rng, truth.shape)
    res = merge_hdr(light, EXPOSURES, darks, NOISE, bloom_rows=2)
    sat_long = light[-1] >= NOISE.saturation_adu
    trail = np.flatnonzero(sat_long[:, 4])
    assert trail.size > 1, "the fake must bloom for this test to mean anything"
    # just beyond the trail: partially filled in the long exposure; the masked merge ignores it
    neighbours = [trail.min() - 1, trail.min() - 2, trail.max() + 1, trail.max() + 2]
    z = (res.radiance[neighbours, 4] - 2000.0) / np.sqrt(res.variance[neighbours, 4])
    assert np.all(np.abs(z) < 5), z
    unmasked = merge_hdr(light, EXPOSURES, darks, NOISE, bloom_rows=0)
    zu = (unmasked.radiance[neighbours, 4] - 2000.0) / np.sqrt(unmasked.variance[neighbours, 4])
    assert np.max(np.abs(zu)) > 10
    # other columns are untouched by the bloom mask
    assert np.all(res.n_valid[:, [0, 1, 2, 6, 7, 8]] == len(EXPOSURES))


def test_pixel_saturated_in_every_exposure_is_flagged():
    rng = np.random.default_rng(7)
    truth = np.full((8, 8), 500.0)
    truth[4, 4] = 5.0e9
    light = _stack(rng, truth)
    res = merge_hdr(light, EXPOSURES, _darks(rng, truth.shape), NOISE)
    assert not res.mask[4, 4] and np.isinf(res.variance[4, 4])
    assert res.radiance[4, 4] > 1.0e7  # lower bound from the shortest exposure
    assert res.mask[0, 0] and np.isfinite(res.variance[0, 0])
    assert res.channels()["mask"][4, 4] == 0.0


def test_fitted_dark_model_removes_bias_structure_and_dark_current():
    rng = np.random.default_rng(9)
    shape = (24, 24)
    bias_map = TEST_SENSOR.bias_adu + rng.normal(0, 6.0, shape)
    times = [0.01, 1.0, 10.0, 30.0]
    frames = [
        Frame(simulate_frame(rng, 0.0, t, TEST_SENSOR, dark=True, shape=shape, bias_map=bias_map), t, True, -20.0, 0, t, ROI())
        for t in times
        for _ in range(4)
    ]
    model = FittedDark.fit(frames, NOISE)
    g = TEST_SENSOR.gain_e_per_adu
    assert np.std(model.bias_adu - bias_map) < 3.0  # the fixed pattern (6 ADU) is learnt
    assert abs(float(model.rate_adu_per_s.mean()) * g - TEST_SENSOR.dark_current_e_per_s) < 0.2
    truth = np.full(shape, 3000.0)
    light = _stack(rng, truth, bias_map=bias_map)
    res = merge_hdr(light, EXPOSURES, model, NOISE)
    z = (res.radiance - truth) / np.sqrt(res.variance)
    assert abs(float(z.mean())) < 0.3 and 0.8 < float(z.std()) < 1.2
    with pytest.raises(ValueError, match="two or more"):
        FittedDark.fit(frames[:4], NOISE)


def test_matched_darks_must_cover_every_exposure():
    rng = np.random.default_rng(8)
    truth = np.full((4, 4), 100.0)
    darks = _darks(rng, truth.shape, exposures=EXPOSURES[:3])
    with pytest.raises(ValueError, match="no dark frame matched"):
        merge_hdr(_stack(rng, truth), EXPOSURES, darks, NOISE)


# --------------------------------------------------------------------------- bracket


def _run_bracket(truth, policy, seed=0, exposure_range=(0.001, 3600.0)):
    rng = np.random.default_rng(seed)
    ctl = BracketController(policy, NOISE, exposure_range)
    t = ctl.first()
    while t is not None:
        t = ctl.add(simulate_frame(rng, truth, t, TEST_SENSOR), t)
    return ctl.status


def _profile(peak, floor, rows=9, cols=200):
    x = np.arange(cols)
    row = peak * np.exp(-np.abs(x - cols / 2) / 12.0) + floor
    img = np.full((rows, cols), floor)
    img[rows // 2] = row
    img[rows // 2 - 1] = row / 2
    img[rows // 2 + 1] = row / 2
    return img


def test_bracket_stops_when_dim_pixels_reach_target_snr_with_peak_measured():
    policy = BracketPolicy(target_snr=20.0, dim_fraction=1e-3, max_exposures=8)
    st = _run_bracket(_profile(3e6, 1.0), policy)
    assert st.reason == "target SNR reached"
    assert st.peak_unsaturated and st.min_snr >= 20.0
    assert st.exposures_s[0] == 0.001  # the camera's shortest
    assert st.exposures_s == sorted(st.exposures_s)
    assert st.profile_rows == (3, 6)
    # a stricter target needs longer exposures
    st2 = _run_bracket(_profile(3e6, 1.0), BracketPolicy(target_snr=60.0, dim_fraction=1e-3, max_exposures=8))
    assert max(st2.exposures_s) > max(st.exposures_s)


def test_bracket_goes_shorter_when_the_first_exposure_saturates():
    policy = BracketPolicy(first_exposure_s=0.1, target_snr=10.0)
    st = _run_bracket(_profile(5e6, 50.0), policy)
    assert min(st.exposures_s) < 0.1 and st.peak_unsaturated


def test_bracket_is_bounded():
    dim = _profile(30.0, 0.5)
    st = _run_bracket(dim, BracketPolicy(target_snr=1000.0, max_exposures=4))
    assert len(st.exposures_s) == 4 and st.reason == "maximum number of exposures"
    st = _run_bracket(dim, BracketPolicy(target_snr=1000.0, max_exposures=20, max_exposure_s=0.05))
    assert max(st.exposures_s) == pytest.approx(0.05) and st.reason == "maximum exposure time"
    # the peak cannot be desaturated at the camera's shortest exposure
    st = _run_bracket(_profile(1e9, 1e4), BracketPolicy(target_snr=5.0, max_exposure_s=10.0), exposure_range=(0.001, 10.0))
    assert not st.peak_unsaturated


@pytest.mark.parametrize(
    "kw",
    [{"ratio": 1.0}, {"max_exposures": 0}, {"first_exposure_s": 0.0}, {"max_exposure_s": 1e-4}, {"n_darks": 0}, {"dim_fraction": 0.0}],
)
def test_bad_bracket_policy_is_a_plan_error(kw):
    with pytest.raises(PlanError):
        BracketPolicy(**kw).check((0.001, 3600.0))


def test_open_exposure_limits_come_from_the_camera():
    p = BracketPolicy().resolved((0.03, 3600.0))
    assert (p.first_exposure_s, p.max_exposure_s) == (0.03, 60.0)
    p = BracketPolicy(first_exposure_s=0.05).resolved((0.03, 10.0))
    assert (p.first_exposure_s, p.max_exposure_s) == (0.05, 10.0)
    assert BracketPolicy.from_dict(p.to_dict()) == p


def test_bracket_outside_the_camera_range_is_a_plan_error():
    with pytest.raises(PlanError, match="camera's range"):
        BracketPolicy(max_exposure_s=120.0).check((0.001, 60.0))


# --------------------------------------------------------------------------- files


def test_exr_round_trip_keeps_channels_attributes_and_meta(tmp_path):
    rng = np.random.default_rng(1)
    rad = rng.random((5, 7)).astype(np.float32) * 1e6
    var = np.full((5, 7), np.inf, np.float32)
    sha = write_exr(tmp_path / "a.exr", {"radiance": rad, "variance": var}, {"rig_angle_deg": 15.0, "rig_filter": "g"}, meta={"x": [1, 2]})
    assert len(sha) == 64
    img = read_exr(tmp_path / "a.exr")
    assert np.array_equal(img["radiance"], rad) and np.isinf(img["variance"]).all()
    assert img.attributes["rig_angle_deg"] == 15.0 and img.attributes["rig_filter"] == "g"
    assert img.meta == {"x": [1, 2]}
    with pytest.raises(ValueError, match="reserved"):
        write_exr(tmp_path / "b.exr", {"radiance": rad}, {"channels": "x"})
    with pytest.raises(ValueError, match="shape"):
        write_exr(tmp_path / "b.exr", {"radiance": rad, "variance": rad[:2]})
    assert not (tmp_path / "b.exr").exists()


def test_raw_frames_round_trip_bit_exact(tmp_path):
    rng = np.random.default_rng(2)
    roi = ROI(0, 10, 64, 16)
    frames = [
        Frame(rng.integers(0, 65536, (16, 64), dtype=np.uint16), t, d, -19.5, 100.0 + t, 101.0 + t, roi, "cam", {"k": 1})
        for t, d in [(0.001, False), (0.004, False), (0.001, True)]
    ]
    write_frames(tmp_path / "s.npz", frames)
    back = read_frames(tmp_path / "s.npz")
    assert len(back) == 3
    for a, b in zip(frames, back):
        assert np.array_equal(a.data, b.data) and b.data.dtype == np.uint16
        assert (a.exposure_s, a.dark, a.ccd_temp_c, a.roi, a.camera, a.extra) == (b.exposure_s, b.dark, b.ccd_temp_c, b.roi, b.camera, b.extra)
    with pytest.raises(ValueError, match="uint16"):
        write_frames(tmp_path / "t.npz", [Frame(np.zeros((2, 2), np.float32), 1.0, False, 0, 0, 1, roi)])
