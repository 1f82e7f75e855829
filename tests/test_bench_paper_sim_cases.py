"""The paper simulation's case names (`benchmarks/bench_paper_sim.parse_cases`), which the
benchmark and its probes (`exp_phase_projection`, `exp_phase_only_lm`, `exp_sigma_t_profile`)
all read."""

import math
import sys
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import bench_paper_sim as bps

NAMES = [bps.case_name(d, s) for s in bps.SIGMAS for d in bps.DIAMETERS]


def test_all_is_the_eight_cases_in_the_benchmarks_order():
    assert [bps.case_name(d, s) for d, s in bps.parse_cases("all")] == NAMES
    assert len(set(NAMES)) == 8 and "d0.5_s2" in NAMES and "d0.01_s6" in NAMES


@given(st.lists(st.sampled_from(NAMES), min_size=1, max_size=12))
def test_a_list_of_names_gives_those_cases_once_each_in_the_order_given(names):
    got = [bps.case_name(d, s) for d, s in bps.parse_cases(",".join(names))]
    assert got == list(dict.fromkeys(names))


@given(st.text(min_size=1, max_size=12).filter(lambda t: t not in NAMES and t != "all" and "," not in t))
def test_anything_else_is_refused_in_one_line_naming_the_flag_and_the_cases(item):
    with pytest.raises(ValueError) as e:
        bps.parse_cases(f"d0.5_s2,{item}", "--case")
    msg = str(e.value)
    assert msg.startswith("--case ") and "\n" not in msg.replace(repr(item), "") and "d0.01_s6" in msg


@pytest.mark.parametrize("text", ["0.5:2", "d0.5_s3", "d0.50_s2", "", "d0.5_s2,"])
def test_the_old_diameter_colon_form_and_near_misses_are_refused(text):
    with pytest.raises(ValueError, match="not a paper-simulation case"):
        bps.parse_cases(text)


def test_loss_ratio_is_the_ratio_of_means_with_the_pairs_scatter():
    # the ratio of means, not the mean of ratios: (2 + 6) / (1 + 2) = 8 / 3, while the
    # per-pair ratios 2 and 3 (sd 0.707) give the standard error 0.707 / sqrt(2) = 0.5
    ratio, se = bps.loss_ratio([2.0, 6.0], [1.0, 2.0])
    assert ratio == pytest.approx(8 / 3) and se == pytest.approx(0.5)
    ratio, se = bps.loss_ratio([3.0], [2.0])
    assert ratio == 1.5 and math.isnan(se)   # one pair: no scatter to speak of
