"""Wiring concrete devices to the interfaces: the only place that knows whether a
device is real or simulated.

One table maps each configured driver to its real constructor and to its twin.
``--sim`` (or a ``sim://`` port) swaps in the twin through the same table: the
same driver code then talks to the twin through the real byte protocol.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from urllib.parse import parse_qs, urlencode, urlsplit

from drivers.interfaces import AngleRange, Camera, FilterChanger, RotationStage
from drivers.iolog import Transcript
from rig.config import RigConfig
from rig.errors import UsageError

#: pyserial URL scheme of each serial driver's twin.
SIM_SCHEMES = {"sigma-koki": "sim-shot702", "fw102c": "sim-fw102c"}


@dataclass
class Rig:
    """The three devices of one rig, opened; close() releases them all."""

    stage: RotationStage
    camera: Camera
    changer: FilterChanger
    config: RigConfig
    simulated: bool
    transcript: Transcript | None = None
    _closers: list[Callable[[], None]] = field(default_factory=list, repr=False)

    def close(self) -> None:
        for dev in (self.stage, self.camera, self.changer):
            try:
                dev.close()
            except Exception:  # noqa: BLE001 - closing must reach every device
                pass
        if self.transcript is not None:
            self.transcript.close()

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _is_sim(port: str | None, sim: bool) -> bool:
    return sim or (port or "").startswith("sim")


def config_is_simulated(cfg: RigConfig) -> bool:
    """True when the configuration's ports name twins (``sim-*://``): a simulated rig even
    without ``--sim``; its world comes from the config's ``sim.world``."""
    return _is_sim(cfg.stage.port, False) or _is_sim(cfg.filter.port, False)


def _sim_url(driver: str, port: str | None, cfg: RigConfig, **extra: object) -> str:
    """Twin URL for a driver: keep an explicit ``sim-*://`` port, else build one."""
    query = {"timescale": cfg.sim.time_scale, "seed": cfg.sim.seed, **extra}
    if cfg.sim.faults:
        query["faults"] = cfg.sim.faults
    if port and "://" in port and port.split("://", 1)[0] == SIM_SCHEMES[driver]:
        # An explicit twin URL keeps its settings; the device facts the driver is configured
        # with (e.g. the stage's zero_offset_deg) and the sim section's time scale, seed and
        # faults are added when the URL does not set them, so that the twin's angles mean
        # what the driver thinks they mean and ``sim.faults`` reaches every twin.
        given = parse_qs(urlsplit(port).query)
        missing = {k: v for k, v in query.items() if k not in given}
        if not missing:
            return port
        return port + ("&" if "?" in port else "?") + urlencode(missing)
    return f"{SIM_SCHEMES[driver]}://{cfg.sim.bench}?{urlencode(query)}"


def prepare_bench(cfg: RigConfig, scene: object | None = None) -> None:
    """Configure the named simulated bench from the rig config (filter positions, time scale)."""
    import sim_devices  # noqa: F401 - registers the pyserial URL handlers
    from sim_devices.bench import Bench, set_bench

    bench = Bench(time_scale=cfg.sim.time_scale,
                  filter_by_position={p: n for n, p in cfg.filter.positions.items()})
    if scene is not None:
        bench.scene = scene  # type: ignore[assignment]
    set_bench(cfg.sim.bench, bench)


def open_stage(cfg: RigConfig, *, sim: bool = False, transcript: Transcript | None = None) -> RotationStage:
    from drivers.sigma_koki import SigmaKokiStage

    s = cfg.stage
    port = s.port
    if _is_sim(port, sim):
        import sim_devices  # noqa: F401

        port = _sim_url(s.driver, port, cfg, model=s.model, zero_offset_deg=s.zero_offset_deg)
    return SigmaKokiStage(
        port,
        allowed=AngleRange(*s.allowed_range_deg),
        model=s.model,
        axis=s.axis,
        degrees_per_pulse=s.degrees_per_pulse,
        division=s.division,
        zero_offset_deg=s.zero_offset_deg,
        speed_deg_s=s.speed_deg_s,
        transcript=transcript,
    )


def open_camera(cfg: RigConfig, *, sim: bool = False, transcript: Transcript | None = None) -> Camera:
    from drivers.apogee_alta import AltaCamera

    backend = None
    if sim:
        from sim_devices.alta_usb import AltaBackend
        from sim_devices.faults import FaultPlan

        backend = AltaBackend(
            cfg.sim.bench,
            time_scale=cfg.sim.time_scale,
            faults=FaultPlan.parse(cfg.sim.faults, cfg.sim.seed),
            seed=cfg.sim.seed,
        )
        from rig.simbench import configure_backend

        configure_backend(backend)  # an installed world's sensor (non-linearity, overrides)
    return AltaCamera(backend=backend, serial_number=cfg.camera.serial_number, transcript=transcript)


def open_changer(cfg: RigConfig, *, sim: bool = False, transcript: Transcript | None = None,
                 ask: Callable[[str], str] | None = None) -> FilterChanger:
    f = cfg.filter
    if f.driver == "manual":
        from drivers.manual_filter import ManualFilterChanger

        return ManualFilterChanger(f.positions, ask=ask) if ask else ManualFilterChanger(f.positions)
    from drivers.fw102c import FW102C

    port = f.port
    if _is_sim(port, sim):
        import sim_devices  # noqa: F401

        port = _sim_url(f.driver, port, cfg, pcount=6 if max(f.positions.values()) <= 6 else 12)
    return FW102C(port, positions=f.positions, transcript=transcript)  # type: ignore[arg-type]


def check_log_io(log_io: str | None) -> None:
    """``--log-io`` in a folder that does not exist: a one-line UsageError, for commands that
    check it before they create their output (the transcript itself opens with the rig)."""
    from pathlib import Path

    if log_io and not Path(log_io).parent.is_dir():
        raise UsageError(f"--log-io {log_io}: its directory does not exist")


def open_transcript(log_io: str | None) -> Transcript | None:
    """The byte transcript of ``--log-io`` (appended to), or None; a path that cannot be
    written is a one-line UsageError before any device is opened."""
    if not log_io:
        return None
    try:
        return Transcript(log_io)
    except OSError as e:
        raise UsageError(f"--log-io {log_io}: cannot write it ({e.strerror or e}); give a file in an existing, "
                         "writable folder") from None


def open_rig(cfg: RigConfig, *, sim: bool = False, log_io: str | None = None, scene: object | None = None) -> Rig:
    """Open every configured device. With ``sim`` the twins are used (and the bench prepared).

    Args:
        cfg: the validated configuration.
        sim: use the simulated twins whatever the ports say.
        log_io: path of a byte transcript of every exchange, or None.
        scene: for the simulated bench, the irradiance function the camera sees.
    """
    uses_sim = sim or _is_sim(cfg.stage.port, False) or _is_sim(cfg.filter.port, False)
    if uses_sim:
        prepare_bench(cfg, scene)
    transcript = open_transcript(log_io)
    opened: list = []
    try:
        stage = open_stage(cfg, sim=sim, transcript=transcript)
        opened.append(stage)
        camera = open_camera(cfg, sim=uses_sim, transcript=transcript)
        opened.append(camera)
        changer = open_changer(cfg, sim=sim, transcript=transcript)
    except BaseException:
        for dev in opened:
            try:
                dev.close()
            except Exception:  # noqa: BLE001
                pass
        if transcript is not None:
            transcript.close()
        raise
    return Rig(stage, camera, changer, cfg, uses_sim, transcript)
