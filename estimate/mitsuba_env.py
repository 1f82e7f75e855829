"""Load Mitsuba 3 safely on this project's machines and pick its variant.

Dr.Jit's CPU backend loads a system libLLVM at import time. LLVM 14 is refused
by Dr.Jit; LLVM 15 and 16 load but abort the whole process at the first render
("LLVM ERROR: Cannot select ... fminimum"), so they must never be reached.
LLVM 19 works. This module points ``DRJIT_LIBLLVM_PATH`` at a libLLVM 19
before Mitsuba is imported and refuses 15/16 with a Python exception.
"""

from __future__ import annotations

import functools
import glob
import os
import re
import shutil
import subprocess
from types import ModuleType

from estimate.errors import EstimateError

__all__ = ["MitsubaSetupError", "default_variant", "find_libllvm", "init_mitsuba", "renders_on_gpu"]

_LLVM_GLOBS = (
    "/usr/lib/*/libLLVM-19.so*",
    "/usr/lib/*/libLLVM.so.19*",
    "/usr/lib/llvm-19/lib/libLLVM*.so*",
)
_BAD_MAJORS = (15, 16)
_VARIANT_ENV = "RIG_MITSUBA_VARIANT"

_state: dict[str, object] = {}


class MitsubaSetupError(EstimateError, RuntimeError):
    """Raised when Mitsuba cannot be set up: no usable libLLVM, a libLLVM known to
    abort the process (15/16), or an unknown variant name."""


def _llvm_major(path: str) -> int | None:
    """Major version of a libLLVM file from its name (libLLVM-19.so, libLLVM.so.19.1)."""
    name = os.path.basename(os.path.realpath(path))
    for pattern in (r"libLLVM-(\d+)", r"libLLVM\.so\.(\d+)"):
        m = re.search(pattern, name)
        if m:
            return int(m.group(1))
    m = re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else None


def find_libllvm() -> str | None:
    """Path of a libLLVM 19 shared library on this system, or None."""
    for pattern in _LLVM_GLOBS:
        for path in sorted(glob.glob(pattern)):
            if os.path.isfile(path) and _llvm_major(path) == 19:
                return path
    return None


@functools.cache
def _gpu_usable() -> bool:
    """True when an NVIDIA driver answers (the CUDA variants need one). Asked once a process:
    `nvidia-smi` can take seconds, and `FitSettings.for_variant` and the benchmarks' caches
    ask for the default variant many times."""
    if shutil.which("nvidia-smi") is None:
        return False
    try:
        out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, timeout=10, text=True, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return out.returncode == 0 and "GPU" in out.stdout


def default_variant() -> str:
    """`RIG_MITSUBA_VARIANT` if set, else `cuda_ad_mono` with a GPU, else `llvm_ad_mono`."""
    env = os.environ.get(_VARIANT_ENV)
    if env:
        return env
    return "cuda_ad_mono" if _gpu_usable() else "llvm_ad_mono"


def renders_on_gpu(variant: str | None = None) -> bool:
    """Whether a Mitsuba variant renders on a GPU (`cuda_*`); None asks `default_variant()`,
    the one `init_mitsuba` will pick. What the device-dependent defaults (the estimator's
    final spp, the diagnosis' spp) key on."""
    return (default_variant() if variant is None else variant).startswith("cuda")


def active_variant() -> str | None:
    """The variant `init_mitsuba` set in this process (None before the first call)."""
    v = _state.get("variant")
    return str(v) if v is not None else None


def _prepare_llvm() -> None:
    path = os.environ.get("DRJIT_LIBLLVM_PATH")
    if not path:
        path = find_libllvm()
        if path is None:
            raise MitsubaSetupError(
                "no libLLVM 19 found for Mitsuba's CPU backend (install Debian package "
                "libllvm19 or set DRJIT_LIBLLVM_PATH)")
        os.environ["DRJIT_LIBLLVM_PATH"] = path
    major = _llvm_major(path)
    if major in _BAD_MAJORS:
        raise MitsubaSetupError(
            f"DRJIT_LIBLLVM_PATH={path} is LLVM {major}, which aborts the process at the "
            "first render; point it at libLLVM 19")
    if not os.path.exists(path):
        raise MitsubaSetupError(f"DRJIT_LIBLLVM_PATH={path} does not exist")


def init_mitsuba(variant: str | None = None) -> ModuleType:
    """Import Mitsuba with a safe libLLVM and set its variant; idempotent.

    Args:
        variant: a Mitsuba variant name (`llvm_ad_mono`, `cuda_ad_mono`...); None picks
            `default_variant()`. Calling again with another variant switches to it.

    Returns:
        The `mitsuba` module with the variant set.

    Raises:
        MitsubaSetupError: no usable libLLVM (CPU variants), LLVM 15/16, unknown variant.
    """
    chosen = variant or default_variant()
    if _state.get("variant") == chosen:
        return _state["module"]  # type: ignore[return-value]
    if chosen.startswith(("llvm", "scalar")):
        _prepare_llvm()
    import mitsuba as mi

    if chosen not in mi.variants():
        raise MitsubaSetupError(
            f"unknown Mitsuba variant {chosen!r}; available: {', '.join(mi.variants())}")
    mi.set_variant(chosen)
    # The plugins are registered per variant.
    from estimate import beam, mitsuba_integrator, mitsuba_phase

    mitsuba_phase.register_plugins()
    beam.register_plugins()
    mitsuba_integrator.register_plugins()
    _state["variant"] = chosen
    _state["module"] = mi
    return mi
