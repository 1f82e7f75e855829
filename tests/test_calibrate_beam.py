"""rig calibrate-beam on the simulated rig: finds the hidden zero error, the beam's centre,
widths and relative powers; refuses to overwrite; bad input is one line, exit 2."""

import json
import math

import numpy as np
import pytest
import yaml

from calibrate.beam import (
    CalibrationError,
    beam_moments,
    check_output_dir,
    fit_rotation_zero,
)
from rig.cli import main

ZERO_ERROR = 0.37
AXIS = (258.3, 253.6)
SIGMA_MM = 0.25


@pytest.fixture
def sim(tmp_path):
    """A fast world (the straight beam needs no render) and a fast simulated rig config."""
    world = {
        "slab": {"thickness_mm": 1.0},
        "materials": {f: {"sigma_t": 2.0, "albedo": 0.9, "phase": {"type": "hg", "g": 0.5}} for f in "rgb"},
        "beam": {"profile": {"type": "gaussian", "sigma_mm": SIGMA_MM},
                 "power_e_per_s": {"r": 4.0e10, "g": 3.0e10, "b": 2.0e10}},
        "optics": {"axis_px": list(AXIS)},
        "stage": {"zero_error_deg": ZERO_ERROR},
        "render": {"spp_profile": 4, "spp_band": 1, "band_halfwidth_rows": 2, "spp_outside": 0,
                   "cache_dir": str(tmp_path / "cache")},
    }
    (tmp_path / "world.yaml").write_text(yaml.safe_dump(world))
    from rig.config import PACKAGED_SIM_CONFIG

    cfg = yaml.safe_load(PACKAGED_SIM_CONFIG.read_text())
    cfg["sim"]["time_scale"] = 5000.0
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(cfg))
    return tmp_path


def _run(sim, *extra):
    return main(["calibrate-beam", "--sim", str(sim / "world.yaml"), "--config", str(sim / "rig.yaml"), *extra])


def test_finds_the_hidden_zero_centre_widths_and_powers(sim, capsys):
    out = sim / "cal"
    assert _run(sim, "--out", str(out), "--json", "--filters", "rgb") == 0
    summary = json.loads(capsys.readouterr().out)
    doc = yaml.safe_load((out / "calibration.yaml").read_text())
    assert doc["format"] == "rig-calibration/1"
    zero, unc = doc["rotation_zero_deg"], doc["rotation_zero_uncertainty_deg"]
    assert summary["rotation_zero_deg"] == zero
    assert 0 < unc < 0.01
    assert abs(zero - (180.0 - ZERO_ERROR)) < 3 * unc
    cx, cy = doc["beam"]["center_px"]
    assert abs(cx - AXIS[0]) < 0.02 and abs(cy - AXIS[1]) < 0.02
    assert doc["pixel_pitch_mm"] == pytest.approx(0.020 / 0.3)
    filters = doc["beam"]["filters"]
    assert list(filters) == ["r", "g", "b"]
    for f, expect in (("r", 1.0), ("g", 0.75), ("b", 0.5)):
        v = filters[f]
        assert v["relative_power"] == pytest.approx(expect, rel=0.01)
        assert v["power_e_per_s"] == pytest.approx({"r": 4e7, "g": 3e7, "b": 2e7}[f], rel=0.01)
        for wmm in v["width_mm"]:
            assert wmm == pytest.approx(SIGMA_MM, rel=0.01)
        from capture.exr_io import read_exr

        img = read_exr(out / v["map"])
        assert set(img.channels) == {"radiance", "variance"}
        x0, y0 = img.meta["origin_px"]
        assert [x0, y0] == v["origin_px"]
        j, i = np.unravel_index(np.argmax(img["radiance"]), img["radiance"].shape)
        assert (x0 + i, y0 + j) == (int(AXIS[0]), int(AXIS[1]))
    for rel in doc["raw_files"]:
        assert (out / rel).is_file()
    assert "rotation_scan" in " ".join(doc["raw_files"])
    # nothing of the world's truth is written
    text = (out / "calibration.yaml").read_text()
    assert "zero_error" not in text and "world" not in text


