"""estimate.problem: profile extraction from a session and its refusals."""

from __future__ import annotations

import numpy as np
import pytest
from synth_session import CENTER_PX, PITCH_MM, make_session

from estimate.errors import DataError
from estimate.problem import Y_SHAPE_MAX, load_problem, y_shape_from_rows

TRUTH = {"g": {"sigma_t": 3.0, "albedo": 0.85, "phase.b1": 3.0}, "r": {"sigma_t": 2.0, "albedo": 0.9, "phase.b1": 2.0}}


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    return make_session(tmp_path_factory.mktemp("p") / "s", TRUTH, angles=[30, 150], spp=64, width=96,
                        scale=2e5, skip=["a01_r"])


def test_profile_window_geometry_and_data(session):
    pb = load_problem(session, "g", columns=40)
    assert pb.measured.shape == pb.variance.shape == (2, 40)
    assert list(pb.angles_deg) == [30.0, 150.0] and pb.stack_ids == ["a00_g", "a01_g"]
    assert pb.wavelength_nm == 530.0
    # Columns centred on the beam: x from about -20 to +20 pixels around the axis.
    assert abs(pb.x_mm.mean()) < PITCH_MM
    assert np.allclose(np.diff(pb.x_mm), PITCH_MM)
    assert pb.geometry.center_px == CENTER_PX and pb.geometry.row == 256
    # The spot is in the window: the brightest pixel lies near the centre.
    assert np.all(np.abs(pb.x_mm[np.argmax(pb.measured, axis=1)]) < 1.0)
    assert pb.valid.all() and np.all(pb.variance > 0)
    assert abs(pb.beam.power() - 1e6 / PITCH_MM ** 2 * PITCH_MM ** 2) / 1e6 < 1e-6


def test_session_from_before_the_stage_offset_gets_its_angles_corrected(tmp_path):
    """A plan without stage_offset_deg commanded the stage to the recorded angle: the beam met
    the slab at angle + 180 - rotation_zero_deg; a plan with it recorded world angles."""
    import yaml
    from synth_session import write_calibration

    from capture.session import Session

    s = make_session(tmp_path / "s", {"g": TRUTH["g"]}, angles=[30, 150], spp=16, width=32, scale=2e5)
    assert list(load_problem(s, "g").angles_deg) == [30.0, 150.0]
    # the same session with a calibration whose zero is 0.4 deg short of 180, and a legacy plan
    cal = write_calibration(tmp_path / "cal2", ["g"], rotation_zero_deg=179.6)
    sess = Session.open(s)
    man = sess.manifest
    sess.close()
    assert load_problem(s, "g").angle_correction_deg == 0.0
    import shutil

    shutil.copy(cal / "calibration.yaml", s / "calibration" / "calibration.yaml")
    from capture.atomic import sha256_file

    man["calibration"]["files"]["calibration.yaml"]["sha256"] = sha256_file(s / "calibration" / "calibration.yaml")
    man["calibration"]["files"]["calibration.yaml"]["bytes"] = (s / "calibration" / "calibration.yaml").stat().st_size
    (s / "session.yaml").write_text(yaml.safe_dump(man, sort_keys=False))
    assert list(load_problem(s, "g").angles_deg) == [30.0, 150.0]  # the plan records its (zero) offset
    del man["plan"]["stage_offset_deg"]
    (s / "session.yaml").write_text(yaml.safe_dump(man, sort_keys=False))
    pb = load_problem(s, "g")
    assert pb.angle_correction_deg == pytest.approx(0.4)
    assert pb.angles_deg == pytest.approx([30.4, 150.4])


