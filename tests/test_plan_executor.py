"""Angle plans, plan steps, and the executor on fake devices (cleanup, resume)."""

from __future__ import annotations

import numpy as np
import pytest
from fakes import make_rig

from capture.atomic import sha256_file
from capture.errors import PlanError, SessionError
from capture.executor import Executor, run_capture
from capture.plan import (
    AngleSpec,
    Bracket,
    BracketPolicy,
    Dark,
    Home,
    Move,
    SaveStack,
    SelectFilter,
    StackKey,
    make_plan,
    plan_steps,
)
from capture.session import Session
from drivers.errors import DeviceTimeout
from drivers.interfaces import AngleRange, ShutterMode

STAGE = AngleRange(-10.0, 190.0)
FILTERS = ["r", "g", "b"]
FAST = BracketPolicy(max_exposures=5, n_darks=1)


def _plan(n=4, filters=("r", "g", "b"), **kw):
    return make_plan(AngleSpec(n, tuple(filters), **kw), available_filters=FILTERS, stage_range=STAGE, bracket=FAST)


# --------------------------------------------------------------------------- plans


def test_default_plan_splits_front_and_back_outside_the_camera_cone():
    p = make_plan(AngleSpec(), available_filters=FILTERS, stage_range=STAGE)
    front = [a for a in p.angles_deg if a < 90]
    back = [a for a in p.angles_deg if a > 90]
    assert len(front) == 5 and len(back) == 5 and p.n_front == 5
    cone = p.cone_half_angle_deg
    assert all(cone <= a for a in front) and all(a <= 180 - cone for a in back)
    assert front == sorted(front) and np.allclose(np.diff(front), np.diff(front)[0])
    assert p.filters == ("r", "g", "b") and len(p.keys()) == 30


def test_odd_counts_and_explicit_split():
    assert make_plan(AngleSpec(3, ("g",)), available_filters=FILTERS, stage_range=STAGE).n_front == 2
    p = make_plan(AngleSpec(4, ("g",), n_front=0), available_filters=FILTERS, stage_range=STAGE)
    assert all(a > 90 for a in p.angles_deg)
    p1 = make_plan(AngleSpec(1, ("g",)), available_filters=FILTERS, stage_range=STAGE)
    assert p1.angles_deg == (45.0,)


@pytest.mark.parametrize(
    "spec, match",
    [
        (AngleSpec(0), "positive integer"),
        (AngleSpec(4, ("r", "x")), "unknown filter 'x'"),
        (AngleSpec(4, ("r", "r")), "repeats a filter"),
        (AngleSpec(4, ()), "no filters"),
        (AngleSpec(4, n_front=5), "cannot split"),
        (AngleSpec(4, front_range_deg=(5.0, 60.0)), "camera's cone"),
        (AngleSpec(4, back_range_deg=(100.0, 175.0)), "camera's cone"),
        (AngleSpec(4, front_range_deg=(60.0, 20.0)), "reversed"),
        (AngleSpec(4, front_range_deg=(30.0, 30.0)), "zero-width"),
        (AngleSpec(4, front_range_deg=(30.0, 95.0)), "grazing"),
        (AngleSpec(4, cone_half_angle_deg=95.0), "cone half-angle"),
    ],
)
def test_plans_that_cannot_be_made(spec, match):
    with pytest.raises(PlanError, match=match):
        make_plan(spec, available_filters=FILTERS, stage_range=STAGE)


def test_angle_outside_the_stage_range_is_a_plan_error():
    with pytest.raises(PlanError, match="outside the stage's allowed range"):
        make_plan(AngleSpec(10), available_filters=FILTERS, stage_range=AngleRange(0.0, 120.0))


def test_bracket_beyond_the_camera_is_a_plan_error():
    with pytest.raises(PlanError, match="camera's range"):
        make_plan(
            AngleSpec(2), available_filters=FILTERS, stage_range=STAGE,
            bracket=BracketPolicy(first_exposure_s=0.001), exposure_range_s=(0.01, 3600.0),
        )
    p = make_plan(AngleSpec(2), available_filters=FILTERS, stage_range=STAGE, exposure_range_s=(0.01, 30.0))
    assert (p.bracket.first_exposure_s, p.bracket.max_exposure_s) == (0.01, 30.0)


