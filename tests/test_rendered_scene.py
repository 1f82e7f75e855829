"""The rendered bench scene: physical angle, scale, caches (memory and disk), effects, install."""

import math

import numpy as np
import pytest

from sim_devices.rendered_scene import RenderedScene
from sim_devices.world import WorldError, parse_world

FULL = (slice(0, 512), slice(0, 512))


def _world(tmp_path, **over):
    d = {
        "slab": {"thickness_mm": 1.0},
        "materials": {"r": {"sigma_t": 2.0, "albedo": 0.9, "phase": {"type": "exp", "b": [1.5, 0.2]}},
                      "g": {"sigma_t": 2.5, "albedo": 0.9, "phase": {"type": "hg", "g": 0.5}}},
        "beam": {"profile": {"type": "gaussian", "sigma_mm": 0.25}, "power_e_per_s": {"r": 4e10, "g": 2e10}},
        "optics": {"axis_px": [260.5, 250.5]},
        "stage": {"zero_error_deg": 0.4},
        "render": {"spp_profile": 8, "profile_halfwidth_rows": 1, "spp_band": 2, "band_halfwidth_rows": 3,
                   "spp_outside": 0, "cache_dir": str(tmp_path / "cache")},
    }
    d.update(over)
    return parse_world(d, "test.yaml")


def test_render_is_cached_in_memory_and_on_disk(tmp_path):
    w = _world(tmp_path)
    s = RenderedScene(w, magnification=0.3)
    a = s(45.0, "r", *FULL)
    assert s.renders == 1 and a.shape == (512, 512)
    r0, r1 = s.profile_rows()
    assert a[r0:r1].max() > 0 and a[:r0 - 3].max() == 0  # outside the band: not rendered (spp_outside 0)
    b = s(45.0, "r", slice(0, 512), slice(100, 200))  # another ROI, another exposure: same image
    assert s.renders == 1 and np.array_equal(b, a[:, 100:200])
    s(45.0, "g", *FULL)
    assert s.renders == 2
    fresh = RenderedScene(w, magnification=0.3)  # a later run: read from disk, not rendered
    c = fresh(45.0, "r", *FULL)
    assert fresh.renders == 0 and fresh.disk_hits == 1 and np.array_equal(c, a)
    other = RenderedScene(_world(tmp_path, slab={"thickness_mm": 1.2}), magnification=0.3)
    assert other.cache_key(45.4, "r") != fresh.cache_key(45.4, "r")


def test_each_image_has_its_own_render_noise(tmp_path):
    # r and g the same material: with one seed for every image their renders were identical
    d = {"materials": {f: {"sigma_t": 2.0, "albedo": 0.9, "phase": {"type": "hg", "g": 0.5}} for f in "rg"}}
    s = RenderedScene(_world(tmp_path, **d), magnification=0.3)
    r0, r1 = s.profile_rows()
    a, b = s.radiance(45.0, "r")[r0:r1], s.radiance(45.0, "g")[r0:r1]
    assert not np.array_equal(a, b)
    assert a.sum() == pytest.approx(b.sum(), rel=0.1)  # the same radiance, other noise
    seeds = {s.image_seed(p, f, i) for p in (30.0, 45.0) for f in "rg" for i in range(3)}
    assert len(seeds) == 12
    assert s.image_seed(45.0, "r", 0) == s.image_seed(45.0 + 1e-9, "r", 0)  # one stage position, one seed
    reseeded = RenderedScene(_world(tmp_path, render={**_world(tmp_path).raw["render"], "seed": 5}),
                             magnification=0.3)
    assert reseeded.image_seed(45.0, "r", 0) != s.image_seed(45.0, "r", 0)


def test_a_lens_blur_widens_the_profile_quality_rows(tmp_path):
    plain = RenderedScene(_world(tmp_path), magnification=0.3)
    blurred = RenderedScene(_world(tmp_path, effects={"lens_blur": {"core_sigma_px": 1.5, "tail_fraction": 0.02}}),
                            magnification=0.3)
    r0, r1 = plain.profile_rows()
    b0, b1 = blurred.profile_rows()
    assert (r0, r1) == (249, 252)  # axis row 250 +- 1 (profile_halfwidth_rows)
    assert (b0, b1) == (250 - 6, 250 + 7)  # +- (ceil(3 x 1.5) + 1)
    assert blurred.row_tiers()[0][2] == plain.row_tiers()[0][2]  # at the profile spp


