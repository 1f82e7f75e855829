"""The rig from Python (a notebook), with the same behaviour as the command line.

Each step runs the very command the terminal runs (same checks, same files, same
errors), and returns the command's machine-readable result instead of printing it::

    from rig import api

    cal = api.calibrate_beam("cal", sim=True)
    summary = api.capture("sessions/s1", angles=10, filters="rgb", calibration="cal", sim=True)
    results = api.estimate("sessions/s1")            # per channel: sigma_t, albedo, phase, ...
    diagnosis = api.diagnose("sessions/s1")
    page = api.report("sessions/s1")

Bad input raises :class:`rig.errors.UsageError` (or the capture/estimate error of the
step), a device fault :class:`drivers.errors.DeviceError`: the one-line messages the
command line prints. ``sim`` is ``False`` (the devices of ``config``), ``True`` (the
simulated rig with its default world) or a world file's path.

``open_rig``, ``load_session`` and ``load_results`` give direct access to the devices,
a session and the estimate runs.
"""

from __future__ import annotations

import io
import json
from collections.abc import Sequence
from contextlib import redirect_stdout
from pathlib import Path
from typing import Any

__all__ = [
    "calibrate_beam", "capture", "devices", "diagnose", "estimate", "info", "load_results",
    "load_session", "open_rig", "report",
]


def _invoke(argv: Sequence[str], *, json_output: bool = True, ok_codes: tuple[int, ...] = (0,)) -> Any:
    """Run one ``rig`` command in this process; its JSON (or text) output is the result."""
    from rig.cli import build_parser

    args = build_parser().parse_args([str(a) for a in argv])  # raises ArgumentsError (a UsageError)
    buf = io.StringIO()
    with redirect_stdout(buf):
        code = int(args.func(args) or 0)
    out = buf.getvalue()
    if code not in ok_codes:
        from rig.errors import UsageError

        last = out.strip().splitlines()[-1] if out.strip() else ""
        raise UsageError(f"rig {args.command} ended with exit code {code}{': ' + last if last else ''}")
    return json.loads(out) if json_output else out


def _common(config: str | Path | None, sim: bool | str | Path) -> list[str]:
    argv: list[str] = []
    if config is not None:
        argv += ["--config", str(config)]
    if sim is True:
        argv += ["--sim"]
    elif sim:
        argv += ["--sim", str(sim)]
    return argv


def devices(*, config: str | Path | None = None, sim: bool = False) -> dict:
    """Probe every configured device; the same result as ``rig devices --json``."""
    return _invoke(["devices", "--json"] + (["--config", str(config)] if config else []) + (["--sim"] if sim else []))


def calibrate_beam(out: str | Path, *, filters: str = "rgb", config: str | Path | None = None,
                   sim: bool | str | Path = False, log_io: str | Path | None = None) -> dict:
    """Beam calibration with the slab removed (``rig calibrate-beam``); returns its summary."""
    argv = ["calibrate-beam", "--out", str(out), "--filters", filters, "--json"] + _common(config, sim)
    if log_io:
        argv += ["--log-io", str(log_io)]
    return _invoke(argv)


def capture(out: str | Path | None = None, *, angles: int = 10, filters: str = "rgb",
            calibration: str | Path | None = None, thickness_mm: float = 1.0,
            config: str | Path | None = None, sim: bool | str | Path = False,
            resume: str | Path | None = None, extra_args: Sequence[str] = ()) -> dict:
    """Capture a session (``rig capture``), or continue one with ``resume=DIR``; returns the summary.

    ``extra_args`` passes further command-line options (e.g. ``["--band-rows", "16"]``).
    """
    argv = ["capture", "--json", "--no-progress"] + _common(config, sim)
    if resume is not None:
        argv += ["--resume", str(resume)]
    else:
        argv += ["--angles", str(angles), "--filters", filters, "--thickness-mm", str(thickness_mm)]
        if out is not None:
            argv += ["--out", str(out)]
        if calibration is not None:
            argv += ["--calibration", str(calibration)]
    return _invoke(argv + list(extra_args))


def info(session: str | Path) -> dict:
    """Summary of a session with every checksum verified (``rig info --json``): ``checksums_ok``
    and ``problems`` say what failed (no exception for a damaged file)."""
    return _invoke(["info", str(session), "--json"], ok_codes=(0, 1))


def estimate(session: str | Path, *, model: str = "exp", degree: int | str = 3, channels: str | None = None,
             extra_args: Sequence[str] = ()) -> dict:
    """Fit the scattering parameters per channel (``rig estimate --json``); a new run is written
    into the session and its results are returned. `degree`: of the exponential phase
    function, or "auto" (the recording chooses, `estimate.phase_degree`)."""
    argv = ["estimate", str(session), "--model", model, "--degree", str(degree), "--json"]
    if channels:
        argv += ["--channels", channels]
    return _invoke(argv + list(extra_args))


def diagnose(session: str | Path, *, fit: str | None = None, effects: Sequence[str] | None = None,
             channels: str | None = None, extra_args: Sequence[str] = ()) -> dict:
    """Locate and explain a fit/recording mismatch, refit (``rig diagnose --json``)."""
    argv = ["diagnose", str(session), "--json"]
    if fit:
        argv += ["--fit", fit]
    if effects:
        argv += ["--effects", ",".join(effects)]
    if channels:
        argv += ["--channels", channels]
    return _invoke(argv + list(extra_args))


def report(session: str | Path) -> Path:
    """Write the session's HTML report (``rig report``); returns its path."""
    from rig.report import write_report

    return Path(write_report(Path(session)))


def open_rig(config: str | Path | None = None, *, sim: bool | str | Path = False, log_io: str | None = None) -> Any:
    """The devices of a rig, opened (a context manager with ``.stage``, ``.camera``, ``.changer``).

    With ``sim`` the twins are used and the simulated world (default or the given file) is
    put on the bench first, as the commands do.
    """
    from rig import wiring
    from rig.config import load_config

    cfg = load_config(config)
    simulated = bool(sim) or wiring.config_is_simulated(cfg)
    scene = None
    if simulated:
        from rig.simbench import install_world

        scene = install_world(cfg, str(sim) if isinstance(sim, (str, Path)) and not isinstance(sim, bool) else None).scene
    return wiring.open_rig(cfg, sim=bool(sim), log_io=log_io, scene=scene)


def load_session(path: str | Path) -> Any:
    """A session opened read-only (:class:`capture.session.Session`)."""
    from capture.session import Session

    return Session.open(Path(path))


def load_results(session: str | Path, run: str | None = None) -> dict:
    """The results of an estimate run (the latest when ``run`` is None) as a dict."""
    from estimate.results import list_runs, read_run
    from rig.errors import UsageError

    runs = list_runs(Path(session))
    if not runs:
        raise UsageError(f"{session}: no estimate runs; run rig estimate first")
    if run is None:
        chosen = runs[-1]
    else:
        matches = [r for r in runs if Path(r).name == run]
        if not matches:
            raise UsageError(f"{session}: no estimate run {run!r}; runs: {', '.join(Path(r).name for r in runs)}")
        chosen = matches[0]
    return read_run(chosen)
