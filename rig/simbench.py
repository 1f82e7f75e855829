"""The simulated rig's world: install a world on the bench, and the simulated operator.

``install_world(cfg, path)`` loads a world file (the default world when None), builds its
:class:`~sim_devices.rendered_scene.RenderedScene` and installs it on the configured bench.
Open the devices afterwards with ``rig.wiring.open_rig(cfg, sim=True, scene=world_scene)``
(``open_rig`` prepares the bench again; passing the scene keeps it), e.g.::

    installed = install_world(cfg, args.sim_world)
    rig = open_rig(cfg, sim=True, scene=installed.scene)

The stage's hidden zero error is applied by the scene (physical angle = twin angle +
error); the sensor non-linearity and sensor overrides reach the camera twin through
:func:`configure_backend`, which ``rig.wiring.open_camera`` calls for every simulated camera.
"""

from __future__ import annotations

import dataclasses
import threading
from dataclasses import dataclass

from rig.config import RigConfig
from rig.errors import UsageError
from sim_devices.rendered_scene import RenderedScene, raw_nonlinearity
from sim_devices.world import World, WorldError, check_filters, load_world

__all__ = [
    "InstalledWorld",
    "SimOperator",
    "TerminalOperator",
    "configure_backend",
    "install_world",
    "installed_world",
]


@dataclass
class InstalledWorld:
    """A world on a bench: the parsed truth and the scene function the camera samples."""

    world: World
    scene: RenderedScene
    bench: str

    def __getattr__(self, name: str) -> object:
        # everything else reads like the World itself (name, materials, render, ...)
        if name in ("world", "scene", "bench"):
            raise AttributeError(name)
        return getattr(self.world, name)


_INSTALLED: dict[str, InstalledWorld] = {}
_LOCK = threading.Lock()


def install_world(cfg: RigConfig, world: str | None) -> InstalledWorld:
    """Load a world (None: ``cfg.sim.world``, else the default world) and install its
    rendered scene on the bench ``cfg.sim.bench``.

    Raises:
        UsageError: the world file is missing or invalid, or lacks a rig filter (one line).
    """
    from drivers.alta_protocol import KAF0261E
    from rig.wiring import prepare_bench

    path = world if world is not None else cfg.sim.world
    try:
        w = load_world(path)
        check_filters(w, list(cfg.filter.positions))
        scene = RenderedScene(w, magnification=cfg.camera.magnification,
                              sensor_px=(KAF0261E.width, KAF0261E.height), pixel_um=KAF0261E.pixel_size_um)
    except WorldError as e:
        raise UsageError(str(e)) from None
    prepare_bench(cfg, scene=scene)
    inst = InstalledWorld(w, scene, cfg.sim.bench)
    with _LOCK:
        _INSTALLED[cfg.sim.bench] = inst
    return inst


def installed_world(bench: str = "default") -> InstalledWorld | None:
    """The world installed on a bench, if any."""
    with _LOCK:
        return _INSTALLED.get(bench)


def configure_backend(backend: object) -> None:
    """Give a simulated camera (``sim_devices.alta_usb.AltaBackend``) the installed world's
    sensor: overridden sensor parameters and the raw-frame non-linearity. No world: no change."""
    from sim_devices.bench import get_bench

    name = getattr(backend, "bench_name", "default")
    inst = installed_world(name)
    # only while that world's scene is still the bench's (a later plain bench drops it)
    if inst is None or get_bench(name).scene is not inst.scene:
        return
    ccd = backend.ccd  # type: ignore[attr-defined]
    if inst.world.sensor:
        ccd.sensor = dataclasses.replace(ccd.sensor, **inst.world.sensor)
    ccd.nonlinearity = raw_nonlinearity(inst.world, ccd.sensor.full_well_e)


class SimOperator:
    """The operator of the simulated rig: does what a prompt asks on the bench and says yes.

    Prompts are identified by action: "remove_slab", "mount_slab"; others are answered yes.
    """

    def __init__(self, installed: InstalledWorld) -> None:
        self.installed = installed
        self.log: list[str] = []

    def ask(self, action: str, message: str) -> bool:
        """Carry out `action` and confirm (the real rig asks a person at the terminal)."""
        self.log.append(action)
        if action == "remove_slab":
            self.installed.scene.slab_present = False
        elif action == "mount_slab":
            self.installed.scene.slab_present = True
        return True


class TerminalOperator:
    """The real rig's operator: prints the request and waits for y/n on the terminal."""

    def __init__(self, input_fn=input) -> None:  # type: ignore[no-untyped-def]
        self.input_fn = input_fn

    def ask(self, action: str, message: str) -> bool:
        try:
            answer = self.input_fn(f"{message} [y/N] ")
        except EOFError:
            return False
        return answer.strip().lower() in ("y", "yes")
