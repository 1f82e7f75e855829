"""World files: the default and example worlds parse; every mistake is one line naming file and key."""

from pathlib import Path

import pytest
import yaml

from sim_devices.world import (
    DEFAULT_WORLD_PATH,
    WorldError,
    beam_map,
    check_filters,
    load_world,
    parse_world,
)

WORLDS = Path(__file__).resolve().parent.parent / "worlds"

MINIMAL = {
    "slab": {"thickness_mm": 1.0},
    "materials": {"r": {"sigma_t": 2.0, "albedo": 0.9, "phase": {"type": "exp", "b": [1.0, 0.2]}}},
    "beam": {"profile": {"type": "gaussian", "sigma_mm": 0.3}, "power_e_per_s": {"r": 1.0e10}},
}


def _with(path: tuple, value):
    d = yaml.safe_load(yaml.safe_dump(MINIMAL))
    node = d
    for k in path[:-1]:
        node = node.setdefault(k, {})
    node[path[-1]] = value
    return d


def test_default_world_is_clean_and_documented():
    w = load_world(None)
    assert w.effects == {}
    assert set(w.materials) == {"r", "g", "b"}
    assert w.stage_zero_error_deg != 0.0  # calibrate-beam has something to find
    assert DEFAULT_WORLD_PATH.exists()
    assert "(default world)" in w.source


@pytest.mark.parametrize("name", ["default.yaml", "refractive.yaml", "optics.yaml"])
def test_example_worlds_parse(name):
    w = load_world(WORLDS / name)
    for m in w.materials.values():
        assert m.parameters()["sigma_t"] > 0
    for vals in w.effects.values():
        assert vals  # every effect has its parameters filled in


def test_phase_kinds_map_to_forward_model_names():
    d = _with(("materials", "g"), {"sigma_t": 1.0, "albedo": 0.5, "phase": {"type": "hg", "g": 0.3}})
    d["materials"]["b"] = {"sigma_t": 1.0, "albedo": 0.5,
                           "phase": {"type": "tthg", "g_forward": 0.7, "g_backward": -0.2, "w_forward": 0.8}}
    d["beam"]["power_e_per_s"].update({"g": 1.0, "b": "2.0e10"})  # YAML 1.1 reads 2.0e10 as text
    w = parse_world(d, "w.yaml")
    assert w.materials["r"].model == "exp2" and w.materials["r"].phase_params == {"phase.b1": 1.0, "phase.b2": 0.2}
    assert w.materials["g"].model == "hg"
    assert w.materials["b"].model == "tthg" and w.materials["b"].phase_params["phase.w_forward"] == 0.8
    assert w.beam.power_e_per_s["b"] == 2.0e10


def test_mie_phase_is_fitted_by_an_exponential_of_the_set_degree():
    d = _with(("materials", "r", "phase"), {"type": "mie", "dispersion": "mono", "diameter_um": 0.3,
                                            "wavelength_nm": 600})
    d["render"] = {"mie_degree": 4}
    w = parse_world(d, "mie.yaml")
    assert w.materials["r"].model == "exp4"
    assert w.materials["r"].phase_params["phase.b1"] > 0  # forward scattering


def test_mie_phase_can_be_rendered_from_its_table():
    """`render.mie_phase: table` renders the Mie table itself (model "table", no phase
    parameters); the truth hash tells it from the exp fit, and `mie_phase: exp` (the default)
    keeps the hash of worlds written before the key existed."""
    phase = {"type": "mie", "dispersion": "poly", "diameter_um": 0.5, "spread": 0.1, "wavelength_nm": 600}
    d = _with(("materials", "r", "phase"), phase)
    d["render"] = {"mie_phase": "table"}
    w = parse_world(d, "mie.yaml")
    m = w.materials["r"]
    assert m.model == "table" and m.phase_params == {} and m.parameters() == {"sigma_t": 2.0, "albedo": 0.9}
    assert m.phase_table is not None and m.phase_table.g == pytest.approx(0.846, abs=0.002)
    plain = _with(("materials", "r", "phase"), phase)
    fitted = parse_world(plain, "mie.yaml")
    assert fitted.materials["r"].model == "exp8" and fitted.materials["r"].phase_table is None
    assert fitted.truth_hash() != w.truth_hash()
    plain["render"] = {"mie_phase": "exp"}
    assert parse_world(plain, "mie.yaml").truth_hash() == fitted.truth_hash()


