"""`rig report SESSION/ [--out FILE]`: one self-contained HTML page (rig/report.py)."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="write an HTML report of a session, its calibration and estimates")
    p.add_argument("session", metavar="SESSION", help="session directory")
    p.add_argument("--out", default=None, help="HTML file to write (default SESSION/report.html)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rig.report import write_report

    print(write_report(args.session, args.out))
    return 0