def test_scale_is_radiance_times_power_pixel_area_and_collection(tmp_path):
    w = _world(tmp_path)
    s = RenderedScene(w, magnification=0.3)
    img = s(30.0, "r", *FULL)
    rad = s.radiance(30.0 + 0.4, "r")  # physical angle = stage angle + hidden error
    k = 4e10 * (0.020 / 0.3) ** 2 * 0.01
    assert np.allclose(img, np.clip(rad, 0, None) * k)


def test_straight_beam_peaks_at_the_hidden_zero_and_carries_the_power(tmp_path):
    w = _world(tmp_path)
    s = RenderedScene(w, magnification=0.3)
    s.slab_present = False
    at_zero = s(180.0 - 0.4, "r", *FULL)
    # all the beam (through the calibration ND) lands on the sensor at the true zero
    assert math.isclose(at_zero.sum(), 4e10 * 1e-3, rel_tol=1e-3)
    tilted = s(180.0 - 0.4 + 0.5, "r", *FULL)
    assert math.isclose(tilted.sum() / at_zero.sum(), math.exp(-0.5), rel_tol=2e-3)  # acceptance sigma 0.5 deg
    j, i = np.unravel_index(np.argmax(at_zero), at_zero.shape)
    assert (i, j) == (260, 250)  # the axis pixel
    _ys, xs = np.indices(at_zero.shape) + 0.5
    cx = (at_zero * xs).sum() / at_zero.sum()
    wx = math.sqrt((at_zero * (xs - cx) ** 2).sum() / at_zero.sum()) * 0.020 / 0.3
    assert abs(cx - 260.5) < 1e-3 and abs(wx - 0.25) < 0.002
    assert s(150.0, "r", *FULL).max() == 0.0  # far from 180: the beam misses the lens
    assert s(179.6, None, *FULL).max() == 0.0  # wheel between positions
    assert s.renders == 0  # no Mitsuba render for the straight beam


def test_image_effects_and_raw_nonlinearity(tmp_path):
    from sim_devices.rendered_scene import raw_nonlinearity

    w = _world(tmp_path, effects={"lens_blur": {"core_sigma_px": 2.0},
                                  "sensor_nonlinearity": {"compression": 0.1}})
    s = RenderedScene(w, magnification=0.3)
    s.slab_present = False
    img = s(179.6, "r", *FULL)
    sharp = 4e10 * 1e-3 * (0.020 / 0.3) ** 2 * s._beam_on_pixels(0.0)
    assert math.isclose(img.sum(), sharp.sum(), rel_tol=1e-3) and img.max() < 0.9 * sharp.max()
    f = raw_nonlinearity(w, 2e5)
    assert f(np.array([2e5]))[0] == pytest.approx(1.8e5)
    assert raw_nonlinearity(_world(tmp_path), 2e5) is None


def test_install_world_drives_the_twins(tmp_path):
    import yaml

    from rig.config import load_config
    from rig.simbench import SimOperator, install_world
    from rig.wiring import open_rig

    cfg = load_config(None)
    wpath = tmp_path / "w.yaml"
    d = yaml.safe_load(yaml.safe_dump(_world(tmp_path).raw))
    d["materials"]["b"] = d["materials"]["g"]
    d["beam"]["power_e_per_s"]["b"] = 1e10
    d["effects"] = {"sensor_nonlinearity": {"compression": 0.2}}
    wpath.write_text(yaml.safe_dump(d))
    inst = install_world(cfg, str(wpath))
    assert inst.name == "w"  # no name in the file: its stem
    op = SimOperator(inst)
    assert op.ask("remove_slab", "remove it") and not inst.scene.slab_present
    with open_rig(cfg, sim=True, scene=inst.scene) as rig:
        rig.changer.select("r")
        rig.stage.move_to(180.0 - 0.4)  # the hidden zero error puts the beam into the lens here
        fr = rig.camera.expose(0.001)
        assert fr.data.max() > 300  # the beam, in ADU above the 250 bias
    assert op.ask("mount_slab", "mount it") and inst.scene.slab_present


def test_configure_backend_gives_the_camera_twin_the_world_sensor(tmp_path):
    import yaml

    from rig.config import load_config
    from rig.simbench import configure_backend, install_world
    from rig.wiring import prepare_bench
    from sim_devices.alta_usb import AltaBackend

    cfg = load_config(None)
    d = yaml.safe_load(yaml.safe_dump(_world(tmp_path).raw))
    for f in ("g", "b"):
        d["materials"][f] = d["materials"]["r"]
        d["beam"]["power_e_per_s"][f] = 1e10
    d["effects"] = {"sensor_nonlinearity": {"compression": 0.2}}
    d["sensor"] = {"read_noise_e": 9.0}
    (tmp_path / "w.yaml").write_text(yaml.safe_dump(d))
    install_world(cfg, str(tmp_path / "w.yaml"))
    backend = AltaBackend(cfg.sim.bench)
    configure_backend(backend)
    assert backend.ccd.sensor.read_noise_e == 9.0
    assert backend.ccd.nonlinearity(np.array([backend.ccd.sensor.full_well_e]))[0] == pytest.approx(
        0.8 * backend.ccd.sensor.full_well_e)
    prepare_bench(cfg)  # a plain bench again: the world no longer applies
    plain = AltaBackend(cfg.sim.bench)
    configure_backend(plain)
    assert plain.ccd.nonlinearity is None and plain.ccd.sensor.read_noise_e != 9.0


