"""The ``rig`` command line.

Sub-commands live in :mod:`rig.commands`, one module each, discovered at start.
User-facing errors become one line on stderr and a non-zero exit, never a traceback:
bad input exits 2, a device fault 3, Ctrl-C 130.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from collections.abc import Sequence
from typing import NoReturn

import rig
import rig.commands
from rig.errors import EXIT_INTERRUPTED, UsageError


class ArgumentsError(UsageError):
    """Raised by the parser for bad command-line arguments (one line, with the command's name)."""

    def __init__(self, prog: str, message: str) -> None:
        super().__init__(f"{message} (see '{prog} --help')")
        self.prog = prog


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]  # one line, not usage + error
        raise ArgumentsError(self.prog, message)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="rig", description="Drive the goniometric capture rig and estimate how light scatters in a translucent slab.")
    parser.add_argument("--version", action="version", version=f"rig {rig.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for info in sorted(pkgutil.iter_modules(rig.commands.__path__), key=lambda m: m.name):
        mod = importlib.import_module(f"rig.commands.{info.name}")
        if hasattr(mod, "register"):
            mod.register(sub)
    return parser


def _user_errors() -> tuple[type[BaseException], ...]:
    from capture.errors import CaptureError
    from drivers.errors import DeviceError
    from estimate.errors import EstimateError
    from rig.errors import UsageError

    return (UsageError, CaptureError, EstimateError, DeviceError)


def forget_interrupt_in_exec() -> None:
    """Undo CPython's "died of Ctrl-C" mark after an interrupt we have handled.

    CPython 3.11 (the version this project runs) marks the interpreter when a
    KeyboardInterrupt leaves code run by ``exec``/``eval`` of a *string*, even if an outer
    ``except`` catches it; at exit the
    marked interpreter, when run as ``python -m rig.cli``, kills itself with SIGINT, so
    a caller sees signal 2 instead of :data:`~rig.errors.EXIT_INTERRUPTED`. Dataclasses
    build their methods with ``exec``, so a Ctrl-C that lands while a module is first
    imported mid-run (the forward model is imported on the simulated rig's first
    render) leaves that mark. 3.11 also clears the mark at the start of every string
    ``exec``; one that completes leaves it cleared. (CPython gh-128130, 2025, moved that
    clearing to the start of the main run; on versions with it this does nothing.)
    """
    exec("None", {})  # noqa: S102  # a constant string: the point is the exec itself


def main(argv: Sequence[str] | None = None) -> int:
    code = _main(argv)
    if code == EXIT_INTERRUPTED:
        forget_interrupt_in_exec()
    return code


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except ArgumentsError as e:
        print(f"{e.prog}: error: {e}", file=sys.stderr)
        return 2
    from drivers.errors import DeviceError

    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("rig: interrupted; everything completed so far is saved", file=sys.stderr)
        return EXIT_INTERRUPTED
    except _user_errors() as e:
        print(f"rig {args.command}: error: {e}", file=sys.stderr)
        return 3 if isinstance(e, DeviceError) else 2


def run(argv: Sequence[str] | None = None) -> NoReturn:
    """The `rig` program (`python -m rig`, `python -m rig.cli`): `main`, then exit with its code.

    After a handled Ctrl-C the process leaves without the interpreter's finalisation. The
    interrupt can land inside a render of the simulated bench, and the renderer's native
    worker threads may still be unwinding from it when the interpreter finalises: once in
    session 67's CI an interrupted capture that had saved its stacks, closed its session
    and printed its resume line then aborted (SIGABRT, "PyThreadState_Get: the GIL is
    released ... finalizing") instead of exiting 130. By then every stack is saved, the
    session and the devices are closed (`rig.commands.capture`'s ``finally``), so only the
    standard streams and the log handlers are flushed first."""
    code = main(argv)
    if code == EXIT_INTERRUPTED:
        import logging
        import os

        logging.shutdown()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    run()