def test_plan_round_trips_through_its_dict():
    p = _plan(6)
    from capture.plan import CapturePlan

    assert CapturePlan.from_dict(p.to_dict()) == p


def test_steps_home_first_filters_inner_serpentine_and_skip_done():
    p = _plan(2, ("r", "g"))
    steps = list(plan_steps(p))
    assert steps[0] == Home() and steps[1] == Move(p.angles_deg[0])
    kinds = [type(s).__name__ for s in steps[2:7]]
    assert kinds == ["SelectFilter", "Bracket", "Dark", "SaveStack", "SelectFilter"]
    selects = [s.name for s in steps if isinstance(s, SelectFilter)]
    assert selects == ["r", "g", "g", "r"]  # no wheel move between angles
    moves = [s for s in steps if isinstance(s, Move)]
    assert len(moves) == 2
    done = {StackKey(0, "r"), StackKey(0, "g"), StackKey(1, "g")}
    rest = list(plan_steps(p, done=done, home=False))
    a = p.angles_deg[1]
    assert rest == [Move(a), SelectFilter("r"), Bracket(StackKey(1, "r"), p.bracket), Dark(StackKey(1, "r"), 1),
                    SaveStack(StackKey(1, "r"), a, a)]


def test_calibrated_stage_offset_moves_the_stage_not_the_world_angle():
    # the calibration found the beam into the lens at stage 179.63: stage = world - 0.37
    p = make_plan(AngleSpec(2, ("g",)), available_filters=FILTERS, stage_range=STAGE, bracket=FAST,
                  stage_offset_deg=-0.37)
    moves = [s.angle_deg for s in plan_steps(p) if isinstance(s, Move)]
    saves = [s for s in plan_steps(p) if isinstance(s, SaveStack)]
    assert moves == pytest.approx([a - 0.37 for a in p.angles_deg])
    assert [s.angle_deg for s in saves] == list(p.angles_deg)
    assert [s.stage_angle_deg for s in saves] == pytest.approx(moves)
    from capture.plan import CapturePlan

    assert CapturePlan.from_dict(p.to_dict()) == p
    legacy = p.to_dict()
    del legacy["stage_offset_deg"]  # a session written before the offset was recorded
    assert CapturePlan.from_dict(legacy).stage_offset_deg == 0.0
    # the range is the stage's: 15 deg world is 14.63 deg on the stage
    with pytest.raises(PlanError, match="stage angle 14.63"):
        make_plan(AngleSpec(4, ("g",)), available_filters=FILTERS, stage_range=AngleRange(15.0, 185.0),
                  stage_offset_deg=-0.37)


# --------------------------------------------------------------------------- executor


def _session(tmp_path, plan, cam, name="s"):
    return Session.create(tmp_path / name, plan=plan, frame_shape=cam.roi.shape, devices={"camera": cam.identity()}, sensor=cam.sensor)


def test_full_capture_measures_the_truth_and_cleans_up(tmp_path):
    bench, stage, cam, wheel = make_rig(seed=1)
    plan = _plan(2, ("r", "b"))
    with _session(tmp_path, plan, cam) as s:
        summary = run_capture(s, stage, cam, wheel, progress=False)
    assert summary.complete and summary.completed == ["a00_r", "a00_b", "a01_b", "a01_r"] and summary.skipped == []
    assert bench.log[0] == ("shutter", "normal") and bench.log[1] == ("home",)
    assert bench.log[-2:] == [("stop",), ("shutter", "closed")]
    r = Session.open(tmp_path / "s")
    assert r.verify() == [] and r.complete
    for rec, img in r.iter_hdr():
        truth = bench.scene(rec.angle_deg, rec.key.filter)
        z = (img["radiance"] - truth) / np.sqrt(img["variance"])
        assert abs(float(z.mean())) < 0.1 and 0.85 < float(z.std()) < 1.15, rec.id
        assert rec.info["bracket"]["peak_unsaturated"]
        raw = r.load_raw(rec.key)
        light = [f for f in raw if not f.dark]
        darks = [f for f in raw if f.dark]
        assert sorted({f.exposure_s for f in darks}) == sorted({f.exposure_s for f in light})
    # every light frame was taken at its stack's angle and filter
    for t, dark, angle, filt in cam.exposures:
        assert angle in plan.angles_deg and filt in plan.filters