def test_y_shape_from_the_recorded_rows():
    x = np.arange(60)
    rows = np.arange(20)
    j = 8
    g = np.exp(-0.5 * ((rows - j) / 3.0) ** 2)
    img = g[:, None] * (1.0 + 0.001 * x[None, :])
    ok = np.ones(img.shape, bool)
    h = y_shape_from_rows(img, ok, j, (10, 50), radius=64)
    assert h.shape == (129, 40)
    assert np.allclose(h[64], 1.0)
    # inside the band: the spot's own shape (the slow x trend cancels in the ratio)
    for dy in (-8, -3, 1, 5, 11):
        assert np.allclose(h[64 + dy, 5:-5], g[j + dy], rtol=1e-3), dy
    # beyond the band: the decay of its outermost rows continued, never growing
    below, beyond = h[:64 - 8, 5:-5][::-1], h[64 + 12:, 5:-5]
    for side, edge in ((below, h[64 - 8, 5:-5]), (beyond, h[64 + 11, 5:-5])):
        assert np.all(np.diff(side, axis=0) <= 0) and np.all(side[0] < edge)
    # a side of fewer than 7 rows cannot say how fast it falls: its outermost row repeated
    short = y_shape_from_rows(img[4:], ok[4:], j - 4, (10, 50), radius=64)
    assert np.allclose(short[:64 - 4], short[64 - 4])
    # ... at the rate of the band's edge: a Gaussian falls faster than that, so the continued
    # decay lies between the spot's own shape and the outermost row
    assert np.all(beyond[0] > g[j + 11] * np.exp(-0.5 * (2 * 12 - 1) / 9.0) * 0.5)
    wide = np.exp(-0.5 * ((np.arange(40) - 20) / 6.0) ** 2)[:, None] * np.ones((1, 60))
    hw = y_shape_from_rows(wide, np.ones(wide.shape, bool), 20, (10, 50), radius=64)
    assert np.all(np.diff(hw[:64 - 20 + 1, 20], axis=0) >= 0) and hw[0, 20] < 1e-3
    # a single-row recording, or an unlit profile row, says nothing: h = 1 (the LSF)
    assert np.all(y_shape_from_rows(img[j:j + 1], ok[j:j + 1], 0, (10, 50)) == 1.0)
    dark = img.copy()
    dark[j] = 0.0
    assert np.all(y_shape_from_rows(dark, ok, j, (10, 50))[64 + 1] == 1.0)
    # a hot row is clipped; unusable pixels are left out of the averages
    hot = img.copy()
    hot[j + 1] *= 100.0
    assert np.all(y_shape_from_rows(hot, ok, j, (10, 50))[65] == Y_SHAPE_MAX)
    masked = ok.copy()
    masked[j + 2, 20:25] = False
    hm = y_shape_from_rows(np.where(masked, img, 1e6), masked, j, (10, 50))
    assert np.allclose(hm[66, 5:-5], g[j + 2], rtol=1e-2)  # the masked 1e6 values left no trace


def test_a_recording_without_y_structure_has_a_flat_y_shape(session):
    pb = load_problem(session, "g", columns=40)
    # the synthetic session repeats the profile row over its band: h = 1, the LSF
    assert pb.y_shape.shape == (2, 129, 40) and np.all(pb.y_shape == 1.0)
    assert set(pb.y_shapes()) == {30.0, 150.0}
    assert set(pb.subset([1]).y_shapes()) == {150.0}


def test_missing_stack_refused_unless_partial(session):
    with pytest.raises(DataError, match=r"a01_r \(not captured\).*--allow-partial"):
        load_problem(session, "r")
    with pytest.raises(DataError, match="only 1 usable"):
        load_problem(session, "r", allow_partial=True)


def test_unknown_channel(session):
    with pytest.raises(DataError, match="unknown channel 'b'"):
        load_problem(session, "b")


def test_no_calibration(tmp_path):
    s = make_session(tmp_path / "s", {"g": TRUTH["g"]}, angles=[30, 150], spp=16, width=64, calibration=False)
    with pytest.raises(DataError, match="no beam calibration"):
        load_problem(s, "g")


