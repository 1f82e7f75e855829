"""`rig estimate` / `rig report` end to end on a tiny synthetic session."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from synth_session import make_session

from rig.cli import main

TRUTH = {"sigma_t": 3.0, "albedo": 0.85, "phase.b1": 3.0}


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    return make_session(tmp_path_factory.mktemp("c") / "s", {"g": TRUTH, "r": TRUTH}, angles=[30, 150],
                        spp=256, width=64, scale=2e5, skip=["a01_r"])


def test_json_shape_and_runs_never_overwritten(session, capsys):
    argv = ["estimate", str(session), "--channels", "g", "--columns", "32", "--max-iterations", "4",
            "--spp-max", "128", "--polish-steps", "2", "--json"]
    assert main(argv) == 0
    out = json.loads(capsys.readouterr().out)
    (run,) = out["runs"]
    ch = run["channels"]["g"]
    assert run["model"] == "exp3"
    assert set(ch) >= {"model", "sigma_t", "albedo", "phase", "uncertainties", "reduced_chi2"}
    assert set(ch["phase"]) == {"phase.b1", "phase.b2", "phase.b3"}
    assert set(ch["uncertainties"]) == {"sigma_t", "albedo", "phase.b1", "phase.b2", "phase.b3"}
    # sigma_a and sigma_s' (what thick slabs determine) with propagated uncertainties
    d = ch["derived"]
    assert d["sigma_a"]["value"] == pytest.approx(ch["sigma_t"] * (1 - ch["albedo"]))
    assert d["sigma_a"]["unit"] == "1/mm" and d["sigma_s_reduced"]["uncertainty"] > 0
    results = Path(run["path"]) / "results.yaml"
    doc = yaml.safe_load(results.read_text())
    assert doc["channels"]["g"]["derived"]["sigma_s_reduced"]["value"] == pytest.approx(d["sigma_s_reduced"]["value"])
    cov = doc["channels"]["g"]["covariance"]
    assert cov["sigma_t"]["sigma_t"] == pytest.approx(ch["uncertainties"]["sigma_t"] ** 2)
    assert cov["sigma_t"]["albedo"] == pytest.approx(cov["albedo"]["sigma_t"])
    assert doc["format"] == "rig-estimate/1" and doc["channels"]["g"]["iterations"] == 4
    # The budget flags: two polish steps (four at most, while the last ones still walk); the
    # final evaluation at 2 x --spp-max, and the uncertainties' Jacobian (512 by default) no
    # finer than that.
    fit = doc["settings"]["fit"]
    assert 2 <= len(doc["channels"]["g"]["polish"]) <= 4 and fit["polish_steps"] == 2
    assert fit["final_spp"] == 256 and fit["uncertainty_spp"] == 256
    # The renders' backend is recorded (this process's variant: the CPU's without a GPU).
    from estimate.mitsuba_env import default_variant

    assert doc["software"]["mitsuba_variant"] == default_variant()
    stages = doc["channels"]["g"]["stage_times_s"]
    assert list(stages) == ["start", "iterations", "polish", "evaluation", "uncertainties"]
    assert 0 < sum(stages.values()) <= doc["channels"]["g"]["time_s"] + 0.05   # rounded to 0.01 s each
    # Default: the calibrated scale (beam power x pixel area x the lens's collection solid angle).
    assert doc["settings"]["scale"] == "calibrated" and doc["settings"]["fit"]["scale"] == "calibrated"
    assert doc["channels"]["g"]["scale"] == pytest.approx(2e5)
    assert doc["settings"]["scale_calibration"]["g"]["scale"] == pytest.approx(2e5)
    first = results.read_text()
    assert main(argv) == 0
    second = json.loads(capsys.readouterr().out)["runs"][0]["path"]
    assert second != run["path"] and results.read_text() == first
    # The report gathers both runs into one page.
    assert main(["report", str(session)]) == 0
    html_path = capsys.readouterr().out.strip().splitlines()[-1]
    html = Path(html_path).read_text()
    assert run["run_id"] in html and "data:image/png;base64," in html
    # No Python reprs in the tables: a calibrated scale says where it came from, nothing reads None.
    assert "<td>from the calibration</td>" in html and ">None<" not in html and "{'" not in html
    # The light engine by default (estimate.light_paths), named in the run and the report.
    assert fit["engine"] == "light" and "render engine light" in html


def test_engine_flag_chooses_the_forward_models_renderer(session, capsys):
    argv = ["estimate", str(session), "--channels", "g", "--columns", "32", "--max-iterations", "2",
            "--spp-max", "32", "--polish-steps", "1", "--engine", "camera", "--json"]
    assert main(argv) == 0
    (run,) = json.loads(capsys.readouterr().out)["runs"]
    doc = yaml.safe_load((Path(run["path"]) / "results.yaml").read_text())
    assert doc["settings"]["fit"]["engine"] == "camera"
    assert main(["estimate", str(session), "--engine", "photons"]) == 2
    err = capsys.readouterr().err
    assert "invalid choice" in err and "Traceback" not in err


def test_report_cells_round_floats_wherever_they_are():
    """YAML gives full-precision floats; a cell shows 5 significant digits, also inside lists
    and mappings, a missing value as "-"."""
    from rig.report import _fmt

    assert _fmt(8.109064234910571e-07) == "8.1091e-07"
    assert _fmt([258.29982094409644, 253.600102204556]) == "[258.3, 253.6]"
    assert _fmt({"rig": "0.1.0", "width_mm": (0.24985426399829674, 0.25)}) == "rig 0.1.0, width_mm [0.24985, 0.25]"
    assert _fmt(None) == "-" and _fmt({}) == "-" and _fmt(True) == "True" and _fmt(3) == "3"


def test_report_degree_table_tolerates_hand_edits():
    """A run without a degree search shows none; a hand-edited one is named, not a traceback."""
    from rig.report import _degree_choice

    assert _degree_choice(None) == "" and _degree_choice({}) == ""
    assert "g: the degree choice is not readable" in _degree_choice({"g": {"steps": "oops"}})
    page = _degree_choice({"r": {"chosen": 4, "stopped": "reached exp4", "steps": [
        {"degree": 3, "chi2_adjusted": 120.0, "gain": float("nan"), "gain_se": float("nan"), "accepted": True},
        {"degree": 4, "chi2_adjusted": 90.0, "gain": 25.5, "gain_se": 3.25, "accepted": True}, "junk"]}})
    assert "<td>+25.5 +- 3.2</td>" in page and "r: kept exp4 (reached exp4)" in page and page.count("<tr>") == 3
    # A close call decided over more seed pairs says so (runs since session 81).
    page = _degree_choice({"r": {"chosen": 4, "seeds": 4, "steps": [
        {"degree": 4, "chi2_adjusted": 90.0, "gain": 60.5, "gain_se": 9.0, "gain_pairs": 16, "accepted": True},
        {"degree": 5, "chi2_adjusted": 89.0, "gain": -7.0, "gain_se": 2.0, "gain_pairs": 4, "accepted": False}]}})
    assert "<td>+60.5 +- 9.0 (16 pairs)</td>" in page and "<td>-7.0 +- 2.0</td>" in page
    assert "(16 pairs)" not in _degree_choice({"r": {"chosen": 4, "seeds": "four", "steps": [
        {"degree": 4, "chi2_adjusted": 90.0, "gain": 60.5, "gain_se": 9.0, "gain_pairs": 16, "accepted": True}]}})


def test_report_shows_the_lm_stages_of_a_channel(tmp_path):
    """A high-degree fit's Levenberg-Marquardt stages: spp and steps each, and the last one's
    render-noise share of the floor and why it stopped; a channel without them has no row."""
    from rig.report import _run_section

    ch = {"parameters": {"sigma_t": 2.0}, "uncertainties": {"sigma_t": 0.03}, "scale": 1.0, "loss": 1e-6,
          "reduced_chi2": 1.2, "iterations": 10, "time_s": 113.0}
    lm = [{"spp": 4096, "steps": 3, "losses": [1.0, 0.5], "stop": "no step lowered the loss", "noise_excess": 0.33},
          {"spp": 16384, "steps": 3, "losses": [0.6, 0.5], "stop": "a step gained under 0.1% of the loss",
           "noise_excess": 0.0712345}]
    doc = {"run_id": "r1", "settings": {"model": "exp10"}, "channels": {"g": {**ch, "levenberg_marquardt": lm},
                                                                        "r": dict(ch)}}
    page = "".join(_run_section(tmp_path, doc))
    assert "<td>4096: 3, 16384: 3</td>" in page and page.count("Levenberg-Marquardt stages") == 1
    assert "render-noise share of the floor 0.071235; a step gained under 0.1% of the loss" in page


@pytest.mark.parametrize("extra, message", [
    (["--channels", "r"], "a01_r (not captured)"),
    (["--channels", "x"], "unknown channel 'x'"),
    (["--polish-steps", "-1"], "--polish-steps -1: use 0..20"),
    (["--spp-max", "0"], "--spp-max 0: use a positive number"),
    (["--final-spp", "1"], "--final-spp 1: use at least 2 samples per pixel"),
    (["--degree", "three"], "--degree three: use a whole number 0..12 or auto"),
    (["--degree", "13"], "--degree 13: use 0..12 or auto"),
    (["--degree-spp-max", "4096"], "--degree-spp-max 4096: only --degree auto compares degrees"),
    (["--degree", "auto", "--degree-spp-max", "0"], "--degree-spp-max 0: use a positive number"),
    (["--degree-max", "9"], "--degree-max 9: only --degree auto searches degrees; add --degree auto, or give "
                            "the degree itself with --degree 9"),
    (["--degree", "auto", "--degree-max", "2"], "--degree-max 2: use 3..12 (the search starts at exp3)"),
    (["--degree", "auto", "--degree-max", "13"], "--degree-max 13: use 3..12"),
    (["--channels", ","], "--channels ',': names nothing"),
    (["--channels", "gg"], "--channels 'gg': channel 'g' is named twice"),
    (["--columns", "0"], "--columns 0: use at least 2 pixels"),
    (["--seed", "-1"], "--seed -1: use a whole number >= 0"),
    (["--extensions", "stray_light,moonlight"], "--extensions 'stray_light,moonlight': unknown extension "
                                                "'moonlight'; choose from "),
    (["--extensions", "stray_light,stray_light"], "extension 'stray_light' is named twice"),
    (["--extensions", ","], "--extensions ',': names nothing"),
    (["--time-limit", "0"], "--time-limit 0: give a positive number of seconds"),
    (["--time-limit", "nan"], "--time-limit nan: give a positive number of seconds"),
])
def test_bad_input_one_line_exit_2(session, capsys, extra, message):
    runs = sorted((session / "estimates").glob("*")) if (session / "estimates").is_dir() else []
    assert main(["estimate", str(session), "--max-iterations", "1", *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
    # no run directory, not even an empty one, is left behind
    assert (sorted((session / "estimates").glob("*")) if (session / "estimates").is_dir() else []) == runs


def test_time_limit_bounds_each_fit_and_the_run_says_what_it_cut(session, capsys):
    """`--time-limit` is the fit's budget (FitSettings.time_limit_s, recorded in the run): a
    spent one stops the iterations after one and starts no polish step, and the run still
    has its evaluation and intervals."""
    argv = ["estimate", str(session), "--channels", "g", "--columns", "32", "--spp-max", "32", "--polish-steps", "2",
            "--time-limit", "1e-6", "--json"]
    assert main(argv) == 0
    (run,) = json.loads(capsys.readouterr().out)["runs"]
    ch = run["channels"]["g"]
    assert ch["iterations"] == 1 and ch["stop_reason"].startswith("time_limit; the time limit cut the Gauss-Newton")
    assert all(v > 0 for v in ch["uncertainties"].values())
    doc = yaml.safe_load((Path(run["path"]) / "results.yaml").read_text())
    assert doc["settings"]["fit"]["time_limit_s"] == 1e-6 and doc["channels"]["g"]["polish"] == []


def test_a_window_wider_than_the_stacks_is_said(session, capsys):
    assert main(["estimate", str(session), "--channels", "g", "--columns", "100000", "--max-iterations", "1",
                 "--polish-steps", "0", "--spp-max", "16"]) == 0
    err = capsys.readouterr().err
    assert "note: --columns 100000 is wider than the stacks' window; fitting 64 pixels" in err


def test_unwritable_estimates_folder_fails_before_fitting(session, tmp_path, capsys, monkeypatch):
    """A session whose estimates/ cannot be written is refused before the fit (which would
    otherwise be lost), in one line; what is there stays as it was."""
    import shutil

    import estimate.fit

    copy = tmp_path / "s"
    shutil.copytree(session, copy, ignore=shutil.ignore_patterns("estimates"))
    (copy / "estimates").write_text("not a folder")
    monkeypatch.setattr(estimate.fit, "fit_channel", lambda *a, **k: pytest.fail("fitted"))
    assert main(["estimate", str(copy), "--channels", "g", "--columns", "32", "--max-iterations", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "estimates is a file" in err and len(err.splitlines()) == 1 and "Traceback" not in err
    assert (copy / "estimates").read_text() == "not a folder"


def test_report_shows_a_hand_edited_run_and_refuses_an_unwritable_page(session, tmp_path, capsys):
    """A results.yaml of the wrong shape is named in the page (the other runs still shown), not a
    traceback; a report that cannot be written is one line, exit 2."""
    import shutil

    copy = tmp_path / "s"
    shutil.copytree(session, copy, ignore=shutil.ignore_patterns("estimates", "report.html"))
    for name, doc in (("20260101T000000_exp3", {"channels": {"g": {}}}),
                      ("20260101T000001_exp3", {"run_id": "x", "channels": ["g"]}),
                      ("20260101T000002_exp3", {"run_id": "y", "settings": "oops"})):
        (copy / "estimates" / name).mkdir(parents=True)
        (copy / "estimates" / name / "results.yaml").write_text(yaml.safe_dump({"format": "rig-estimate/1", **doc}))
    assert main(["report", str(copy)]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    html = (copy / "report.html").read_text()
    assert html.count("results.yaml: malformed (") == 3 and "KeyError" in html and "AttributeError" in html
    for out, needle in ((tmp_path / "nowhere" / "r.html", "does not exist"), (tmp_path, "it is a folder")):
        assert main(["report", str(copy), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert needle in err and "--out" in err and len(err.splitlines()) == 1 and "Traceback" not in err


def test_free_scale_is_fitted(session, capsys):
    # --final-spp after --spp-max: the polish and final evaluation take it, the uncertainties
    # at most it.
    assert main(["estimate", str(session), "--channels", "g", "--columns", "32", "--max-iterations", "2",
                 "--spp-max", "64", "--final-spp", "96", "--scale", "free", "--json"]) == 0
    (run,) = json.loads(capsys.readouterr().out)["runs"]
    doc = yaml.safe_load((Path(run["path"]) / "results.yaml").read_text())
    assert doc["settings"]["fit"]["final_spp"] == 96 and doc["settings"]["fit"]["uncertainty_spp"] == 96
    assert doc["settings"]["scale"] == "free" and doc["settings"]["scale_calibration"] == {}
    assert doc["channels"]["g"]["scale"] != pytest.approx(2e5, rel=1e-6)


def test_extension_parameters_are_printed(session, capsys, monkeypatch):
    # Every reduced chi2 lies above a hint level of -1: the summary points at `rig diagnose`.
    monkeypatch.setattr("rig.commands.estimate.CHI2_HINT", -1.0)
    assert main(["estimate", str(session), "--channels", "g", "--columns", "32", "--max-iterations", "2",
                 "--spp-max", "64", "--extensions", "stray_light"]) == 0
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if "stray_light.offset" in ln)
    assert "stray_light.slope_per_mm" in line and "(solved each iteration)" in line
    assert f"`rig diagnose {session}` tells that from a mismatch" in out


def test_missing_session_exit_2(tmp_path, capsys):
    assert main(["estimate", str(tmp_path / "nope")]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_live_status_names_each_stage_on_a_terminal_and_draws_nothing_off_it(session):
    """The fit reports its stages in order; on a terminal the status line shows each stage and
    the iterations' spp and loss, and off a terminal (a log, a pipe) nothing is drawn."""
    import io

    from rich.console import Console

    from estimate.fit import STAGES, FitSettings, fit_channel
    from estimate.problem import load_problem
    from rig.fit_progress import STAGE_LABELS, FitProgress

    pb = load_problem(session, "g", 32)
    settings = FitSettings(max_iterations=3, spp_start=32, spp_max=32, final_spp=64, polish_steps=1,
                           uncertainty_spp=32, scale="free")
    for terminal in (True, False):
        buf = io.StringIO()
        stages: list[str] = []
        with FitProgress(console=Console(file=buf, force_terminal=terminal, width=120)) as live:
            progress, on_stage = live.channel("g", "exp3")

            def record(stage: str, on_stage=on_stage, stages=stages) -> None:
                stages.append(stage)
                on_stage(stage)

            fit_channel(pb, "exp3", settings=settings, progress=progress, on_stage=record)
        assert stages == list(STAGES)
        text = buf.getvalue()
        if terminal:
            for stage in STAGES[:-1]:
                assert f"g (exp3): {STAGE_LABELS[stage]}" in text
            assert "iteration 1, 32 spp, loss " in text
        else:
            assert text == ""