def test_executor_takes_each_stack_at_its_calibrated_stage_angle(tmp_path):
    bench, stage, cam, wheel = make_rig(seed=2)
    plan = make_plan(AngleSpec(2, ("g",)), available_filters=FILTERS, stage_range=STAGE, bracket=FAST,
                     stage_offset_deg=0.25)
    with _session(tmp_path, plan, cam) as s:
        assert run_capture(s, stage, cam, wheel, progress=False).complete
    moves = [e[1] for e in bench.log if e[0] == "move"]
    assert moves == pytest.approx([a + 0.25 for a in plan.angles_deg])
    r = Session.open(tmp_path / "s")
    assert r.plan.stage_offset_deg == 0.25
    for rec in r.stacks():
        assert rec.angle_deg in plan.angles_deg
        assert rec.info["stage_angle_deg"] == pytest.approx(rec.angle_deg + 0.25)


def _files(d, ids):
    out = {}
    for i in ids:
        for sub, ext in (("raw", "npz"), ("hdr", "exr")):
            p = d / sub / f"{i}.{ext}"
            out[p.name] = (sha256_file(p), p.stat().st_mtime_ns, p.stat().st_ino)
    return out


@pytest.mark.parametrize("fault", ["device", "interrupt"])
def test_exit_on_fault_or_ctrl_c_stops_stage_closes_shutter_and_resume_finishes(tmp_path, fault):
    plan = _plan(2, ("r", "g"))
    kw = {"fail_at": 14} if fault == "device" else {"interrupt_at": 14}
    bench, stage, cam, wheel = make_rig(seed=2, **kw)
    s = _session(tmp_path, plan, cam)
    with pytest.raises(DeviceTimeout if fault == "device" else KeyboardInterrupt):
        run_capture(s, stage, cam, wheel, progress=False)
    s.close()
    assert stage.stops >= 1 and cam.shutter_calls[-1] == ShutterMode.CLOSED
    assert bench.log[-2:] == [("stop",), ("shutter", "closed")]
    r = Session.open(tmp_path / "s")
    done = sorted(k.id for k in r.done_keys())
    assert 0 < len(done) < 4 and r.verify() == []
    before = _files(tmp_path / "s", done)

    bench2, stage2, cam2, wheel2 = make_rig(seed=3)
    with Session.resume(tmp_path / "s", plan=plan) as s2:
        summary = run_capture(s2, stage2, cam2, wheel2, progress=False)
    assert summary.complete and sorted(summary.skipped) == done
    assert set(summary.completed) == {k.id for k in plan.keys()} - set(done)
    # nothing of a done stack was exposed again or rewritten
    redone = {(a, f) for _, _, a, f in cam2.exposures}
    for i in done:
        k = next(k for k in plan.keys() if k.id == i)
        assert (plan.angles_deg[k.angle_index], k.filter) not in redone
    assert _files(tmp_path / "s", done) == before
    assert Session.open(tmp_path / "s").verify() == []


def test_resume_of_a_complete_session_touches_no_hardware(tmp_path):
    plan = _plan(1, ("g",))
    bench, stage, cam, wheel = make_rig(seed=4)
    with _session(tmp_path, plan, cam) as s:
        run_capture(s, stage, cam, wheel, progress=False)
    bench2, stage2, cam2, wheel2 = make_rig(seed=5)
    with Session.resume(tmp_path / "s") as s2:
        summary = run_capture(s2, stage2, cam2, wheel2, progress=False)
    assert summary.completed == [] and summary.skipped == ["a00_g"] and cam2.exposures == []
    assert not any(e[0] in ("home", "move", "expose") for e in bench2.log)
    assert bench2.log[-2:] == [("stop",), ("shutter", "closed")]  # cleanup still runs


