"""``rig fit-phase`` and the phase-table CSV reader."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimate.errors import DataError
from estimate.phase_hg import HenyeyGreenstein
from estimate.phase_table import parse_phase_csv
from rig.cli import main


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    rc = main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


def _hg_csv(path: Path, g: float = 0.7, n: int = 91) -> Path:
    th = np.linspace(0, 180, n)
    p = HenyeyGreenstein(g).eval(np.cos(np.radians(th)))
    path.write_text("theta_deg,p\n" + "".join(f"{a:.6f},{v:.10e}\n" for a, v in zip(th, p)))
    return path


def test_mie_json_shape(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, err = _run(capsys, "fit-phase", "--mie", "mono", "--diameters", "0.1,2", "--models", "exp3,hg,poly3",
                        "--n-theta", "181", "--out", str(tmp_path), "--json", "--no-plots")
    assert rc == 0, err
    doc = json.loads(out)
    assert doc["models"] == ["exp3", "hg", "poly3"]
    assert [d["diameter_um"] for d in doc["datasets"]] == [0.1, 2.0]
    for d in doc["datasets"]:
        assert 0 < d["g"] < 1
        assert set(d["fits"]) == {"exp3", "hg", "poly3"}
        assert isinstance(d["fits"]["exp3"]["sad"], float)
        assert len(d["fits"]["exp3"]["params"]["b"]) == 4
        assert -1 < d["fits"]["hg"]["params"]["g"] < 1
    big = doc["datasets"][1]["fits"]["poly3"]
    assert big["sad"] is None and big["params"] == {} and "<= 0" in big["message"]
    assert (tmp_path / "sad_table.csv").read_text().splitlines()[0] == "dataset,diameter_um,g,exp3,hg,poly3"
    assert json.loads((tmp_path / "results.json").read_text()) == doc


def test_table_fit_prints_sad_table_and_plots(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    csv = _hg_csv(tmp_path / "hg.csv")
    rc, out, err = _run(capsys, "fit-phase", str(csv), "--models", "hg,exp3", "--out", str(tmp_path / "o"))
    assert rc == 0, err
    lines = out.splitlines()
    assert lines[1].split() == ["dataset", "g", "hg", "exp3"]
    row = lines[2].split()
    assert row[0] == "hg" and float(row[1]) == pytest.approx(0.7, abs=1e-3) and float(row[2]) < 0.5
    for f in ("sad_table.csv", "results.json", "sad_vs_diameter.png", "fit_examples.png"):
        assert (tmp_path / "o" / f).stat().st_size > 0


@pytest.mark.parametrize("content,needle", [
    ("theta,p\n0,1\n10,2\n20,-1\n30,1\n40,1\n50,1\n", "line 4"),
    ("theta,p\n0,1\n10,2\n20,0\n30,1\n40,1\n50,1\n", "line 4"),
    ("theta,p\n0,1\n10,nan\n20,1\n30,1\n40,1\n50,1\n", "line 3"),
    ("theta,p\n0,1\n10,2\n30,1\n20,1\n40,1\n50,1\n", "line 5"),
    ("theta,p\n0,1\n10,2\n20,1\n30,1\n40,1\n200,1\n", "line 7"),
    ("mu,p\n1,1\n0.5,2\n0,1\n-0.5,1\n-1.5,1\n", "line 6"),
    ("theta,p\n0,1\n10,abc\n", "line 3"),
    ("theta,p\n0,1\n10,1\n", "at least 5"),
])
def test_bad_table_is_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str,
                                      needle: str) -> None:
    f = tmp_path / "bad.csv"
    f.write_text(content)
    rc, _, err = _run(capsys, "fit-phase", str(f), "--out", str(tmp_path / "o"), "--no-plots")
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and needle in err


@pytest.mark.parametrize("argv,needle", [
    (["--mie", "mono", "--models", "exp3,spline2"], "unknown phase model"),
    (["--mie", "mono", "--models", "exp-1"], "degree"),
    (["--mie", "mono", "--diameters", "1,abc"], "--diameters"),
    (["--mie", "mono", "--diameters", "1,-2"], "--diameters"),
    (["--mie", "mono", "--n-medium", "0.8"], "n_medium"),
    (["--mie", "mono", "--n-particle", "glass"], "--n-particle"),
    (["--mie", "poly", "--spread", "-0.1"], "spread"),
    (["--mie", "mono", "--n-theta", "100"], "n_theta"),
    ([], "nothing to fit"),
    (["no_such_file.csv"], "no such file"),
])
def test_bad_arguments_are_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str],
                                           needle: str) -> None:
    rc, _, err = _run(capsys, "fit-phase", *argv, "--out", str(tmp_path / "o"), "--no-plots")
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and needle in err


def test_unwritable_output_is_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An output file that cannot be written (here a folder in its place) is one line, exit 2."""
    out = tmp_path / "out"
    (out / "sad_table.csv").mkdir(parents=True)
    rc, _, err = _run(capsys, "fit-phase", str(_hg_csv(tmp_path / "hg.csv")), "--models", "hg", "--out", str(out),
                      "--no-plots")
    assert rc == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert f"--out {out}: cannot write sad_table.csv" in err


def test_table_and_mie_together_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    csv = _hg_csv(tmp_path / "hg.csv")
    rc, _, err = _run(capsys, "fit-phase", str(csv), "--mie", "mono", "--out", str(tmp_path / "o"))
    assert rc == 2 and "not both" in err


_angles = st.lists(st.floats(0.0, 180.0, allow_nan=False), min_size=5, max_size=40, unique=True).map(sorted)


@settings(max_examples=60, deadline=None)
@given(angles=_angles, data=st.data())
def test_parser_accepts_valid_tables(angles: list[float], data: st.DataObject) -> None:
    if min(np.diff(angles)) <= 1e-9:
        return
    values = data.draw(st.lists(st.floats(1e-6, 1e6), min_size=len(angles), max_size=len(angles)))
    text = "theta,p\n" + "".join(f"{a!r},{v!r}\n" for a, v in zip(angles, values))
    t = parse_phase_csv(text)
    assert t.p.size == len(angles)
    np.testing.assert_allclose(t.theta_deg, angles)
    assert t.normalisation() == pytest.approx(1.0, rel=1e-9)
    # ratios of the values survive the normalisation
    np.testing.assert_allclose(t.p / t.p[0], np.array(values) / values[0], rtol=1e-9)


@settings(max_examples=60, deadline=None)
@given(angles=_angles, data=st.data())
def test_parser_names_the_bad_row(angles: list[float], data: st.DataObject) -> None:
    if min(np.diff(angles)) <= 1e-9:
        return
    values = [1.0] * len(angles)
    i = data.draw(st.integers(0, len(angles) - 1))
    values[i] = data.draw(st.sampled_from([0.0, -1.0, math.nan, math.inf, -1e-9]))
    text = "theta,p\n" + "".join(f"{a!r},{v!r}\n" for a, v in zip(angles, values))
    with pytest.raises(DataError, match=f"line {i + 2}:"):
        parse_phase_csv(text)
