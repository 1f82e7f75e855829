"""The session directory: manifest, atomic writes, checksums, refusal rules, resume."""

from __future__ import annotations

import os
from collections import namedtuple
from pathlib import Path

import numpy as np
import pytest
import yaml
from fakes import TEST_SENSOR

import capture.session as session_mod
from capture import atomic
from capture.atomic import atomic_write_bytes, remove_stale_temps, sha256_file
from capture.errors import SessionError
from capture.exr_io import write_exr
from capture.hdr import HdrResult, NoiseModel
from capture.plan import AngleSpec, StackKey, make_plan
from capture.session import FORMAT_VERSION, MANIFEST_NAME, Session
from drivers.interfaces import ROI, AngleRange, Frame

SHAPE = (8, 12)


@pytest.fixture
def plan():
    return make_plan(AngleSpec(2, ("r", "g")), available_filters=["r", "g", "b"], stage_range=AngleRange(0, 180))


def _create(path, plan, **kw):
    return Session.create(
        path,
        plan=plan,
        frame_shape=SHAPE,
        rig_config={"stage": {"driver": "fake"}},
        devices={"stage": "S", "camera": "C", "filter": "F"},
        sensor=TEST_SENSOR,
        noise=NoiseModel.from_sensor(TEST_SENSOR),
        geometry={"thickness_mm": 4.0},
        **kw,
    )


def _stack_payload(seed=0):
    rng = np.random.default_rng(seed)
    frames = [Frame(rng.integers(900, 2000, SHAPE, dtype=np.uint16), t, d, -20.0, 0.0, t, ROI(0, 0, 12, 8)) for t, d in [(0.01, False), (0.01, True)]]
    rad = rng.random(SHAPE).astype(np.float32)
    hdr = HdrResult(rad, rad * 0.1, np.ones(SHAPE, bool), np.ones(SHAPE, np.uint8))
    return frames, hdr


def test_create_open_round_trip(tmp_path, plan):
    d = tmp_path / "s"
    with _create(d, plan) as s:
        assert [k.id for k in s.pending_keys()] == ["a00_r", "a00_g", "a01_g", "a01_r"]
        frames, hdr = _stack_payload()
        rec = s.write_stack(StackKey(0, "r"), frames=frames, hdr=hdr, info={"bracket": {"exposures_s": [0.01]}})
        assert rec.done and set(rec.files) == {"raw", "hdr"}
    m = yaml.safe_load((d / MANIFEST_NAME).read_text())
    assert m["format"] == "rig-session" and m["format_version"] == FORMAT_VERSION
    assert m["software"]["version"] and m["devices"]["camera"] == "C" and m["geometry"]["thickness_mm"] == 4.0
    r = Session.open(d)
    assert r.done_keys() == {StackKey(0, "r")} and not r.complete
    assert r.plan == plan and r.sensor() == TEST_SENSOR and r.geometry() == {"thickness_mm": 4.0}
    img = r.load_hdr("a00_r")
    assert np.array_equal(img["radiance"], hdr.radiance) and img.attributes["rig_angle_deg"] == plan.angles_deg[0]
    assert img.meta["bracket"]["exposures_s"] == [0.01]
    raw = r.load_raw(StackKey(0, "r"))
    assert all(np.array_equal(a.data, b.data) for a, b in zip(frames, raw))
    assert [rec.id for rec, _ in r.iter_hdr(filter="r")] == ["a00_r"]
    assert r.find(plan.angles_deg[1], "g").id == "a01_g"
    with pytest.raises(SessionError, match="no stack at"):
        r.find(plan.angles_deg[1], "b")
    assert r.verify() == []
    with pytest.raises(SessionError, match="not captured yet"):
        r.load_hdr("a01_g")
    with pytest.raises(SessionError, match="read-only"):
        r.write_stack(StackKey(0, "g"), frames=frames, hdr=hdr)


