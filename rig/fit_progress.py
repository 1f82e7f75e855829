"""A live status line while `rig estimate` fits a channel.

A fit takes minutes per channel on a CPU (coarse start, iterations, the Gauss-Newton polish,
the final evaluation, the uncertainties). On a terminal this shows which stage is running,
the iteration, its samples per pixel and loss, and the elapsed time; the line disappears
when the channel is done. Off a terminal (a log file, a pipe, `--json`) it draws nothing,
so logs keep only the one-line messages of the command.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Self

__all__ = ["STAGE_LABELS", "FitProgress"]

#: What each stage of `estimate.fit.fit_channel` (`estimate.fit.STAGES`) is called on screen.
STAGE_LABELS = {
    "start": "coarse start",
    "iterations": "iterations",
    "polish": "Gauss-Newton polish",
    "evaluation": "final evaluation",
    "uncertainties": "uncertainties",
    "done": "done",
}


class FitProgress:
    """Context manager around the fits of one command.

    Args:
        console: a rich Console to draw on (default: standard error).
        enabled: False draws nothing (`--no-progress`, `--json`).
    """

    def __init__(self, console: Any = None, enabled: bool = True) -> None:
        from rich.console import Console

        self.console = console if console is not None else Console(stderr=True)
        self.enabled = enabled and self.console.is_terminal
        self._progress: Any = None
        self._task: Any = None

    def __enter__(self) -> Self:
        if self.enabled:
            from rich.progress import (
                Progress,
                SpinnerColumn,
                TextColumn,
                TimeElapsedColumn,
            )

            self._progress = Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(),
                                      console=self.console, transient=True)
            self._progress.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._progress is not None:
            self._progress.stop()
            self._progress = None

    def channel(self, channel: str, model: str) -> tuple[Callable[[int, float, int], None], Callable[[str], None]]:
        """Callbacks for one channel's fit: (progress, on_stage) of `fit_channel`. Each
        channel gets its own line and clock."""
        head = f"{channel} ({model})"
        state = {"stage": "start"}
        if self._progress is not None:
            if self._task is not None:
                self._progress.remove_task(self._task)
            self._task = self._progress.add_task(f"{head}: {STAGE_LABELS['start']}", total=None)

        def show(text: str) -> None:
            if self._progress is not None:
                # Drawn at once: a stage can be shorter than the 0.1 s auto-refresh.
                self._progress.update(self._task, description=f"{head}: {text}", refresh=True)

        def on_stage(stage: str) -> None:
            state["stage"] = stage
            show(STAGE_LABELS.get(stage, stage))

        def progress(iteration: int, loss: float, spp: int) -> None:
            if state["stage"] == "iterations":
                show(f"iteration {iteration}, {spp} spp, loss {loss:.3g}")

        return progress, on_stage
