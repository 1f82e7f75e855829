"""One self-contained HTML page about a session: plan, devices, stacks, calibration, every
estimate run (tables + plots) and every diagnosis run. Plots are embedded as base64 PNG.
"""

from __future__ import annotations

import base64
import contextlib
import html
import io
import os
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import yaml

__all__ = ["write_report"]


def _img(path_or_bytes: Path | bytes, alt: str = "") -> str:
    data = path_or_bytes if isinstance(path_or_bytes, bytes) else Path(path_or_bytes).read_bytes()
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(data).decode()}">'


def _table(rows: list[list[Any]], head: list[str]) -> str:
    h = "".join(f"<th>{html.escape(str(c))}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(_fmt(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def _fmt(v: Any) -> str:
    """A table cell: floats to 5 significant digits (also inside lists and mappings, which
    YAML gives as full-precision floats: a beam centroid of 8.109064234910571e-07 mm says no
    more than 8.1091e-07), a missing value as "-", a mapping as "key value, ..."."""
    if v is None:
        return "-"
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, float):
        return f"{v:.5g}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, dict):
        return ", ".join(f"{k} {_fmt(x)}" for k, x in v.items()) if v else "-"
    return str(v)


def _beam_plots(cal_dir: Path, cal: dict[str, Any]) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from capture.exr_io import read_exr

    out = []
    for f, entry in ((cal.get("beam") or {}).get("filters") or {}).items():
        try:
            img = np.asarray(read_exr(cal_dir / entry["map"])["radiance"], dtype=float)
        except Exception as e:  # noqa: BLE001  (a report shows what it can)
            out.append(f"<p>beam map {html.escape(f)}: unreadable ({html.escape(type(e).__name__)})</p>")
            continue
        fig, ax = plt.subplots(figsize=(3, 3))
        ax.imshow(np.log10(np.clip(img, img.max() * 1e-4 + 1e-30, None)), cmap="magma")
        ax.set_title(f"beam {f} (log10 e-/s)", fontsize=9)
        ax.axis("off")
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=80)
        plt.close(fig)
        out.append(_img(buf.getvalue(), f"beam {f}"))
    return "".join(out)


def _degree_choice(choices: Any) -> str:
    """The table of a `rig estimate --degree auto` run's degree search (settings.degree_choice:
    per channel every degree tried, its chi^2 at the noise floor, its BIC gain over the best
    degree before it, and which one was kept; estimate/phase_degree.py)."""
    if not isinstance(choices, dict) or not choices:
        return ""
    rows: list[list[Any]] = []
    notes: list[str] = []
    for ch, c in choices.items():
        steps = c.get("steps") if isinstance(c, dict) else None
        if not isinstance(steps, list):
            notes.append(f"{ch}: the degree choice is not readable")
            continue
        for st in steps:
            if not isinstance(st, dict):
                continue
            gain, se = st.get("gain"), st.get("gain_se")
            shown = (f"{gain:+.1f} +- {se:.1f}" if isinstance(gain, float) and isinstance(se, float)
                     and np.isfinite(gain) else "-")
            # Runs since session 81 say how many seed pairs each gain was taken over (more
            # after a close call); earlier ones took four for every degree.
            pairs, seeds = st.get("gain_pairs"), c.get("seeds")
            if isinstance(pairs, int) and isinstance(seeds, int) and pairs > seeds:
                shown += f" ({pairs} pairs)"
            kept = st.get("degree") == c.get("chosen")
            rows.append([ch, f"exp{st.get('degree')}", st.get("chi2_adjusted"), shown, st.get("sigma_t"),
                         st.get("albedo"), "kept" if kept else ("better" if st.get("accepted") else "")])
        # Runs since session 86 say the comparison renders' spp (raised where the recording
        # is quieter than the renders at 2 x the final spp).
        spp = c.get("spp")
        at = f"; compared at {spp} spp" if isinstance(spp, int) and spp > 0 else ""
        notes.append(f"{ch}: kept exp{c.get('chosen')} ({c.get('stopped', '')}{at})")
    rule = next((c.get("rule") for c in choices.values() if isinstance(c, dict) and c.get("rule")), "")
    return (f"<p>degree search (--degree auto): {html.escape(str(rule))}</p>"
            + _table(rows, ["channel", "degree", "chi2 at the noise floor", "BIC gain +- s.e.", "sigma_t [1/mm]",
                            "albedo", ""])
            + "".join(f"<p>{html.escape(n)}</p>" for n in notes))


