"""``rig selftest``: exercise every device briefly and safely, one line per check.

Exit status: 0 all checks passed (warnings allowed), 1 a check failed, 2 bad
input (configuration, arguments), 3 a device cannot be opened (wrong device on
the port, camera busy or not permitted): one line naming the device and the fix.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("selftest", help="exercise each device briefly and safely and check it against its specs")
    p.add_argument("--config", metavar="RIG.yaml", help="rig configuration (default: the simulated rig)")
    p.add_argument("--sim", action="store_true", help="use the simulated twins whatever the ports say")
    p.add_argument("--transcript", metavar="FILE",
                   help="where to write the byte transcript of the run (default: selftest-<time>.log here); "
                        "send it with any request for help")
    p.add_argument("--json", action="store_true", help="print the results as JSON")
    p.set_defaults(func=run)


def _transcript_path(text: str | None) -> Path:
    from rig.errors import UsageError
    from rig.selftest import default_transcript_path

    if text is None:
        return default_transcript_path(".")
    path = Path(text)
    if path.is_dir():
        raise UsageError(f"--transcript {text}: is a folder; give a file name, e.g. {path / 'selftest.log'}")
    if path.exists():
        raise UsageError(f"--transcript {text}: exists; transcripts are never overwritten, choose a new name")
    if not path.parent.is_dir():
        raise UsageError(f"--transcript {text}: folder {path.parent} does not exist; create it first")
    return path


def run(args: argparse.Namespace, *, open_rig: Callable[..., Any] | None = None) -> int:
    """The command; ``open_rig`` replaces :func:`rig.wiring.open_rig` (tests inject devices)."""
    from drivers.errors import DeviceConnectionError
    from rig.config import load_config
    from rig.selftest import CheckResult, selftest_from_config
    from rig.wiring import config_is_simulated

    cfg = load_config(args.config)
    path = _transcript_path(args.transcript)
    simulated = args.sim or config_is_simulated(cfg)

    def show(r: CheckResult) -> None:
        print(r.line(), flush=True)

    if not args.json:
        print(f"selftest: config {cfg.path}{'  (simulated twins)' if simulated else ''}; transcript {path}",
              flush=True)
    try:
        report = selftest_from_config(cfg, sim=bool(args.sim), transcript_path=path,
                                      on_result=None if args.json else show, open_rig=open_rig)
    except DeviceConnectionError as e:
        # One line naming the device and the fix; the transcript holds the exchange.
        print(f"rig selftest: {e} (transcript: {path})", file=sys.stderr)
        return 3
    if args.json:
        print(json.dumps(report.to_dict(), indent=2))
    else:
        print(report.summary())
    return 0 if report.ok else 1
