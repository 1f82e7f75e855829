"""The paper simulation's table (`benchmarks/paper_sim_table.py`): rows, targets, summary."""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import paper_sim_table as pst


def _fit(case: str, model: str, sigma_t: float, albedo: float, loss: float, kept: str | None = None,
         unbiased: float | None = None) -> dict:
    d, s = case[1:].split("_s")
    row = {"case": case, "diameter_um": float(d), "sigma_t_true": float(s), "model": kept or model,
           "requested_model": model, "sigma_t": sigma_t, "albedo": albedo,
           "sigma_t_rel_error": abs(sigma_t / float(s) - 1), "albedo_abs_error": abs(albedo - 0.9),
           "loss_ratio": loss, "time_s": 12.0, "uncertainties": {"sigma_t": 0.1},
           "sigma_a_rel_error": 0.01, "reduced_scattering_rel_error": 0.02}
    if unbiased is not None:
        row["loss_unbiased_ratio"] = unbiased
    return row


def test_rows_follow_the_papers_case_order_and_judge_the_loss_without_render_noise(tmp_path, capsys):
    first = {"fits": [_fit("d0.01_s6", "exp3", 6.1, 0.9, 0.9, unbiased=1.2),
                      _fit("d0.5_s2", "exp3", 2.1, 0.905, 1.0, unbiased=1.05),
                      _fit("d0.5_s2", "tthg", 1.0, 0.7, 9.0)]}
    later = {"fits": [_fit("d0.5_s2", "expauto", 2.02, 0.9, 1.0, kept="exp7", unbiased=1.01)]}
    files = []
    for i, doc in enumerate((first, later)):
        files.append(tmp_path / f"r{i}.json")
        files[-1].write_text(json.dumps(doc))
    assert pst.main([str(f) for f in files]) == 0
    lines = capsys.readouterr().out.splitlines()
    body = [ln for ln in lines if ln.startswith("| d") or ln.startswith("|  |")]
    # sigma_t 2 before 6; within a case the models in the order first seen
    assert body[0].startswith("| d 0.5 um, sigma_t 2 | exp3 | exp3 | 1.00 | 1.05 | +5.00 % (z +1.0) | 0.0050 |")
    assert body[0].endswith("| albedo, loss |")  # sigma_t 5 % off
    assert body[1].startswith("|  | tthg |") and body[1].endswith("| none |")  # no unbiased loss: the plain 9.0
    assert body[2].startswith("|  | expauto | exp7 |") and body[2].endswith("| all |")
    assert body[3].startswith("| d 0.01 um, sigma_t 6 | exp3 |") and body[3].endswith("| sigma_t, albedo |")
    summary = "\n".join(lines)
    assert "**exp3**: all three targets on 0 of 2; sigma_t 1, albedo 2, loss 1; 12-12 s a fit." in summary
    assert "**expauto**: all three targets on 1 of 1" in summary
    assert "The lowest loss without render noise: d0.5_s2 expauto." in summary


def test_a_later_file_replaces_a_fit_and_near_equal_losses_are_a_tie():
    rows = pst.collect([{"fits": [_fit("d0.3_s2", "exp3", 2.5, 0.9, 3.0)]},
                        {"fits": [_fit("d0.3_s2", "exp3", 2.0, 0.9, 1.04)]}])
    assert rows[("d0.3_s2", "exp3")]["sigma_t"] == 2.0
    by = {"exp3": _fit("d0.3_s2", "exp3", 2.0, 0.9, 1.040), "expauto": _fit("d0.3_s2", "expauto", 2.0, 0.9, 1.045),
          "tthg": _fit("d0.3_s2", "tthg", 2.0, 0.9, 1.3)}
    assert pst.lowest(by) == "exp3 = expauto"


def test_an_unreadable_file_is_one_line_and_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    assert pst.main([str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot read" in err and str(bad) in err


def test_an_unbiased_ratio_over_several_seed_pairs_is_shown_with_its_standard_error(tmp_path, capsys):
    row = _fit("d0.5_s6", "exp7", 6.1, 0.9, 1.0, unbiased=1.034)
    row["loss_unbiased_ratio_se"] = 0.0123
    (tmp_path / "r.json").write_text(json.dumps({"fits": [row]}))
    assert pst.main([str(tmp_path / "r.json")]) == 0
    body = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("| d")]
    assert body[0].startswith("| d 0.5 um, sigma_t 6 | exp7 | exp7 | 1.00 | 1.03 +- 0.01 | ")