def test_completed_stack_is_never_overwritten(tmp_path, plan):
    with _create(tmp_path / "s", plan) as s:
        frames, hdr = _stack_payload(1)
        rec = s.write_stack(StackKey(1, "g"), frames=frames, hdr=hdr)
        before = {k: (sha256_file(tmp_path / "s" / f.file), (tmp_path / "s" / f.file).stat().st_mtime_ns) for k, f in rec.files.items()}
        frames2, hdr2 = _stack_payload(2)
        with pytest.raises(SessionError, match="already complete"):
            s.write_stack(StackKey(1, "g"), frames=frames2, hdr=hdr2)
        after = {k: (sha256_file(tmp_path / "s" / f.file), (tmp_path / "s" / f.file).stat().st_mtime_ns) for k, f in rec.files.items()}
        assert before == after


def test_refuses_non_empty_dir_existing_session_and_file_parent(tmp_path, plan):
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with pytest.raises(SessionError, match="not empty"):
        _create(other, plan)
    assert sorted(p.name for p in other.iterdir()) == ["notes.txt"]
    _create(tmp_path / "s", plan).close()
    with pytest.raises(SessionError, match="already holds a session"):
        _create(tmp_path / "s", plan)
    (tmp_path / "afile").write_text("x")
    with pytest.raises(SessionError, match="not a directory"):
        _create(tmp_path / "afile" / "s", plan)


def test_full_disk_is_refused_up_front_and_nothing_is_created(tmp_path, plan, monkeypatch):
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(session_mod.shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 1000, 1000))
    with pytest.raises(SessionError, match="not enough space"):
        _create(tmp_path / "s", plan)
    assert not (tmp_path / "s").exists()


def test_space_estimate_grows_with_the_plan(plan):
    small = session_mod.estimate_session_bytes(plan, (16, 512))
    big = session_mod.estimate_session_bytes(plan, (512, 512))
    assert big > 20 * small
    per_stack = plan.bracket.max_exposures * (1 + plan.bracket.n_darks) * 512 * 512 * 2
    assert big >= len(plan.keys()) * per_stack


@pytest.mark.parametrize(
    "content, match",
    [
        (b"\x00\xff\xfe garbage: [", "corrupt manifest"),
        (b"format: rig-session\nformat_version: 1\nplan: {angles_deg: [1", "corrupt manifest"),
        (b"just a string", "not a rig-session manifest"),
        (b"format: rig-session\nformat_version: 99\n", "format version 99"),
        (b"format: rig-session\nformat_version: 1\nstacks: []\n", "corrupt manifest.*missing"),
    ],
)
def test_corrupt_manifest_is_one_line_session_error(tmp_path, plan, content, match):
    d = tmp_path / "s"
    _create(d, plan).close()
    (d / MANIFEST_NAME).write_bytes(content)
    with pytest.raises(SessionError, match=match) as ei:
        Session.open(d)
    assert "\n" not in str(ei.value)
    with pytest.raises(SessionError):
        Session.resume(d)


def test_manifest_whose_stacks_do_not_match_the_plan_is_corrupt(tmp_path, plan):
    d = tmp_path / "s"
    _create(d, plan).close()
    m = yaml.safe_load((d / MANIFEST_NAME).read_text())
    m["stacks"] = m["stacks"][:-1]
    (d / MANIFEST_NAME).write_text(yaml.safe_dump(m))
    with pytest.raises(SessionError, match="does not match the plan"):
        Session.open(d)


def test_missing_manifest_or_dir(tmp_path):
    with pytest.raises(SessionError, match="not a session directory"):
        Session.open(tmp_path / "nope")
    with pytest.raises(SessionError, match="session.yaml is missing"):
        Session.open(tmp_path)