def test_executor_skips_steps_of_done_stacks_even_if_a_plan_yields_them(tmp_path):
    plan = _plan(1, ("r",))
    bench, stage, cam, wheel = make_rig(seed=6)
    with _session(tmp_path, plan, cam) as s:
        run_capture(s, stage, cam, wheel, progress=False)
        n = len(cam.exposures)
        before = _files(tmp_path / "s", ["a00_r"])
        summary = Executor(s, stage, cam, wheel).run(plan_steps(plan))  # the full plan again
    assert len(cam.exposures) == n and summary.skipped == ["a00_r"]
    assert _files(tmp_path / "s", ["a00_r"]) == before


def test_cleanup_failure_does_not_hide_the_original_error(tmp_path):
    plan = _plan(1, ("r",))
    bench, stage, cam, wheel = make_rig(seed=7, fail_at=0)

    def broken_stop():
        raise DeviceTimeout("no reply", device="stage")

    stage._do_stop = broken_stop
    with _session(tmp_path, plan, cam) as s:
        with pytest.raises(DeviceTimeout, match="camera") as ei:
            run_capture(s, stage, cam, wheel, progress=False)
    assert any("during cleanup: stage: no reply" in n for n in ei.value.__notes__)
    assert cam.shutter_calls[-1] == ShutterMode.CLOSED  # still closed although the stage failed


def test_run_capture_rejects_a_different_plan(tmp_path):
    bench, stage, cam, wheel = make_rig()
    with _session(tmp_path, _plan(2), cam) as s:
        with pytest.raises(SessionError, match="differs"):
            run_capture(s, stage, cam, wheel, plan=_plan(3), progress=False)
    assert bench.log == []


def test_progress_bar_renders_with_eta(tmp_path):
    from io import StringIO

    from rich.console import Console

    buf = StringIO()
    console = Console(file=buf, force_terminal=False, width=120)
    bench, stage, cam, wheel = make_rig(seed=8)
    with _session(tmp_path, _plan(1, ("r", "g")), cam) as s:
        run_capture(s, stage, cam, wheel, progress=console)
    out = buf.getvalue()
    assert "2/2" in out and "ETA" in out


class _Killed(BaseException):
    """Stands for the process dying (kill -9, power cut) at a file rename."""


def test_crash_at_every_file_write_then_resume_completes_without_losing_a_stack(tmp_path, monkeypatch):
    import os

    from capture import atomic
    from capture.session import MANIFEST_NAME

    plan = _plan(2, ("r", "g"))
    real_replace = os.replace
    n_writes = 1 + 3 * len(plan.keys())  # manifest at create, then raw + hdr + manifest per stack
    for k in range(n_writes):
        d = tmp_path / f"s{k}"
        calls = [0]

        def replace(src, dst, *a, _k=k, _calls=calls, **kw):
            _calls[0] += 1
            if _calls[0] == _k + 1:
                raise _Killed
            return real_replace(src, dst, *a, **kw)

        monkeypatch.setattr(atomic.os, "replace", replace)
        bench, stage, cam, wheel = make_rig(seed=10 + k)
        s = None
        with pytest.raises(_Killed):
            s = _session(tmp_path, plan, cam, name=d.name)
            run_capture(s, stage, cam, wheel, progress=False)
        if s is not None:
            s.close()  # the kernel would release the lock of a dead process
        monkeypatch.undo()
        assert bench.log == [] or bench.log[-2:] == [("stop",), ("shutter", "closed")]

        bench2, stage2, cam2, wheel2 = make_rig(seed=100 + k)
        if (d / MANIFEST_NAME).exists():
            done = sorted(x.id for x in Session.open(d).done_keys())
            before = _files(d, done)
            s2 = Session.resume(d, plan=plan)
        else:  # died before the first manifest: the directory is still usable for a new session
            done, before = [], {}
            s2 = _session(tmp_path, plan, cam2, name=d.name)
        with s2:
            summary = run_capture(s2, stage2, cam2, wheel2, progress=False)
        assert summary.complete, k
        assert sorted(summary.skipped) == done
        assert _files(d, done) == before
        r = Session.open(d)
        assert r.verify() == [] and r.complete
        assert not [p for p in d.rglob("*") if ".tmp-" in p.name]
