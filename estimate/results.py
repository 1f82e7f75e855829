"""Estimate runs in a session: SESSION/estimates/<run_id>/ (format rig-estimate/1).

A run directory is created once (exclusive mkdir; a clash gets a suffix) and its files are
written atomically (temporary file + rename): an earlier run is never overwritten.
Contents: results.yaml, profiles_<f>.npz, and PNG plots (profiles_<f>.png, phase_<f>.png,
loss_<f>.png).
"""

from __future__ import annotations

import hashlib
import io
import math
import os
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from estimate.errors import DataError

__all__ = ["FORMAT", "check_writable", "list_runs", "new_run_dir", "plot_channel", "read_run", "write_run"]

FORMAT = "rig-estimate/1"
ESTIMATES_DIR = "estimates"


def _atomic_bytes(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def check_writable(session_dir: str | os.PathLike[str], kind: str = ESTIMATES_DIR) -> None:
    """Refuse, before any work, a SESSION/<kind> that new runs cannot be written into (DataError:
    a file in its place, a read-only folder); writes and removes a probe file, creates nothing."""
    root = Path(session_dir) / kind
    if root.exists() and not root.is_dir():
        raise DataError(f"{root} is a file, not a folder of runs; move it away so that runs can be written there")
    where = root if root.is_dir() else Path(session_dir)
    probe = where / f".write-probe-{os.getpid()}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise DataError(f"cannot write runs into {root}: {e.strerror or e}; make the session folder writable "
                        "or work on a writable copy of it") from None


def new_run_dir(session_dir: str | os.PathLike[str], model: str, *, kind: str = ESTIMATES_DIR) -> Path:
    """Create SESSION/<kind>/<UTC timestamp>_<model>[_k] exclusively and return it."""
    root = Path(session_dir) / kind
    root.mkdir(parents=True, exist_ok=True)
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S")
    for k in range(1000):
        name = f"{stamp}_{model}" + (f"_{k}" if k else "")
        d = root / name
        try:
            d.mkdir()
        except FileExistsError:
            continue
        return d
    raise DataError(f"cannot create a new run directory in {root}")