def _run_section(rd: Path, doc: dict[str, Any]) -> list[str]:
    """The report's section of one estimate run (raises on a hand-edited results.yaml of the wrong shape)."""
    parts = [f"<h3>{html.escape(str(doc['run_id']))}</h3>"]
    st = doc.get("settings") or {}
    exts = st.get("extensions") or []
    fit_raw = st.get("fit")
    fit_st: dict = fit_raw if isinstance(fit_raw, dict) else {}
    # Runs before the light engine (session 61) were rendered from the camera.
    engine = fit_st.get("engine") or ("camera" if fit_st else "-")
    parts.append(f"<p>model {html.escape(str(st.get('model')))}, extensions "
                 f"{html.escape(', '.join(map(str, exts)) if exts else 'none')}, scale "
                 f"{html.escape(str(st.get('scale') or '-'))}, render engine {html.escape(str(engine))}, "
                 f"software {html.escape(_fmt(doc.get('software')))}</p>")
    # A calibrated scale (the default) is not fitted and has no interval of its own.
    scale_unc_missing = "from the calibration" if st.get("scale") == "calibrated" else "-"
    rows = []
    for f, ch in (doc.get("channels") or {}).items():
        for k, v in ch["parameters"].items():
            rows.append([f, k, v, (ch.get("uncertainties") or {}).get(k, "fixed")])
        for k, d in (ch.get("derived") or {}).items():
            rows.append([f, f"{k} [{d.get('unit') or '-'}] (derived)", d.get("value"), d.get("uncertainty")])
        s_unc = ch.get("scale_uncertainty")
        rows.append([f, "scale", ch["scale"], scale_unc_missing if s_unc is None else s_unc])
        rows.append([f, "loss / reduced chi2", ch["loss"], ch["reduced_chi2"]])
        rows.append([f, "iterations / time [s]", ch["iterations"], ch["time_s"]])
        lm = ch.get("levenberg_marquardt") or []
        if lm:
            # the fixed-seed LM's stages: spp and accepted steps; the last stage's share of the
            # noise floor that its optimum owes to its renders' noise (estimate.polish.lm_noise_excess)
            rows.append([f, "Levenberg-Marquardt stages (spp: steps)",
                         ", ".join(f"{int(g['spp'])}: {int(g['steps'])}" for g in lm),
                         f"render-noise share of the floor {_fmt(lm[-1].get('noise_excess'))}; {lm[-1].get('stop', '')}"])
        if ch.get("still_drifting"):
            rows.append([f, "still drifting when the fit stopped", ", ".join(ch["still_drifting"]),
                         "uncertainties include the last drift"])
    parts.append(_table(rows, ["channel", "parameter", "value", "1-sigma"]))
    parts.append(_degree_choice(st.get("degree_choice")))
    for png in sorted(rd.glob("*.png")):
        parts.append(_img(png, png.name))
    return parts


