"""Extension `filter_bandwidth`: the channel is a band, not one wavelength.

The rendered channel is the mixture over the filter's band of renders whose extinction
varies linearly across it: sigma_t(x) = sigma_t * (1 + spread * x), x in [-1, 1] over the
band, flat passband. The mixture is integrated with `NODES`-point Gauss-Legendre
quadrature (exact for the mixture of a smooth response to 2*NODES - 1 degree).
`spread` = 0 is a single wavelength, rendered as one node. Every node is rendered with the
same random numbers (`ForwardModel._bands`), so near `spread` = 0 the band keeps common
random numbers with a model without it. Derivative: Dr.Jit
reverse mode (finite differences, like sigma_t, when `refractive_boundary` is on; see
ForwardModel).
"""

from __future__ import annotations

import numpy as np

from estimate.extensions.base import Extension, ParameterSpec

__all__ = ["NODES", "FilterBandwidth", "band_nodes"]

NODES = 3


def band_nodes(n: int = NODES) -> tuple[np.ndarray, np.ndarray]:
    """Nodes x_k in [-1, 1] and weights summing to 1 (flat passband)."""
    x, w = np.polynomial.legendre.leggauss(n)
    return x, w / w.sum()


class FilterBandwidth(Extension):
    name = "filter_bandwidth"
    kind = "scene"
    neutral_is_identity = True  # spread 0 renders one node, the single wavelength itself
    parameters = (
        ParameterSpec("spread", 0.0, 0.0, 0.9, "", "ad", 0.02,
                      "relative half-range of sigma_t across the band"),
    )