def test_corrupt_stack_named(tmp_path):
    s = make_session(tmp_path / "s", {"g": TRUTH["g"]}, angles=[30, 60, 150], spp=16, width=64)
    (s / "hdr" / "a01_g.exr").write_bytes(b"garbage")
    with pytest.raises(DataError, match=r"a01_g \(hdr/a01_g.exr is corrupt \(checksum mismatch\)\)"):
        load_problem(s, "g")
    pb = load_problem(s, "g", allow_partial=True)
    assert pb.stack_ids == ["a00_g", "a02_g"] and pb.missing == ["a01_g (hdr/a01_g.exr is corrupt (checksum mismatch))"]
    # a file that is gone is named as missing, not corrupt
    (s / "hdr" / "a02_g.exr").unlink()
    with pytest.raises(DataError, match=r"a02_g \(hdr/a02_g.exr is missing\)"):
        load_problem(s, "g")


def test_nan_and_negative_radiance_named(tmp_path):
    from capture.exr_io import read_exr, write_exr
    from capture.session import Session

    s = make_session(tmp_path / "s", {"g": TRUTH["g"]}, angles=[30, 150], spp=16, width=64)
    img = read_exr(s / "hdr" / "a01_g.exr")
    rad = img["radiance"].copy()
    row = 256 - 252
    rad[row, 30] = np.nan
    _rewrite(s, "a01_g", {**img.channels, "radiance": rad})
    with pytest.raises(DataError, match=r"stack a01_g: radiance is NaN .* column 254 \(row 256\)"):
        load_problem(s, "g", columns=64)
    rad[row, 30] = -1e6
    _rewrite(s, "a01_g", {**img.channels, "radiance": rad})
    with pytest.raises(DataError, match=r"stack a01_g: negative radiance"):
        load_problem(s, "g", columns=64)
    del Session, write_exr


def _rewrite(session, sid, channels):
    """Replace a stack's EXR and its manifest checksum (simulating a bad merge, not corruption)."""
    import yaml

    from capture.atomic import sha256_file
    from capture.exr_io import write_exr

    p = session / "hdr" / f"{sid}.exr"
    write_exr(p, channels)
    m = yaml.safe_load((session / "session.yaml").read_text())
    for st in m["stacks"]:
        if st["id"] == sid:
            st["files"]["hdr"]["sha256"] = sha256_file(p)
            st["files"]["hdr"]["bytes"] = p.stat().st_size
    (session / "session.yaml").write_text(yaml.safe_dump(m, sort_keys=False))


def test_beam_map_from_a_pixel_image_keeps_the_true_width_and_power():
    """A Gaussian beam imaged by 0.067 mm pixels, read back bilinearly: the raw frame is
    0.9 % too wide (pixel box + bilinear triangle), the corrected map has the true width."""
    from scipy.special import erf

    from estimate.beam import BeamProfile, map_from_pixel_image

    pitch, sigma = 0.0667, 0.25
    edges = (np.arange(-30, 31) - 0.5) * pitch

    def pixels(x0: float) -> np.ndarray:
        z = (edges - x0) / (sigma * np.sqrt(2.0))
        return 0.5 * np.diff(erf(z))

    image = np.outer(pixels(-0.02), pixels(0.01)) / pitch ** 2
    f = np.linspace(-1.5, 1.5, 901)
    uu, vv = np.meshgrid(f, f)

    def width(m: np.ndarray) -> float:
        e = BeamProfile.centered(m, pitch).lookup(uu, vv)
        mean = (e * uu).sum() / e.sum()
        return float(np.sqrt((e * (uu - mean) ** 2).sum() / e.sum()))

    corrected = map_from_pixel_image(image)
    assert width(image) / sigma - 1.0 > 0.007
    assert abs(width(corrected) / sigma - 1.0) < 5e-4
    assert corrected.sum() == pytest.approx(image.sum(), rel=1e-12)
    assert corrected.min() >= 0.0