def write_report(session_dir: str | os.PathLike[str], out: str | os.PathLike[str] | None = None) -> Path:
    """Write SESSION/report.html (or `out`) and return its path."""
    from capture.session import Session
    from estimate.errors import DataError
    from estimate.results import list_runs, read_run
    from rig.errors import UsageError

    s = Session.open(session_dir)
    path = Path(out) if out else s.path / "report.html"
    if path.is_dir() or not path.parent.is_dir():
        raise UsageError(f"cannot write the report to {path}: "
                         + ("it is a folder" if path.is_dir() else f"folder {path.parent} does not exist")
                         + "; pass --out FILE.html in an existing folder")
    parts = [f"<h1>rig session {html.escape(str(s.path))}</h1>",
             f"<p>report written {datetime.now(UTC).isoformat(timespec='seconds')}</p>"]
    summ = s.summary()
    parts.append("<h2>Session</h2>")
    parts.append(_table([[k, v] for k, v in summ.items() if k != "devices"], ["", ""]))
    parts.append("<h3>Devices</h3>" + _table([[k, v] for k, v in (s.devices or {}).items()], ["device", "identity"]))
    parts.append("<h3>Geometry</h3>" + _table([[k, v] for k, v in (s.geometry() or {}).items()], ["", ""]))
    parts.append("<h3>Stacks</h3>" + _table(
        [[r.id, r.angle_deg, r.key.filter, r.state, (r.info.get("bracket") or {}).get("exposures_s", "")]
         for r in s.stacks()], ["stack", "angle [deg]", "filter", "state", "exposures [s]"]))
    problems = s.verify()
    parts.append("<p>checksums: " + (html.escape("; ".join(problems)) if problems else "all match") + "</p>")
    parts.append("<h2>Calibration</h2>")
    if s.calibration_dir is None:
        parts.append("<p>none attached</p>")
    else:
        try:
            cal = s.load_calibration()
            parts.append(_table([[k, cal.get(k)] for k in ("created", "rotation_zero_deg", "rotation_zero_uncertainty_deg",
                                                           "pixel_pitch_mm")] +
                                [["beam centre [px]", (cal.get("beam") or {}).get("center_px")]], ["", ""]))
            filt = ((cal.get("beam") or {}).get("filters") or {})
            parts.append(_table([[f, e.get("power_e_per_s"), e.get("relative_power"), e.get("centroid_mm"), e.get("width_mm")]
                                 for f, e in filt.items()], ["filter", "power [e-/s]", "relative", "centroid [mm]", "width [mm]"]))
            parts.append(_beam_plots(s.calibration_dir, cal))
        except Exception as e:  # noqa: BLE001
            parts.append(f"<p>calibration unreadable: {html.escape(str(e))}</p>")
    parts.append("<h2>Estimates</h2>")
    runs = list_runs(s.path)
    if not runs:
        parts.append("<p>no estimate runs yet (rig estimate SESSION)</p>")
    for rd in runs:
        try:
            parts.extend(_run_section(rd, read_run(rd)))
        except Exception as e:  # noqa: BLE001  (a hand-edited results.yaml: the page says so, the rest is shown)
            what = str(e) if isinstance(e, DataError) else f"{rd / 'results.yaml'}: malformed ({type(e).__name__}: {e})"
            parts.append(f"<h3>{html.escape(rd.name)}</h3><p>{html.escape(what)}</p>")
    diag = sorted((s.path / "diagnoses").glob("*/diagnosis.yaml")) if (s.path / "diagnoses").is_dir() else []
    if diag:
        parts.append("<h2>Diagnoses</h2>")
    for dy in diag:
        parts.append(f"<h3>{html.escape(dy.parent.name)}</h3>")
        try:
            d = yaml.safe_load(dy.read_text(encoding="utf-8"))
        except (OSError, yaml.YAMLError) as e:
            parts.append(f"<p>unreadable: {html.escape(type(e).__name__)}</p>")
            continue
        text = d.get("summary") if isinstance(d, dict) else None
        parts.append("<pre>" + html.escape(text if isinstance(text, str) else yaml.safe_dump(d, sort_keys=False)[:20000]) + "</pre>")
        for png in sorted(dy.parent.glob("*.png")):
            parts.append(_img(png, png.name))
    style = ("<style>body{font-family:sans-serif;max-width:1200px;margin:auto}table{border-collapse:collapse;margin:6px 0}"
             "td,th{border:1px solid #ccc;padding:2px 6px;font-size:13px}img{max-width:100%;margin:4px}</style>")
    page = f"<!doctype html><html><head><meta charset='utf-8'><title>rig report</title>{style}</head><body>{''.join(parts)}</body></html>"
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_text(page, encoding="utf-8")
        os.replace(tmp, path)
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise UsageError(f"cannot write the report to {path}: {e.strerror or e}; "
                         "pass --out FILE.html in a writable folder") from None
    return path