def test_verify_finds_corrupt_and_missing_files_and_resume_refuses(tmp_path, plan):
    d = tmp_path / "s"
    with _create(d, plan) as s:
        for i, k in enumerate(s.pending_keys()[:2]):
            s.write_stack(k, frames=_stack_payload(i)[0], hdr=_stack_payload(i)[1])
    hdr_file = d / "hdr" / "a00_r.exr"
    data = bytearray(hdr_file.read_bytes())
    data[len(data) // 2] ^= 0x01
    hdr_file.write_bytes(bytes(data))
    (d / "raw" / "a00_g.npz").unlink()
    problems = Session.open(d).verify()
    assert problems == ["hdr/a00_r.exr is corrupt (checksum mismatch)", "raw/a00_g.npz is missing"]
    with pytest.raises(SessionError, match="corrupt.*and 1 more"):
        Session.resume(d)


def test_interrupted_atomic_write_leaves_the_old_file(tmp_path, monkeypatch):
    target = tmp_path / "f.bin"
    atomic_write_bytes(target, b"old content")

    def crash(*a, **k):
        raise KeyboardInterrupt  # e.g. Ctrl-C between fsync and rename

    monkeypatch.setattr(atomic.os, "replace", crash)
    with pytest.raises(KeyboardInterrupt):
        atomic_write_bytes(target, b"new content that never lands")
    with pytest.raises(KeyboardInterrupt):
        write_exr(tmp_path / "f.exr", {"radiance": np.ones((2, 2))})
    monkeypatch.undo()
    assert target.read_bytes() == b"old content"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.bin"]  # no temp files, no half EXR


def test_interrupted_manifest_update_keeps_the_stack_pending_and_resume_rewrites_it(tmp_path, plan, monkeypatch):
    d = tmp_path / "s"
    s = _create(d, plan)
    manifest_before = (d / MANIFEST_NAME).read_bytes()
    real_replace = os.replace

    def crash_on_manifest(src, dst, *a, **k):
        if Path(dst).name == MANIFEST_NAME:
            raise OSError(28, "No space left on device")
        return real_replace(src, dst, *a, **k)

    monkeypatch.setattr(atomic.os, "replace", crash_on_manifest)
    frames, hdr = _stack_payload()
    with pytest.raises(SessionError, match="cannot write the manifest"):
        s.write_stack(StackKey(0, "r"), frames=frames, hdr=hdr)
    monkeypatch.undo()
    assert (d / MANIFEST_NAME).read_bytes() == manifest_before
    assert StackKey(0, "r") not in s.done_keys()
    s.close()
    # a crash also leaves a temp file behind: resume removes it and the stack can be written
    (d / "hdr" / ".a00_r.exr.tmp-1-dead").write_bytes(b"half")
    with Session.resume(d, plan=plan) as s2:
        assert not list((d / "hdr").glob(".*tmp-*"))
        s2.write_stack(StackKey(0, "r"), frames=frames, hdr=hdr)
    assert Session.open(d).verify() == []
    assert len(Session.open(d).manifest["resumed"]) == 1


def test_resume_checks_plan_and_lock(tmp_path, plan):
    d = tmp_path / "s"
    s = _create(d, plan)
    with pytest.raises(SessionError, match="in use"):
        Session.resume(d)
    s.close()
    other = make_plan(AngleSpec(3, ("r", "g")), available_filters=["r", "g"], stage_range=AngleRange(0, 180))
    with pytest.raises(SessionError, match="other angles"):
        Session.resume(d, plan=other)
    with Session.resume(d, plan=plan, devices={"camera": "C2"}) as s2:
        assert s2.manifest["resumed"][0]["devices"] == {"camera": "C2"}


def test_calibration_is_copied_checksummed_and_loadable(tmp_path, plan):
    cal = tmp_path / "cal"
    cal.mkdir()
    (cal / "calibration.yaml").write_text("beam_centre_px: [256.0, 250.5]\nrelative_power: {r: 1.0}\n")
    write_exr(cal / "profile_r.exr", {"radiance": np.ones((3, 3))})
    d = tmp_path / "s"
    _create(d, plan, calibration=cal).close()
    s = Session.open(d)
    assert s.load_calibration()["beam_centre_px"] == [256.0, 250.5]
    assert (s.calibration_dir / "profile_r.exr").is_file()
    assert s.verify() == []
    (d / "calibration" / "calibration.yaml").write_text("tampered: true\n")
    assert s.verify() == ["calibration/calibration.yaml is corrupt (checksum mismatch)"]
    with pytest.raises(SessionError, match="references no beam calibration"):
        _create(tmp_path / "t", plan).load_calibration()


def test_remove_stale_temps_only_touches_temp_files(tmp_path):
    (tmp_path / ".x.exr.tmp-12-abcd").write_text("")
    (tmp_path / "x.exr").write_text("keep")
    (tmp_path / ".hidden").write_text("keep")
    removed = remove_stale_temps(tmp_path)
    assert [p.name for p in removed] == [".x.exr.tmp-12-abcd"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [".hidden", "x.exr"]
