"""``rig doctor``: check this machine for a run and print the fix for each problem."""

from __future__ import annotations

import argparse
import json


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("doctor", help="check Python packages, Mitsuba, USB/serial access and disk space")
    p.add_argument("--config", metavar="RIG.yaml", help="rig configuration (default: the simulated rig)")
    p.add_argument("--out", metavar="DIR", default=".", help="where sessions will be written (default: .)")
    p.add_argument("--angles", type=int, default=10, metavar="N", help="light angles per session (default 10)")
    p.add_argument("--filters", metavar="NAMES", help="filters per session, e.g. rgb or r,g,b (default: all configured)")
    p.add_argument("--exposures", type=int, default=6, metavar="N",
                   help="most exposures per bracket (default 6)")
    p.add_argument("--json", action="store_true", help="print the checks as JSON")
    p.set_defaults(func=run)


def _filters(text: str | None, configured: dict[str, int], config: str) -> tuple[str, ...]:
    from rig.name_lists import chosen_names

    names = chosen_names("--filters", text, list(configured), what="filter", where=f"the configuration {config}")
    return tuple(configured) if names is None else tuple(names)


def run(args: argparse.Namespace) -> int:
    from rig.config import load_config
    from rig.doctor import SessionSizePlan, run_checks
    from rig.errors import UsageError

    cfg = load_config(args.config)
    if args.angles < 1 or args.exposures < 1:
        raise UsageError("--angles and --exposures must be >= 1")
    filters = _filters(args.filters, cfg.filter.positions, cfg.path)
    plan = SessionSizePlan(angles=args.angles, filters=len(filters), exposures=args.exposures)
    checks = run_checks(cfg, args.out, plan, filter_names=filters)
    blocking = [c.name for c in checks if c.status == "fail"]
    if args.json:
        print(json.dumps({"config": cfg.path, "out": args.out, "plan": {**plan.__dict__, "filter_names": filters},
                          "ok": not blocking, "blocking": blocking,
                          "checks": [c.to_dict() for c in checks]}, indent=2))
    else:
        for c in checks:
            print(c.line())
        warns = sum(c.status == "warn" for c in checks)
        verdict = f"blocked by: {', '.join(blocking)}" if blocking else "ready"
        print(f"doctor: {len(checks) - len(blocking) - warns} ok, {warns} warn, {len(blocking)} fail; {verdict}")
    return 1 if blocking else 0
