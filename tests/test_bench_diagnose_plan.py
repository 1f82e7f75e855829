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


def _signed(id_: str, concealed: list[str], named: list[str], after: tuple[float, float],
            unc: tuple[float, float] | None) -> dict:
    e = {"sigma_t_rel": after[0], "albedo_abs": after[1],
         "sigma_t_rel_unc": unc[0] if unc else None, "albedo_abs_unc": unc[1] if unc else None}
    return {"id": id_, "concealed": concealed, "named": named, "material_signed": {"before": e, "after": e}}


def test_material_consistency_holds_named_cases_against_the_clean_mean_within_their_intervals():
    # the clean sessions' errors +0.2 .. +0.4 %: the estimator's own bias at this setting
    rows = [_signed(f"clean-{k}", [], [], (e, 0.0), (0.003, 0.0003)) for k, e in enumerate((0.002, 0.003, 0.004))]
    rows += [_signed("a-1", ["a"], ["a"], (0.006, 0.0002), (0.003, 0.0003)),       # 1 sigma above: at the level
             _signed("b-1", ["b"], ["b"], (0.003, 0.0012), (0.003, 0.0003)),       # the albedo 4 sigma off
             _signed("c-1", ["c"], ["c"], (-0.006, 0.0), (0.002, 0.0003)),         # sigma_t 4.2 sigma below
             _signed("d-1", ["d"], [], (0.2, 0.05), (0.003, 0.0003))]               # named nothing: not counted
    mc = bd.material_consistency(rows)
    assert mc["named_cases"] == 3 and mc["clean_cases"] == 3 and not mc["clean_intervals_proxied"]
    st = mc["sigma_t_rel"]
    assert st["clean_mean"] == pytest.approx(0.003) and st["clean_se"] == pytest.approx(0.003 / math.sqrt(3))
    assert mc["z"]["a-1"]["sigma_t_rel"] == pytest.approx(0.003 / math.sqrt(0.003 ** 2 + 0.003 ** 2 / 3))
    assert mc["beyond"] == ["b-1", "c-1"] and mc["fraction"] == pytest.approx(1 / 3)
    assert st["named_mean"] == pytest.approx(0.001)
    # clean fits recorded without intervals take the named cases' median, and say so
    old = [_signed(r["id"], r["concealed"], r["named"], (r["material_signed"]["after"]["sigma_t_rel"],
                                                         r["material_signed"]["after"]["albedo_abs"]),
                   None if not r["concealed"] else (0.003, 0.0003)) for r in rows]
    mc_old = bd.material_consistency(old)
    assert mc_old["clean_intervals_proxied"] and mc_old["sigma_t_rel"]["clean_se"] == pytest.approx(0.003 / math.sqrt(3))
    # a named case without its interval cannot be judged; nothing to compare without clean cases
    assert bd.material_consistency(rows[:3] + [_signed("e-1", ["e"], ["e"], (0.0, 0.0), None)]) is None
    assert bd.material_consistency(rows[3:]) is None
    # end to end from the diagnoses' JSON (`score`, `report`): the base fits' intervals are
    # `material_uncertainty_before`, a refit's `material_uncertainty_after`
    def res(named: list[str], err: tuple[float, float]) -> dict:
        mat = {"sigma_t": 2.0 * (1 + err[0]), "albedo": 0.9 + err[1]}
        unc = {"sigma_t": 0.006, "albedo": 0.0003}
        return {**_result(named), "material_before": mat, "material_after": mat,
                "material_uncertainty_before": unc, "material_uncertainty_after": unc if named else {}}

    scored = [bd.score({"id": r["id"], "effects": {c: {} for c in r["concealed"]}},
                       res(r["named"], (r["material_signed"]["after"]["sigma_t_rel"],
                                        r["material_signed"]["after"]["albedo_abs"])), "bench") for r in rows]
    text, summary = bd.report(scored, "bench", 7, 7)
    assert summary["material_consistency"]["beyond"] == ["b-1", "c-1"]
    assert "33 % of 3 named cases; beyond: b-1 (z +3.5), c-1 (z -2.6)" in text
    assert "c-1 sigma_t -2.60, c-1 albedo +0.00" in text


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
