"""The paper simulation's table (issue 6), in Markdown, from `bench_paper_sim.py` results.

Reads one or more results JSONs (their "fits"), and prints one row per case and model, the
cases in the paper's order (sigma_t 2 then 6, the diameters falling), then a summary per model:
how many cases meet each exponential-fit target and all three, and per case which model's loss
without render noise is the lower. A model asked for by more than one file keeps the last
file's fit, so a later run can replace an earlier one's rows.

Columns: the loss over the loss at the true parameters (the noise floor), plain and without
the renders' Monte Carlo variance (where the run had `--unbiased`); the sigma_t error, signed,
with its z in the fit's own interval; the albedo error; the relative errors of
sigma_a = sigma_t (1 - albedo) and sigma_s' = sigma_t albedo (1 - g); the fit's wall time. The
targets (sigma_t 3 %, albedo 0.01, loss 10 %, the loss judged without render noise where
present) are those of the issue, shown for every model, tthg included, so the two compare.

    .venv/bin/python benchmarks/paper_sim_table.py benchmarks/results/bench_paper_sim_session82_*.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path

from bench_paper_sim import DIAMETERS, SIGMAS, case_name

SIGMA_T_TARGET = 0.03
ALBEDO_TARGET = 0.01
LOSS_TARGET = 1.10
#: Losses over the floor within this share of each other are reported as a tie.
TIE = 0.01


def model_key(row: dict) -> str:
    """The model a row was asked for (``expauto`` for `--degree auto`, whatever it kept)."""
    return str(row.get("requested_model", row["model"]))


def loss_ratio(row: dict) -> float:
    """The loss over the floor the targets are judged on: without render noise where measured."""
    return float(row.get("loss_unbiased_ratio", row["loss_ratio"]))


def targets(row: dict) -> tuple[bool, bool, bool]:
    """(sigma_t within 3 %, albedo within 0.01, loss within 10 % of the floor)."""
    return (row["sigma_t_rel_error"] <= SIGMA_T_TARGET, row["albedo_abs_error"] <= ALBEDO_TARGET,
            loss_ratio(row) <= LOSS_TARGET)


def collect(docs: Iterable[dict]) -> dict[tuple[str, str], dict]:
    """The fits of `docs` by (case, requested model); a later document's fit replaces an earlier one."""
    rows: dict[tuple[str, str], dict] = {}
    for doc in docs:
        for r in doc.get("fits", []):
            rows[(r["case"], model_key(r))] = r
    return rows


def _case_order(case: str) -> tuple[int, int]:
    for i, s in enumerate(SIGMAS):
        for j, d in enumerate(DIAMETERS):
            if case == case_name(d, s):
                return i, j
    return len(SIGMAS), 0


def _sigma_t_cell(r: dict) -> str:
    rel = r["sigma_t"] / r["sigma_t_true"] - 1.0
    se = (r.get("uncertainties") or {}).get("sigma_t")
    z = f" (z {(r['sigma_t'] - r['sigma_t_true']) / se:+.1f})" if isinstance(se, float) and se > 0 else ""
    return f"{rel:+.2%}{z}".replace("%", " %")


def _pct(x: float | None) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.2%}".replace("%", " %")


def table(rows: dict[tuple[str, str], dict], models: Sequence[str]) -> list[str]:
    """The Markdown lines: the per-case table, then the summary."""
    out = ["| case | model | kept | loss / floor | without render noise | sigma_t error (z) | albedo error "
           "| sigma_a error | sigma_s' error | time | targets met |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    cases = sorted({c for c, _ in rows}, key=_case_order)
    for case in cases:
        first = True
        for m in models:
            r = rows.get((case, m))
            if r is None:
                continue
            met = targets(r)
            said = ", ".join(n for n, ok in zip(("sigma_t", "albedo", "loss"), met, strict=True) if ok)
            ub = f"{r['loss_unbiased_ratio']:.2f}" if "loss_unbiased_ratio" in r else "-"
            if r.get("loss_unbiased_ratio_se") is not None:
                ub += f" +- {r['loss_unbiased_ratio_se']:.2f}"
            label = f"d {r['diameter_um']:g} um, sigma_t {r['sigma_t_true']:g}" if first else ""
            out.append(f"| {label} | {m} | {r['model']} | {r['loss_ratio']:.2f} | {ub} | {_sigma_t_cell(r)} "
                       f"| {r['albedo_abs_error']:.4f} | {_pct(r.get('sigma_a_rel_error'))} "
                       f"| {_pct(r.get('reduced_scattering_rel_error'))} | {r['time_s']:.0f} s "
                       f"| {'all' if all(met) else (said or 'none')} |")
            first = False
    out.append("")
    for m in models:
        mine = [r for (c, k), r in rows.items() if k == m]
        if not mine:
            continue
        each = [targets(r) for r in mine]
        times = [r["time_s"] for r in mine]
        out.append(f"- **{m}**: all three targets on {sum(all(t) for t in each)} of {len(mine)}; sigma_t "
                   f"{sum(t[0] for t in each)}, albedo {sum(t[1] for t in each)}, loss {sum(t[2] for t in each)}; "
                   f"{min(times):.0f}-{max(times):.0f} s a fit.")
    lower = [f"{c} {lowest(by)}" for c in cases
             if len(by := {m: rows[(c, m)] for m in models if (c, m) in rows}) > 1]
    if lower:
        out.append(f"- The lowest loss without render noise: {'; '.join(lower)}.")
    return out


def lowest(by_model: dict[str, dict], tie: float = TIE) -> str:
    """The model of lowest `loss_ratio` among `by_model`, joined by " = " with those within
    `tie` of it (the same fit reached two ways, or a difference the floor's noise hides)."""
    ranked = sorted(by_model, key=lambda m: loss_ratio(by_model[m]))
    best = loss_ratio(by_model[ranked[0]])
    return " = ".join(m for m in ranked if loss_ratio(by_model[m]) <= best * (1 + tie))


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", nargs="+", help="bench_paper_sim.py results JSONs; later ones replace earlier fits")
    ap.add_argument("--models", default=None,
                    help="comma list of models, in the order to show them (default: every model, as first seen)")
    args = ap.parse_args(argv)
    docs = []
    for p in args.results:
        try:
            docs.append(json.loads(Path(p).read_text()))
        except (OSError, json.JSONDecodeError) as e:
            print(f"paper_sim_table: cannot read {p}: {e}", file=sys.stderr)
            return 2
    rows = collect(docs)
    models = args.models.split(",") if args.models else list(dict.fromkeys(k for _, k in rows))
    print("\n".join(table(rows, models)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
