"""``rig fit-phase``: fit phase-function models to Mie data or a user's table (SAD of ln p).

    rig fit-phase --mie mono|poly [--diameters 30,20,...] [--wavelength-nm 600]
                  [--n-particle 1.377] [--n-medium 1.333] [--spread 0.1]
                  [--poly-model miesimulatorgui|lognormal] [--models poly7,...,exp1]
                  [--out DIR] [--json] [--no-plots]
    rig fit-phase TABLE.csv [--models ...] [--out DIR] [--json]

Prints the SAD table (rows: datasets, columns: models; "--" = failed fit), writes
``sad_table.csv``, ``results.json``, ``sad_vs_diameter.png`` and ``fit_examples.png``
in the output folder. ``--json`` prints the results document instead of the table.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from rig.errors import UsageError

_DEFAULT_DIAMETERS = "30,20,15,10,5,3,2,1,0.5,0.3,0.2,0.1,0.01"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fit-phase", help="fit phase-function models (exp, poly, hg, tthg) to Mie data or a table")
    p.add_argument("table", nargs="?", metavar="TABLE.csv",
                   help="phase-function table: columns angle [deg] (or mu) and p")
    p.add_argument("--mie", choices=("mono", "poly"), help="fit Mie phase functions instead of a table")
    p.add_argument("--diameters", default=_DEFAULT_DIAMETERS, metavar="D1,D2,...",
                   help="(mean) particle diameters in micrometres (default: the paper's 13)")
    p.add_argument("--wavelength-nm", type=float, default=600.0, help="vacuum wavelength [nm] (600)")
    p.add_argument("--n-particle", default="1.377", help="particle refractive index, e.g. 1.377 or 1.5+0.01j")
    p.add_argument("--n-medium", type=float, default=1.333, help="medium refractive index (1.333)")
    p.add_argument("--spread", type=float, default=0.1,
                   help="poly-dispersion spread (0.1): lognormal = std of diameters / mean; "
                        "miesimulatorgui = the GUI's std field set to spread x D [um], as the paper did")
    p.add_argument("--poly-model", choices=("miesimulatorgui", "lognormal"), default="miesimulatorgui",
                   help="poly-dispersion: the paper's tool (MieSimulatorGUI v1, default) or a physical "
                        "log-normal with the given relative spread")
    p.add_argument("--n-theta", type=int, default=1801, help="angles over 0..180 deg (odd; 1801 = 0.1 deg)")
    p.add_argument("--models", default="poly7,poly5,poly3,hg,tthg,exp7,exp5,exp3,exp1",
                   help="comma-separated: polyN, expN, hg, tthg")
    p.add_argument("--out", default="fit-phase-out", metavar="DIR", help="output folder (fit-phase-out)")
    p.add_argument("--json", action="store_true", help="print machine-readable results")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.set_defaults(func=run)


def _parse_diameters(text: str) -> list[float]:
    out = []
    for item in text.split(","):
        item = item.strip()
        try:
            d = float(item)
        except ValueError:
            raise UsageError(f"--diameters: {item!r} is not a number (use e.g. 30,10,1,0.1)") from None
        if not (math.isfinite(d) and d > 0):
            raise UsageError(f"--diameters: {item!r} must be a positive diameter in micrometres")
        out.append(d)
    return out


def _parse_index(text: str) -> complex | float:
    try:
        z = complex(text.replace(" ", ""))
    except ValueError:
        raise UsageError(f"--n-particle: {text!r} is not a refractive index (e.g. 1.377 or 1.5+0.01j)") from None
    return z.real if z.imag == 0 else z


def _load_tables(args: argparse.Namespace) -> tuple[list[Any], dict[str, Any]]:
    from estimate import mie
    from estimate.phase_table import read_phase_csv

    if args.table and args.mie:
        raise UsageError("give either TABLE.csv or --mie, not both")
    if args.table:
        path = Path(args.table)
        if not path.is_file():
            raise UsageError(f"{path}: no such file")
        return [read_phase_csv(path)], {"kind": "table", "path": str(path)}
    if not args.mie:
        raise UsageError("nothing to fit: give TABLE.csv or --mie mono|poly")
    diameters = _parse_diameters(args.diameters)
    settings = mie.MieSettings(wavelength_nm=args.wavelength_nm, n_particle=_parse_index(args.n_particle),
                               n_medium=args.n_medium, n_theta=args.n_theta)
    tables = mie.mie_dataset(args.mie, diameters, settings, spread=args.spread, poly_model=args.poly_model)
    source: dict[str, Any] = {"kind": f"mie-{args.mie}", "wavelength_nm": settings.wavelength_nm,
                              "n_particle": str(settings.n_particle), "n_medium": settings.n_medium,
                              "n_theta": settings.n_theta}
    if args.mie == "poly":
        source.update(spread=args.spread, poly_model=args.poly_model)
    return tables, source


def _fmt(v: float | None) -> str:
    return "--" if v is None else f"{v:.1f}"


def run(args: argparse.Namespace) -> int:
    from estimate.phase_fit import fit_models, parse_models

    specs = parse_models(args.models)          # bad names fail before any computation
    tables, source = _load_tables(args)
    names = [s.name for s in specs]
    datasets = []
    results_per_table = []
    for t in tables:
        fits = fit_models(t, specs)
        results_per_table.append(fits)
        datasets.append({
            "label": t.label,
            "diameter_um": t.diameter_um,
            "g": t.g,
            "n_angles": int(t.p.size),
            "fits": {f.model: f.to_json() for f in fits},
        })
    doc = {"source": source, "models": names, "sad": "sum over angles of |ln p_model - ln p_data|",
           "datasets": datasets}

    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(f"--out {out}: cannot create: {e.strerror}") from None
    try:
        with open(out / "sad_table.csv", "w", encoding="utf-8") as fh:
            fh.write(",".join(["dataset", "diameter_um", "g"] + names) + "\n")
            for d in datasets:
                row = [d["label"], "" if d["diameter_um"] is None else f"{d['diameter_um']:g}", f"{d['g']:.6g}"]
                row += ["" if d["fits"][n]["sad"] is None else f"{d['fits'][n]['sad']:.6g}" for n in names]
                fh.write(",".join(row) + "\n")
        (out / "results.json").write_text(json.dumps(doc, indent=1), encoding="utf-8")
        if not args.no_plots:
            _plots(out, tables, results_per_table, names, source)
    except OSError as e:
        raise UsageError(f"--out {out}: cannot write {Path(e.filename or out).name}: {e.strerror or e}; "
                         "choose a writable folder") from None

    if args.json:
        json.dump(doc, sys.stdout, indent=1)
        sys.stdout.write("\n")
        return 0
    w = max(12, max(len(d["label"]) for d in datasets) + 1)
    print(f"SAD of ln p over {datasets[0]['n_angles']} angles ({source['kind']}); -- = fit failed")
    print(f"{'dataset':<{w}}{'g':>9}" + "".join(f"{n:>9}" for n in names))
    for d in datasets:
        print(f"{d['label']:<{w}}{d['g']:>9.4f}" + "".join(f"{_fmt(d['fits'][n]['sad']):>9}" for n in names))
    print(f"wrote {out}/sad_table.csv, results.json" + ("" if args.no_plots else ", sad_vs_diameter.png, fit_examples.png"))
    return 0


def _plots(out: Path, tables: list[Any], fits: list[list[Any]], names: list[str], source: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    # SAD vs diameter per model (the paper's fitting graph)
    fig, ax = plt.subplots(figsize=(7, 4.2))
    diam = [t.diameter_um for t in tables]
    if all(d is not None for d in diam) and len(tables) > 1:
        for j, n in enumerate(names):
            ys = [f[j].sad if f[j].sad is not None else np.nan for f in fits]
            ax.plot(diam, ys, marker="o", ms=3, label=n)
        ax.set_xscale("log")
        ax.set_xlabel("diameter [um]")
    else:
        ys = [f.sad if f.sad is not None else np.nan for f in fits[0]]
        ax.bar(names, ys)
        ax.set_xlabel("model")
    ax.set_yscale("log")
    ax.set_ylabel("SAD of ln p")
    ax.set_title(f"fit error, {source['kind']}")
    ax.grid(True, which="both", alpha=0.3)
    if len(tables) > 1:
        ax.legend(fontsize=7, ncol=3)
    fig.tight_layout()
    fig.savefig(out / "sad_vs_diameter.png", dpi=110)
    plt.close(fig)

    # examples: log p vs angle with the fits (the paper shows 0.1, 1 and 10 um)
    picks = []
    for want in (0.1, 1.0, 10.0):
        for i, t in enumerate(tables):
            if t.diameter_um is not None and abs(t.diameter_um - want) < 1e-9 and i not in picks:
                picks.append(i)
    if not picks:
        picks = sorted({0, len(tables) // 2, len(tables) - 1})
    fig, axes = plt.subplots(1, len(picks), figsize=(4.6 * len(picks), 4), squeeze=False)
    for ax, i in zip(axes[0], picks):
        t = tables[i]
        ax.plot(t.theta_deg, t.log_p, "k-", lw=2.2, label="data")
        for f in fits[i]:
            if f.ok:
                ax.plot(t.theta_deg, f.log_eval(t.mu), lw=1, label=f"{f.model} ({f.sad:.0f})")
        ax.set_title(t.label)
        ax.set_xlabel("scattering angle [deg]")
        ax.set_ylabel("ln p [1/sr]")
        ax.legend(fontsize=6)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "fit_examples.png", dpi=110)
    plt.close(fig)