def test_refuses_to_overwrite_and_bad_input_is_one_line(sim, capsys):
    out = sim / "cal"
    out.mkdir()
    (out / "calibration.yaml").write_text("format: rig-calibration/1\n")
    assert _run(sim, "--out", str(out)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not empty" in err and "never overwritten" in err
    assert (out / "calibration.yaml").read_text() == "format: rig-calibration/1\n"
    assert _run(sim, "--out", str(sim / "x"), "--filters", "rq") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown filter 'q'" in err
    (sim / "bad.yaml").write_text("slab: {thickness_mm: 1}\n")
    assert main(["calibrate-beam", "--sim", str(sim / "bad.yaml"), "--config", str(sim / "rig.yaml"),
                 "--out", str(sim / "y")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bad.yaml: materials" in err
    assert not (sim / "x").exists() or not any((sim / "x").iterdir())


def test_check_output_dir(tmp_path):
    assert check_output_dir(tmp_path / "new").is_dir()
    (tmp_path / "f").write_text("x")
    with pytest.raises(CalibrationError, match="is a file"):
        check_output_dir(tmp_path / "f")


def test_fit_rotation_zero_recovers_a_known_peak():
    rng = np.random.default_rng(3)
    a = np.arange(179.0, 180.01, 0.1)
    truth = 179.537
    y = 1e6 * np.exp(-0.5 * ((a - truth) / 0.5) ** 2)
    sig = np.sqrt(y) + 10.0
    zs = []
    for _ in range(200):
        z, u, _w, _chi2 = fit_rotation_zero(a, y + sig * rng.normal(size=a.size), sig)
        zs.append((z - truth) / u)
    zs = np.array(zs)
    assert abs(zs.mean()) < 0.3 and 0.8 < zs.std() < 1.25  # unbiased, honest uncertainty
    with pytest.raises(CalibrationError):
        fit_rotation_zero(a[:3], y[:3], sig[:3])


def test_beam_moments_of_a_gaussian():
    ys, xs = np.indices((80, 90)) + 0.5
    img = np.exp(-0.5 * (((xs - 40.2) / 4.0) ** 2 + ((ys - 30.7) / 6.0) ** 2))
    (cx, cy), (wx, wy) = beam_moments(img, 1e-4, (100, 200))
    assert math.isclose(cx, 140.2, abs_tol=1e-3) and math.isclose(cy, 230.7, abs_tol=1e-3)
    assert math.isclose(wx, 4.0, rel_tol=0.005) and math.isclose(wy, 6.0, rel_tol=0.005)
    with pytest.raises(CalibrationError, match="no beam"):
        beam_moments(np.zeros((4, 4)), 1e-3)


def test_capture_after_calibration_lights_the_slab_at_the_planned_world_angles(sim, capsys):
    """The calibration's rotation zero reaches the stage: world angle = stage angle + the hidden zero error."""
    cal = sim / "cal"
    assert _run(sim, "--out", str(cal), "--filters", "g") == 0
    out = sim / "s"
    assert main(["capture", "--sim", str(sim / "world.yaml"), "--config", str(sim / "rig.yaml"), "--calibration",
                 str(cal), "--filters", "g", "--angles", "2", "--out", str(out), "--band-rows", "8",
                 "--max-exposures", "3", "--darks", "1", "--no-progress"]) == 0
    assert "calibrated rotation zero" in capsys.readouterr().err
    from capture.session import Session

    s = Session.open(out)
    for rec in s.stacks():
        physical = rec.info["stage_angle_deg"] + ZERO_ERROR  # what the simulated bench lit the slab at
        assert abs(physical - rec.angle_deg) < 0.01  # calibration uncertainty + one stage step (0.0025 deg)
