"""The proof suite's plan of detection-limit fits (`benchmarks/bench_diagnose.py`)."""

import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import bench_diagnose as bd


def test_optimum_gain_plan_leaves_out_each_effect_of_a_pair_and_both():
    plan = bd.optimum_gain_plan(bd.cases(quick=False))
    by_case: dict[str, list[list[str]]] = {}
    for case, left in plan:
        by_case.setdefault(case["id"], []).append(left)
    assert by_case["beam_halo-1"] == [["beam_halo"]]
    assert by_case["clean-1"] == [[]]
    pair = "sensor_nonlinearity+filter_bandwidth"
    assert sorted(map(tuple, by_case[pair])) == [("filter_bandwidth",), ("filter_bandwidth", "sensor_nonlinearity"),
                                                 ("sensor_nonlinearity",)]
    # every single-effect and clean case once, every pair three times
    n_pairs = len(bd.PAIRS)
    assert len(plan) == len(bd.cases(quick=False)) + 2 * n_pairs


def test_bic_threshold_counts_free_parameters_only():
    n = 400
    # the sensor's full-well radiance is held, so one free parameter: ln n + BIC_STRONG
    one = bd.bic_threshold(["sensor_nonlinearity"], n)
    two = bd.bic_threshold(["beam_halo"], n)
    assert math.isclose(one, math.log(n) + 10.0)
    assert math.isclose(two, 2 * math.log(n) + 10.0)
    assert math.isnan(bd.bic_threshold([], n))


def test_select_cases_keeps_the_given_order_and_rejects_unknown_ids():
    plan = bd.cases(quick=False)
    got = bd.select_cases(plan, "clean-2,refractive_boundary+beam_halo,clean-2,beam_halo-1")
    assert [c["id"] for c in got] == ["clean-2", "refractive_boundary+beam_halo", "beam_halo-1"]
    with pytest.raises(ValueError, match="no_such_case"):
        bd.select_cases(plan, "clean-1,no_such_case")


def _row(id_: str, concealed: list[str], named: list[str], before: tuple[float, float],
         after: tuple[float, float]) -> dict:
    err = lambda e: {"sigma_t_rel": e[0], "albedo_abs": e[1]}
    return {"id": id_, "concealed": concealed, "named": named,
            "material_error": {"before": err(before), "after": err(after)}}


def test_material_fallback_bars_named_cases_by_the_clean_sessions_largest_errors():
    rows = [_row("clean-1", [], [], (0.018, 0.004), (0.018, 0.004)),
            _row("clean-2", [], [], (0.008, 0.006), (0.008, 0.006)),
            _row("a-1", ["a"], ["a"], (0.10, 0.02), (0.005, 0.002)),
            # sigma_t back within the clean sessions' but the albedo is not
            _row("b-1", ["b"], ["b"], (0.10, 0.02), (0.010, 0.014)),
            # named nothing: not a refit, not counted
            _row("c-1", ["c"], [], (0.05, 0.01), (0.05, 0.01))]
    mf = bd.material_fallback(rows)
    assert mf["named_cases"] == 2 and mf["fraction"] == 0.5 and mf["beyond"] == ["b-1"]
    assert mf["clean_sigma_t_rel_max"] == 0.018 and mf["clean_albedo_abs_max"] == 0.006
    assert mf["named_albedo_abs_max"] == 0.014
    assert bd.material_fallback(rows[2:]) is None  # no clean session to compare with
    assert bd.material_fallback(rows[:2]) is None  # nothing named


def test_a_base_fit_from_another_recording_is_refused_in_one_line(tmp_path):
    """`--base-from` takes each case's base fit from another run's cache: one made on other
    recordings (another excess noise or window) is refused, naming the setting to give.
    The settings come from the case result where recorded, else the cache's name."""
    import json

    old = tmp_path / "synthetic-v11-excess0-spp512"
    old.mkdir()
    (old / "clean-1.json").write_text(json.dumps({"base_fit_spp": 1024}))
    prior = json.loads((old / "clean-1.json").read_text())
    bd._check_recording(old / "clean-1.json", prior, 0.0, bd.SYNTHETIC_COLUMNS)
    with pytest.raises(ValueError, match=r"excess 0, not 30 \(give --excess 0"):
        bd._check_recording(old / "clean-1.json", prior, 30.0, bd.SYNTHETIC_COLUMNS)
    with pytest.raises(ValueError, match=r"40-px window, not 256 \(give --columns 40"):
        bd._check_recording(old / "clean-1.json", prior, 0.0, 256)
    new = tmp_path / "copied"
    new.mkdir()
    rec = {"base_fit_spp": 1024, "recording": {"excess": 0.0, "columns": 256}}
    bd._check_recording(new / "clean-1.json", rec, 0.0, 256)
    with pytest.raises(ValueError, match="excess 0, not 30"):
        bd._check_recording(new / "clean-1.json", rec, 30.0, 256)
    bd._check_recording(new / "clean-1.json", {"base_fit_spp": 1024}, 30.0, 256)   # nothing to tell by


def _result(named: list[str]) -> dict:
    mat = {"sigma_t": 2.1, "albedo": 0.88}
    return {"confirmed_effects": {n: {} for n in named}, "candidates": [{"name": "stray_light"}],
            "truth": {"sigma_t": 2.0, "albedo": 0.9}, "material_before": mat, "material_after": mat,
            "significant": True, "reduced_chi2_before": 2.0, "reduced_chi2_after": 2.0}


def test_outside_the_catalogue_a_case_is_right_only_when_nothing_is_named():
    """The out-of-catalogue series (a two-lobe phase function fitted with one lobe): no
    effect is concealed, so any name is a wrong cause; its cases are scored and reported
    apart from the clean sessions, and do not set the clean sessions' error bar."""
    plan = bd.outside_cases()
    assert [c["id"] for c in plan] == [f"phase_two_lobe-{k + 1}" for k in range(len(bd.OUTSIDE_PHASES))]
    assert all(c["effects"] == {} and c["truth_phase"]["model"] == "tthg" for c in plan)
    right = bd.score(plan[0], _result([]))
    wrong = bd.score(plan[1], _result(["stray_light"]))
    assert right["outside"] and right["ok"] and wrong["outside"] and not wrong["ok"]
    clean = bd.score({"id": "clean-1", "effects": {}}, _result([]))
    assert not clean["outside"] and clean["ok"]
    text, summary = bd.report([right, wrong, clean], "synthetic", 3, 3)
    assert summary["outside_nothing_named"] == 0.5 and summary["clean_nothing_named"] == 1.0
    assert "| nothing named outside the catalogue (no wrong cause) | 50 % of 2 |" in text
    # an out-of-catalogue case's errors (its base fit misfits the phase) are not a clean
    # session's: the bar stays the clean session's own
    far = {**right, "material_error": {"before": {"sigma_t_rel": 0.2, "albedo_abs": 0.05},
                                       "after": {"sigma_t_rel": 0.2, "albedo_abs": 0.05}}}
    rows = [far, _row("clean-1", [], [], (0.01, 0.004), (0.01, 0.004)),
            _row("a-1", ["a"], ["a"], (0.10, 0.02), (0.05, 0.002))]
    mf = bd.material_fallback(rows)
    assert mf["clean_sigma_t_rel_max"] == 0.01 and mf["beyond"] == ["a-1"]
