"""Extension `beam_halo`: a weak wide halo / divergence the beam calibration missed.

Adds to the calibrated map a circular Gaussian around the map's centroid carrying
`fraction` of the map's power, standard deviation `sigma_mm` in the beam cross-section.
Derivative: Dr.Jit reverse mode (it only changes the emitter's returned irradiance).
"""

from __future__ import annotations

from estimate.extensions.base import Extension, ParameterSpec

__all__ = ["BeamHalo"]


class BeamHalo(Extension):
    name = "beam_halo"
    kind = "scene"
    neutral_is_identity = True
    parameters = (
        ParameterSpec("fraction", 0.0, 0.0, 1.0, "", "ad", 0.002,
                      "halo power relative to the calibrated beam power"),
        ParameterSpec("sigma_mm", 1.0, 0.0, 50.0, "mm", "ad", 0.05,
                      "halo standard deviation in the beam cross-section", open_lower=True),
    )