def test_unknown_mie_phase_is_one_line_naming_the_key():
    d = _with(("render",), {"mie_phase": "tabel"})
    with pytest.raises(WorldError) as e:
        parse_world(d, "w.yaml")
    msg = str(e.value)
    assert "\n" not in msg and "mie_phase" in msg and "table" in msg and "w.yaml" in msg


def test_effects_take_defaults_and_hash_changes_with_truth():
    a = parse_world(MINIMAL, "a.yaml")
    b = parse_world(_with(("effects",), {"lens_blur": {"core_sigma_px": 1.0}}), "b.yaml")
    assert b.effects["lens_blur"]["core_sigma_px"] == 1.0
    assert b.effects["lens_blur"]["tail_scale_px"] == 20.0
    assert a.truth_hash() != b.truth_hash()
    assert a.truth_hash() == parse_world(MINIMAL, "elsewhere.yaml").truth_hash()


def test_beam_maps_have_unit_power():
    for prof in ({"type": "gaussian", "sigma_mm": 0.3}, {"type": "disk", "radius_mm": 0.5, "edge_mm": 0.02}):
        w = parse_world(_with(("beam", "profile"), prof), "w.yaml")
        e, pitch = beam_map(w)
        assert abs(e.sum() * pitch ** 2 - 1.0) < 1e-9


def test_map_profile_from_npy(tmp_path):
    import numpy as np

    np.save(tmp_path / "beam.npy", np.outer(np.hanning(9), np.hanning(9)))
    (tmp_path / "w.yaml").write_text(yaml.safe_dump(_with(("beam", "profile"),
                                                          {"type": "map", "file": "beam.npy", "pitch_mm": 0.05})))
    w = load_world(tmp_path / "w.yaml")
    e, pitch = beam_map(w)
    assert pitch == 0.05 and e.shape == (9, 9)


@pytest.mark.parametrize("path,value,words", [
    (("slab", "thickness_mm"), -1.0, ["slab.thickness_mm", "outside"]),
    (("materials", "r", "albedo"), 1.5, ["materials.r.albedo"]),
    (("materials", "r", "phase"), {"type": "rayleigh"}, ["materials.r.phase.type", "unknown phase type"]),
    (("materials", "r", "phase"), {"type": "exp", "b": []}, ["materials.r.phase.b"]),
    (("beam", "profile"), {"type": "square"}, ["beam.profile.type"]),
    (("beam", "power_e_per_s"), {"g": 1.0}, ["beam.power_e_per_s.r", "missing"]),
    (("effects",), {"lens_flare": {}}, ["effects.lens_flare", "unknown effect", "lens_blur"]),
    (("effects",), {"lens_blur": {"sigma": 1}}, ["effects.lens_blur.sigma", "unknown key"]),
    (("effects",), {"sensor_nonlinearity": {"compression": 0.4}}, ["sensor_nonlinearity.compression"]),
    (("stage", "zero_error_deg"), 12.0, ["stage.zero_error_deg"]),
    (("optics", "axis_px"), [1.0], ["optics.axis_px"]),
    (("sensor", "read_noise"), 5.0, ["sensor.read_noise", "unknown key"]),
    (("colour",), "red", ["colour", "unknown key"]),
])
def test_errors_are_one_line_with_file_and_key(path, value, words):
    with pytest.raises(WorldError) as e:
        parse_world(_with(path, value), "bad.yaml")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("bad.yaml: ")
    for w in words:
        assert w in msg


def test_file_errors(tmp_path):
    with pytest.raises(WorldError, match="no such world file"):
        load_world(tmp_path / "missing.yaml")
    (tmp_path / "bad.yaml").write_text("slab: [1,\n")
    with pytest.raises(WorldError, match=r"bad.yaml: line \d+: not valid YAML"):
        load_world(tmp_path / "bad.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n")
    with pytest.raises(WorldError, match="must be a YAML mapping"):
        load_world(tmp_path / "list.yaml")


def test_rig_filters_must_all_have_a_material():
    w = parse_world(MINIMAL, "w.yaml")
    check_filters(w, ["r"])
    with pytest.raises(WorldError, match="no entry for filter 'g'"):
        check_filters(w, ["r", "g"])
