"""The small executor that runs a plan's steps on the devices (interfaces only).

``run_capture`` is what ``rig capture`` calls once it has built the devices,
the plan and the session::

    with Session.create(out, plan=plan, frame_shape=camera.roi.shape, ...) as session:
        summary = run_capture(session, stage, camera, changer)

Each stack is merged and written through the session as soon as its darks
are in, so an interruption loses at most the stack being measured. Stacks the
session already holds are skipped (resume) and never rewritten. Whatever ends
the run (normal end, device error, KeyboardInterrupt), the ``finally`` clause
stops the stage and forces the shutter closed.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from capture.bracket import BracketStatus, acquire_bracket, acquire_darks
from capture.errors import SessionError
from capture.hdr import MatchedDarks, MergeOptions, NoiseModel, merge_hdr
from capture.plan import (
    Bracket,
    CapturePlan,
    Dark,
    Home,
    Move,
    SaveStack,
    SelectFilter,
    StackKey,
    Step,
    plan_steps,
)
from capture.session import Session, StackRecord
from drivers.interfaces import Camera, FilterChanger, Frame, RotationStage, ShutterMode


@dataclass
class CaptureSummary:
    """What a run did (``rig capture --json`` prints :meth:`to_dict`)."""

    session: str
    completed: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    stacks: list[dict[str, Any]] = field(default_factory=list)
    elapsed_s: float = 0.0
    complete: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {
            "session": self.session,
            "completed": list(self.completed),
            "skipped": list(self.skipped),
            "stacks": list(self.stacks),
            "elapsed_s": round(self.elapsed_s, 3),
            "complete": self.complete,
        }


class _NoProgress:
    def update(self, description: str) -> None: ...

    def advance(self) -> None: ...

    def close(self) -> None: ...


class _RichProgress:
    """A rich progress bar over stacks with elapsed time and ETA."""

    def __init__(self, total: int, console: Any = None) -> None:
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self._p = Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("stacks"),
            TimeElapsedColumn(),
            TextColumn("ETA"),
            TimeRemainingColumn(),
            console=console,
            transient=False,
        )
        self._p.start()
        self._task = self._p.add_task("capture", total=total)

    def update(self, description: str) -> None:
        self._p.update(self._task, description=description)

    def advance(self) -> None:
        self._p.advance(self._task)

    def close(self) -> None:
        self._p.stop()


class Executor:
    """Runs steps on a stage, a camera and a filter changer, writing stacks into a session.

    Args:
        session: a writable session (made by :meth:`Session.create` or :meth:`Session.resume`).
        stage, camera, changer: the devices (interfaces).
        noise: the sensor noise model for the merge (default: from ``camera.sensor``).
        merge: merge options.
        on_stack: called with each stack record right after it is written.
    """

    def __init__(
        self,
        session: Session,
        stage: RotationStage,
        camera: Camera,
        changer: FilterChanger,
        *,
        noise: NoiseModel | None = None,
        merge: MergeOptions | None = None,
        on_stack: Callable[[StackRecord], None] | None = None,
    ) -> None:
        self.session = session
        self.stage = stage
        self.camera = camera
        self.changer = changer
        self.merge = merge or MergeOptions()
        self.noise = noise or session.noise_model() or NoiseModel.from_sensor(camera.sensor, headroom=self.merge.saturation_headroom)
        self.on_stack = on_stack
        self._light: dict[StackKey, list[Frame]] = {}
        self._status: dict[StackKey, BracketStatus] = {}
        self._dark: dict[StackKey, list[Frame]] = {}
        self._angle: float | None = None

    def run(self, steps: Iterable[Step], *, total: int | None = None, progress: bool | Any = False) -> CaptureSummary:
        """Run ``steps`` in order; the stage is stopped and the shutter closed on any exit.

        Args:
            steps: the plan's steps (usually :func:`capture.plan.plan_steps`).
            total: number of stacks, for the progress bar.
            progress: True for a rich progress bar on the terminal, or a rich Console to draw it on.
        """
        summary = CaptureSummary(session=str(self.session.path))
        t0 = time.monotonic()
        bar: _NoProgress | _RichProgress = _NoProgress()
        if progress:
            bar = _RichProgress(total or 0, console=None if progress is True else progress)
        in_flight: BaseException | None = None
        try:
            self.camera.set_shutter(ShutterMode.NORMAL)
            for step in steps:
                self._run_step(step, summary, bar)
        except BaseException as e:
            in_flight = e
            raise
        finally:
            bar.close()
            summary.elapsed_s = time.monotonic() - t0
            problems = self._cleanup()
            if problems:
                if in_flight is not None:
                    for p in problems:
                        in_flight.add_note(f"during cleanup: {p}")
                else:
                    raise problems[0]
        summary.complete = self.session.complete
        return summary

    def _cleanup(self) -> list[BaseException]:
        """Stop the stage and close the shutter; each attempted even if the other fails
        (also when a second Ctrl-C lands in the middle of the first)."""
        problems: list[BaseException] = []
        for action in (self.stage.stop, lambda: self.camera.set_shutter(ShutterMode.CLOSED)):
            try:
                action()
            except BaseException as e:  # reported after the other action ran
                problems.append(e)
        return problems

    def _done(self, key: StackKey) -> bool:
        return key in self.session.done_keys()

    def _run_step(self, step: Step, summary: CaptureSummary, bar: _NoProgress | _RichProgress) -> None:
        if isinstance(step, Home):
            bar.update("homing")
            self.stage.home()
        elif isinstance(step, Move):
            bar.update(f"moving to {step.angle_deg:g} deg")
            self.stage.move_to(step.angle_deg)
            self._angle = step.angle_deg
        elif isinstance(step, SelectFilter):
            self.changer.select(step.name)
        elif isinstance(step, Bracket):
            if self._done(step.key):
                return
            bar.update(f"{step.key.id} bracket")
            frames, status = acquire_bracket(self.camera, step.policy, self.noise)
            self._light[step.key] = frames
            self._status[step.key] = status
        elif isinstance(step, Dark):
            if self._done(step.key):
                return
            bar.update(f"{step.key.id} darks")
            bracketed = self._status.get(step.key)
            if bracketed is None:
                raise RuntimeError(f"plan error: Dark step for {step.key.id} before its Bracket")
            self._dark[step.key] = acquire_darks(self.camera, bracketed.exposures_s, step.n)
        elif isinstance(step, SaveStack):
            if self._done(step.key):
                summary.skipped.append(step.key.id)
                return
            bar.update(f"{step.key.id} merge + save")
            rec = self._save(step)
            summary.completed.append(rec.id)
            summary.stacks.append({"id": rec.id, "angle_deg": rec.angle_deg, "filter": rec.key.filter, **rec.info["bracket"]})
            bar.advance()
            if self.on_stack is not None:
                self.on_stack(rec)
        else:
            raise TypeError(f"unknown plan step {step!r}")

    def _save(self, step: SaveStack) -> StackRecord:
        key = step.key
        if key not in self._light or key not in self._dark:
            raise RuntimeError(f"plan error: SaveStack for {key.id} before its Bracket and Dark steps")
        stage_angle = step.angle_deg if step.stage_angle_deg is None else step.stage_angle_deg
        if self._angle is None or abs(self._angle - stage_angle) > 1e-9:
            raise RuntimeError(f"plan error: stack {key.id} saved at stage angle {self._angle} deg, "
                               f"planned at {stage_angle} deg")
        light = self._light.pop(key)
        darks = self._dark.pop(key)
        status = self._status.pop(key)
        m = self.merge
        hdr = merge_hdr(
            np.stack([f.data for f in light]),
            [f.exposure_s for f in light],
            MatchedDarks.from_frames(darks, self.noise),
            self.noise,
            bloom_rows=m.bloom_rows,
            bloom_cols=m.bloom_cols,
            iterations=m.iterations,
            detect_plateau=m.detect_plateau,
        )
        temps = [f.ccd_temp_c for f in light + darks]
        info = {
            "bracket": status.to_dict(),
            "n_darks_per_exposure": len(darks) // max(1, len(set(status.exposures_s))),
            "ccd_temp_c": [min(temps), max(temps)],
            # darks are taken seconds after the light frames at the regulated set-point; a
            # drift here means the dark level (dark current doubles every ~6 C) may not match
            "dark_temp_delta_c": abs(float(np.mean([f.ccd_temp_c for f in darks])) - float(np.mean([f.ccd_temp_c for f in light]))),
            "roi": light[0].roi,
            "started": light[0].start_time,
            "finished": darks[-1].end_time if darks else light[-1].end_time,
            "noise_model": self.noise.to_dict(),
            # the options, and the raw level the merge took as saturated (lower than the noise
            # model's where the wells clipped below it: `capture.hdr.plateau_saturation_adu`)
            "merge": {**m.to_dict(), "saturation_adu": hdr.saturation_adu},
            "pixels_unmeasured": int((~hdr.mask).sum()),
            "stage_angle_deg": float(stage_angle),
        }
        return self.session.write_stack(key, frames=light + darks, hdr=hdr, info=info)


def run_capture(
    session: Session,
    stage: RotationStage,
    camera: Camera,
    changer: FilterChanger,
    *,
    plan: CapturePlan | None = None,
    progress: bool | Any = True,
    noise: NoiseModel | None = None,
    merge: MergeOptions | None = None,
    home: bool = True,
    on_stack: Callable[[StackRecord], None] | None = None,
) -> CaptureSummary:
    """Measure every pending stack of ``session`` (all of them for a new one).

    Args:
        session: writable session; its plan is run unless ``plan`` is given (it must be the same).
        stage, camera, changer: the devices; the camera's ROI is used as set.
        plan: optional check that the caller's plan is the session's.
        progress: rich progress bar with ETA (True), none (False), or a rich Console.
        noise, merge: noise model (default: the session's, else the camera sensor's) and merge options.
        home: home the stage before the first move.
        on_stack: callback after each stack is written.

    Returns:
        What was done; ``complete`` is True when no stack is pending.

    Raises:
        SessionError: ``plan`` differs from the session's plan.
        drivers.errors.DeviceError, KeyboardInterrupt: passed on after cleanup;
            the session stays resumable.
    """
    if plan is not None and plan.to_dict() != session.plan.to_dict():
        raise SessionError(f"{session.path}: the plan differs from the session's plan")
    ex = Executor(session, stage, camera, changer, noise=noise, merge=merge, on_stack=on_stack)
    done = session.done_keys()
    pending = session.pending_keys()
    steps = plan_steps(session.plan, done=done, home=home and bool(pending))
    summary = ex.run(steps, total=len(pending), progress=progress)
    summary.skipped = [k.id for k in session.plan.keys() if k in done]
    return summary