def _software() -> dict[str, str]:
    out = {"rig": "unknown", "mitsuba": "unknown", "drjit": "unknown"}
    try:
        from capture.session import software_version

        out["rig"] = software_version()
    except ImportError:
        out["rig"] = "unknown"
    from importlib import metadata

    for pkg in ("mitsuba", "drjit"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            pass
    from estimate.mitsuba_env import active_variant

    # The renders' backend: a GPU's (cuda_*) and the CPU's (llvm_*) start from the same seeds
    # but part in floating-point details, so their fits differ within render noise.
    out["mitsuba_variant"] = active_variant() or "unknown"
    return out


def _num(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(float(x)) else None


def write_run(run_dir: Path, session_dir: str | os.PathLike[str], fits: Sequence[Any], problems: Mapping[str, Any],
              settings: Mapping[str, Any], *, plots: bool = True) -> Path:
    """Write results.yaml, profiles_<f>.npz and plots for `fits` (FitResult per channel)."""
    manifest = Path(session_dir) / "session.yaml"
    sha = hashlib.sha256(manifest.read_bytes()).hexdigest() if manifest.is_file() else None
    channels: dict[str, Any] = {}
    for r in fits:
        pb = problems[r.channel]
        channels[r.channel] = {
            "model": r.model,
            "parameters": {k: float(v) for k, v in r.parameters.items()},
            "uncertainties": {k: _num(v) for k, v in r.uncertainties.items()},
            "fixed": {k: float(v) for k, v in r.fixed.items()},
            # sigma_a, sigma_s' (what diffuse profiles determine best), g, ... with 1-sigma
            "derived": {k: {"value": _num(v["value"]), "uncertainty": _num(v["uncertainty"]), "unit": v["unit"]}
                        for k, v in r.derived().items()},
            "covariance": {a: {b: _num(v) for b, v in row.items()} for a, row in r.covariance.items()},
            "scale": float(r.scale), "scale_uncertainty": _num(r.scale_uncertainty),
            "loss": float(r.loss), "loss_unbiased": _num(r.loss_unbiased), "delta_rel": float(r.delta_rel),
            "chi2": float(r.chi2), "dof": int(r.dof), "reduced_chi2": float(r.reduced_chi2),
            "iterations": int(r.iterations), "time_s": float(r.time_s), "stop_reason": r.stop_reason,
            # wall seconds per stage: start (coarse search), iterations, polish, evaluation, uncertainties
            "stage_times_s": {k: float(v) for k, v in r.stage_times_s.items()},
            # parameters still moving when the fit stopped (result biased towards the start)
            "still_drifting": list(r.drifting), "drift": {k: _num(v) for k, v in r.drift.items()},
            # additive parameters solved exactly on every iteration's render, not stepped
            "solved_each_iteration": list(r.solved),
            # Gauss-Newton polish at the final spp after the iterations: per step the loss
            # without render noise before / after, whether it was kept, the step and the point
            # it reached, and the step's chi^2 against its own render noise (about the number
            # of parameters when it is noise alone; the polish goes on past its planned steps
            # while one of its last points is larger; the result averages the last points),
            # and the point's own Monte Carlo standard deviation from that noise (noise_sd);
            # jacobians: new Jacobians rendered for the step (0 after a noise-sized step: the
            # last ones kept), spp: its gradient renders' samples per pixel
            # the fixed-seed Levenberg-Marquardt after the polish (exponential phases of degree
            # 5 and more), per stage: its renders' spp, accepted steps, losses (its own, at fixed
            # seeds: they may fall below the noise floor), why it stopped, and the share of the
            # noise floor its optimum owes to its renders' noise (a stage above the target is
            # followed by one at more spp)
            "levenberg_marquardt": [dict(g) for g in r.lm_stages],
            "polish": [{"loss": _num(e["loss"]), "loss_new": _num(e["loss_new"]), "accepted": bool(e["accepted"]),
                        "halvings": int(e.get("halvings", 0)), "step": {k: _num(v) for k, v in e["step"].items()},
                        "step_chi2": _num(e.get("step_chi2", float("nan"))),
                        **({"jacobians": int(e["jacobians"]), "spp": int(e["spp"])} if "jacobians" in e else {}),
                        **({"noise_sd": {k: _num(v) for k, v in e["noise_sd"].items()}} if e.get("noise_sd") else {}),
                        **({"point": {k: _num(v) for k, v in e["point"].items()}} if e.get("point") else {})}
                       for e in r.polish],
            "spp_schedule": [list(map(int, x)) for x in r.spp_schedule],
            "start": {k: float(v) for k, v in r.start.items()},
            "angles_deg": [float(a) for a in r.angles_deg],
            # world angle - recorded angle (sessions captured before the rotation zero was applied)
            "angle_correction_deg": float(pb.angle_correction_deg),
            "stacks": list(pb.stack_ids), "missing_stacks": list(pb.missing),
            "wavelength_nm": pb.wavelength_nm,
        }
        buf = io.BytesIO()
        np.savez_compressed(buf, x_mm=pb.x_mm, angles_deg=pb.angles_deg, measured=pb.measured,
                            variance=pb.variance, fitted=r.fitted * r.scale, valid=pb.valid,
                            model_variance=r.model_variance * r.scale ** 2,
                            loss_curve=np.asarray(r.loss_curve))
        _atomic_bytes(run_dir / f"profiles_{r.channel}.npz", buf.getvalue())
        if plots:
            plot_channel(run_dir, r, pb)
    first = fits[0] if fits else None
    doc = {
        "format": FORMAT,
        "run_id": run_dir.name,
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "software": _software(),
        "session": {"path": str(Path(session_dir).resolve()), "manifest_sha256": sha},
        "settings": {
            "model": first.model if first else None,
            "degree": int(first.model[3:]) if first and first.model.startswith("exp") else None,
            "extensions": list(first.extensions) if first else [],
            **dict(settings),
        },
        "channels": channels,
    }
    _atomic_bytes(run_dir / "results.yaml", yaml.safe_dump(doc, sort_keys=False).encode("utf-8"))
    return run_dir / "results.yaml"


def read_run(run_dir: str | os.PathLike[str]) -> dict[str, Any]:
    """Parse a run's results.yaml (DataError if missing or not rig-estimate/1)."""
    p = Path(run_dir) / "results.yaml"
    try:
        d = yaml.safe_load(p.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as e:
        raise DataError(f"cannot read {p}: {type(e).__name__}") from None
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise DataError(f"{p} is not a {FORMAT} results file")
    return d


def list_runs(session_dir: str | os.PathLike[str]) -> list[Path]:
    """Run directories with a results.yaml, oldest first."""
    root = Path(session_dir) / ESTIMATES_DIR
    if not root.is_dir():
        return []
    return sorted(d for d in root.iterdir() if (d / "results.yaml").is_file())


def phase_of(model: str, params: Mapping[str, float]) -> Any:
    """The phase-function object (with `eval(mu)` [1/sr] and `g`) of a forward-model phase
    name ("exp<M>", "tthg", "hg") and its "phase.*" parameters."""
    if model.startswith("exp"):
        from estimate.phase_exponential import ExponentialPhase

        deg = int(model[3:])
        return ExponentialPhase([params[f"phase.b{i}"] for i in range(1, deg + 1)])
    from estimate.phase_hg import HenyeyGreenstein, TwoTermHG

    if model == "tthg":
        return TwoTermHG(params["phase.g_forward"], params["phase.g_backward"], params["phase.w_forward"])
    return HenyeyGreenstein(params["phase.g"])


def _phase_curve(model: str, params: Mapping[str, float], mu: np.ndarray) -> np.ndarray:
    return np.asarray(phase_of(model, params).eval(mu))


def plot_channel(run_dir: Path, r: Any, pb: Any) -> list[Path]:
    """profiles_<f>.png (measured vs fitted per angle), phase_<f>.png (polar + log), loss_<f>.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = []
    n = len(pb.angles_deg)
    cols = min(5, n)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
    fit = r.fitted * r.scale
    for k in range(rows * cols):
        ax = axes[k // cols][k % cols]
        if k >= n:
            ax.axis("off")
            continue
        ax.semilogy(pb.x_mm, np.clip(pb.measured[k], 1e-3, None), ".", ms=2, label="measured")
        ax.semilogy(pb.x_mm, np.clip(fit[k], 1e-3, None), "-", lw=1, label="fitted")
        ax.set_title(f"{pb.angles_deg[k]:g} deg", fontsize=9)
        ax.tick_params(labelsize=7)
        if k == 0:
            ax.legend(fontsize=7)
    fig.suptitle(f"channel {r.channel}: {r.model}, reduced chi2 {r.reduced_chi2:.3g}; x [mm], e-/s")
    fig.tight_layout()
    p = run_dir / f"profiles_{r.channel}.png"
    fig.savefig(p, dpi=80)
    plt.close(fig)
    out.append(p)

    theta = np.linspace(0, np.pi, 721)
    pf = _phase_curve(r.model, r.parameters, np.cos(theta))
    fig = plt.figure(figsize=(9, 4))
    ax1 = fig.add_subplot(1, 2, 1, projection="polar")
    ax1.plot(theta, np.log10(pf) - np.log10(pf).min(), lw=1.2)
    ax1.plot(-theta, np.log10(pf) - np.log10(pf).min(), lw=1.2, color="C0")
    ax1.set_title("log10 p (shifted), polar", fontsize=9)
    ax2 = fig.add_subplot(1, 2, 2)
    ax2.semilogy(np.degrees(theta), pf)
    ax2.set_xlabel("scattering angle [deg]")
    ax2.set_ylabel("p [1/sr]")
    ax2.set_title(f"fitted phase function ({r.model})", fontsize=9)
    fig.tight_layout()
    p = run_dir / f"phase_{r.channel}.png"
    fig.savefig(p, dpi=80)
    plt.close(fig)
    out.append(p)

    fig, ax = plt.subplots(figsize=(5, 3))
    ax.semilogy(np.arange(1, len(r.loss_curve) + 1), r.loss_curve, lw=1)
    for it, spp in r.spp_schedule[1:]:
        ax.axvline(it, color="0.7", lw=0.8)
        ax.text(it, max(r.loss_curve), f"{spp} spp", fontsize=7, rotation=90, va="top")
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss (reference delta)")
    fig.tight_layout()
    p = run_dir / f"loss_{r.channel}.png"
    fig.savefig(p, dpi=80)
    plt.close(fig)
    out.append(p)
    return out
