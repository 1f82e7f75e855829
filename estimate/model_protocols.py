"""What the refits, evaluations and screening ask of a forward model and of a recording.

`estimate.forward.ForwardModel` and `estimate.problem.Problem` are the real ones. The
diagnosis' tests steer it with small stand-ins (a Gaussian profile whose width is the
"effect", a recording built in memory), so the functions that only render, difference and
compare profiles take these protocols instead of the concrete classes. They say what a
stand-in must have; mypy (`tests/test_typing.py`) checks the packages' own callers against
them, not the tests' stand-ins, which are not type-checked.

Units: angles in degrees (the stage angle phi), profiles in the model's radiance units (per
unit of the calibrated scale), measured radiance and its variance in e-/s and (e-/s)^2.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Protocol

import numpy as np
import numpy.typing as npt

from estimate.extensions.base import ParameterSpec

__all__ = ["ProfileModel", "ProfileRecording"]


class ProfileModel(Protocol):
    """A forward model of one channel's profile rows (`estimate.forward.ForwardModel`)."""

    @property
    def specs(self) -> Mapping[str, ParameterSpec]:
        """Every parameter's range, neutral value and finite-difference step, by name."""
        ...

    @property
    def extensions(self) -> Sequence[str]:
        """The catalogue effects switched on, in the order they act."""
        ...

    def validate(self, params: Mapping[str, float]) -> dict[str, float]:
        """Every parameter's value (defaults filled in); raises
        `estimate.errors.ModelParameterError` outside a range."""
        ...

    def render_profiles(self, params: Mapping[str, float], angles_deg: npt.ArrayLike, *,
                        spp: int = ..., seed: int = ...) -> np.ndarray:
        """Profile rows (N angles, W pixels) at `spp` samples per pixel; the same seed gives
        the same numbers (common random numbers between parameter values)."""
        ...

    def render_profiles_many(self, requests: Sequence[tuple[Mapping[str, float], int]], angles_deg: npt.ArrayLike,
                             *, spp: int = ...) -> list[np.ndarray]:
        """`render_profiles` for each (params, seed), in order."""
        ...

    def jacobian(self, params: Mapping[str, float], angles_deg: npt.ArrayLike, names: Sequence[str], *,
                 spp: int = ..., seed: int = ..., steps: Mapping[str, float] | None = None,
                 columns: tuple[int, int] | None = None, base_profiles: np.ndarray | None = None,
                 backward: bool = False) -> dict[str, np.ndarray]:
        """d profiles / d parameter (N, W) for each of `names`, per unit of the parameter."""
        ...


class ProfileRecording(Protocol):
    """One channel's measured profile rows (`estimate.problem.Problem`)."""

    #: stage angles phi of the rows (degrees), shape (N,)
    angles_deg: np.ndarray
    #: radiance (e-/s per pixel), shape (N, W)
    measured: np.ndarray
    #: its variance ((e-/s)^2), shape (N, W); inf where unmeasured
    variance: np.ndarray