def test_plain_output_ends_each_channel_with_its_time_and_steps(session, capsys, monkeypatch):
    monkeypatch.setattr("rig.commands.estimate.CHI2_HINT", float("inf"))  # no fit lies above it: no note
    argv = ["estimate", str(session), "--channels", "g", "--columns", "32", "--max-iterations", "3",
            "--spp-max", "32", "--polish-steps", "1", "--scale", "free", "--no-progress"]
    assert main(argv) == 0
    captured = capsys.readouterr()
    err = captured.err
    assert "fitting channel g (exp3) ..." in err
    line = next(x for x in err.splitlines() if x.startswith("  g: "))
    assert "iterations + " in line and "polish steps" in line
    assert "rig diagnose" not in captured.out


def test_python_dash_m_rig_is_the_rig_command():
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "rig", "estimate", "--help"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and "--engine" in r.stdout
    bad = subprocess.run([sys.executable, "-m", "rig", "estimate", "/nonexistent/session"], capture_output=True,
                         text=True, timeout=120)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr


def test_degree_auto_keeps_the_lowest_degree_the_recording_supports(session, capsys):
    """The truth's phase is exp1 (b1 = 3), which exp3 holds: exp4 gains no more than the
    margin, so exp3 is kept, and `--degree-max 4` ends the search there (the stop after two
    degrees in a row that gain nothing: `tests/test_phase_degree.py`); the run records every
    degree's comparison and is named for the search."""
    assert main(["estimate", str(session), "--channels", "g", "--columns", "32", "--max-iterations", "4",
                 "--spp-max", "128", "--polish-steps", "2", "--degree", "auto", "--degree-spp-max", "2048",
                 "--degree-max", "4", "--json"]) == 0
    (run,) = json.loads(capsys.readouterr().out)["runs"]
    assert run["model"] == "expauto" and run["path"].endswith("_expauto")
    assert run["channels"]["g"]["model"] == "exp3"
    choice = run["degree_choice"]["g"]
    assert choice["chosen"] == 3 and [s["degree"] for s in choice["steps"]] == [3, 4]
    assert [s["accepted"] for s in choice["steps"]] == [True, False] and choice["stopped"].startswith("reached exp4")
    for s in choice["steps"][1:]:
        assert s["gain"] <= 10.0 + 2.0 * s["gain_se"]
    # The comparison renders: 2 x the final spp (2 x --spp-max), doubled while their variance
    # exceeded the recording's, up to --degree-spp-max; the render variance measured on the
    # first and the last falls as 1 / spp (within the scatter of a variance over eight renders).
    spp, first, last = choice["spp"], choice["render_ratio_first"], choice["render_ratio"]
    assert spp in (512, 1024, 2048) and (spp in (512, 2048) or last <= 2.0)
    if spp > 512:
        assert 0.5 < (first / last) / (spp / 512) < 2.0 and first > 1.0
    doc = yaml.safe_load((Path(run["path"]) / "results.yaml").read_text())
    assert doc["settings"]["degree"] == "auto" and doc["settings"]["degree_choice"]["g"]["chosen"] == 3
    assert doc["channels"]["g"]["model"] == "exp3"
    # The report shows the search: a row per degree, the kept one marked, and why it stopped.
    assert main(["report", str(session), "--out", str(Path(run["path"]) / "report.html")]) == 0
    capsys.readouterr()
    page = (Path(run["path"]) / "report.html").read_text()
    assert "degree search (--degree auto)" in page and "g: kept exp3 (reached exp4, the largest tried" in page
    assert page.count("<td>exp4</td>") == 1 and "<td>kept</td>" in page