@pytest.mark.parametrize("slope, side", [(0.0005, "left"), (-0.0005, "right")])
def test_stray_light_that_goes_negative_on_the_frame_is_refused_in_one_line(tmp_path, slope, side):
    import yaml

    from rig.config import load_config
    from rig.errors import UsageError
    from rig.simbench import install_world
    from sim_devices.world import WorldError

    # 512 px of 20 um at magnification 0.3: x reaches +-17.0 mm, where 0.003 - 0.0005 * 17 < 0
    bad = _world(tmp_path, effects={"stray_light": {"offset": 0.003, "slope_per_mm": slope}})
    with pytest.raises(WorldError, match=rf"effects\.stray_light: .* frame's {side} edge .*slope_per_mm\| <= 0\.000176"):
        RenderedScene(bad, magnification=0.3)
    ok = _world(tmp_path, effects={"stray_light": {"offset": 0.003, "slope_per_mm": slope * 0.3}})
    assert RenderedScene(ok, magnification=0.3).world is ok  # 0.003 - 0.00015 * 17 > 0
    cfg = load_config(None)
    d = yaml.safe_load(yaml.safe_dump(bad.raw))
    d["materials"]["b"] = d["materials"]["g"]
    d["beam"]["power_e_per_s"]["b"] = 1e10
    (tmp_path / "w.yaml").write_text(yaml.safe_dump(d))
    with pytest.raises(UsageError, match=r"w\.yaml: effects\.stray_light") as e:
        install_world(cfg, str(tmp_path / "w.yaml"))
    assert "\n" not in str(e.value)


def test_the_light_engine_renders_the_same_frame_with_less_noise(tmp_path):
    """`render.engine: light`: the frame in blocks of at most 64 rows, the same radiance as
    the camera engine's (its own cache entry), and a world file with another engine is refused."""
    base = _world(tmp_path).raw["render"]
    cam = RenderedScene(_world(tmp_path, render={**base, "spp_profile": 256, "spp_outside": 1}), magnification=0.3)
    light_world = _world(tmp_path, render={**base, "spp_profile": 256, "spp_outside": 1, "engine": "light"})
    light = RenderedScene(light_world, magnification=0.3)
    assert light.cache_key(45.0, "g") != cam.cache_key(45.0, "g")
    a, b = cam.radiance(45.0, "g"), light.radiance(45.0, "g")
    r0, r1 = light.profile_rows()
    assert b[r0:r1].sum() == pytest.approx(a[r0:r1].sum(), rel=0.05)
    assert b[:r0 - 3].sum() > 0    # the rows outside the band, rendered in 64-row blocks
    # the camera engine's default leaves the truth hash (and the caches) of earlier worlds alone
    assert parse_world({**_world(tmp_path).raw, "render": {**base, "engine": "camera"}}, "t.yaml").truth_hash() \
        == _world(tmp_path).truth_hash()
    with pytest.raises(WorldError, match="render.engine: must be camera or light"):
        _world(tmp_path, render={**base, "engine": "photons"})


def test_a_new_light_engine_revision_renders_afresh_and_the_camera_keeps_its_cache(tmp_path, monkeypatch):
    """Images cached by an earlier revision of the light engine (whose single-precision sums
    put bright pixels 0.03-0.10 % low) are not reused: the revision is part of their key. The
    camera engine's keys do not depend on it."""
    import estimate.light_paths as lp

    base = _world(tmp_path).raw["render"]
    light = RenderedScene(_world(tmp_path, render={**base, "engine": "light"}), magnification=0.3)
    cam = RenderedScene(_world(tmp_path), magnification=0.3)
    keys = (light.cache_key(45.0, "g"), cam.cache_key(45.0, "g"))
    monkeypatch.setattr(lp, "RENDER_REVISION", lp.RENDER_REVISION + 1)
    assert light.cache_key(45.0, "g") != keys[0]
    assert cam.cache_key(45.0, "g") == keys[1]
