"""Noise-normalised residuals of a fit, the test of the whole fit, and where a mismatch sits.

r = (measured - scale * model) / sqrt(var_data + scale^2 * var_model), with var_data the HDR
variance of the recording and var_model the Monte-Carlo variance of the rendered profile.
Under a correct model r is ~N(0, 1) per pixel, so sum r^2 ~ chi^2 with
dof = pixels - fitted parameters (the scale counts as one).

Localisation splits the residuals into regions and reports each region's chi^2 excess
(sum r^2 - pixels, in units of its own standard deviation sqrt(2 * pixels)):
front- (0 < phi < 90) vs back-lit (90 < phi < 180) angles, grazing (angle of incidence
> `GRAZING_DEG` from the slab normal) vs normal angles, the peak of the profile (model
above `PEAK_FRACTION` of its maximum) vs the tails, and the left/right asymmetry of the
signed residual about each angle's spot centroid.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

__all__ = [
    "ALPHA",
    "GRAZING_DEG",
    "MIN_EXCESS",
    "PEAK_FRACTION",
    "FitResiduals",
    "fit_significance",
    "localise",
    "normalised_residuals",
]

#: Angle of incidence (deg from the slab normal) above which a light angle counts as grazing.
GRAZING_DEG = 60.0
#: Pixels where the model exceeds this fraction of its per-angle maximum form the "peak".
PEAK_FRACTION = 0.1
#: Significance level of the whole-fit test.
ALPHA = 1e-3
#: A fit whose reduced chi^2 exceeds 1 by less than this is called consistent even when the
#: p-value is small (huge pixel counts make sub-percent model errors "significant").
MIN_EXCESS = 0.05


@dataclass
class FitResiduals:
    """Residuals of one channel's fit, arrays shaped (angles, pixels).

    Attributes:
        r: noise-normalised residuals (dimensionless).
        chi2: sum of r^2; dof: pixels - n_params; reduced_chi2: chi2 / dof.
        p_value: probability of a chi^2 at least this large under a correct model.
        significant: p_value < ALPHA and reduced_chi2 > 1 + MIN_EXCESS.
    """

    r: np.ndarray
    chi2: float
    dof: int
    reduced_chi2: float
    p_value: float
    significant: bool
    extra: dict[str, Any] = field(default_factory=dict)


def normalised_residuals(measured: np.ndarray, variance: np.ndarray, model: np.ndarray, scale: float = 1.0,
                         model_variance: np.ndarray | None = None) -> np.ndarray:
    """(measured - scale*model) / sqrt(variance + scale^2 * model_variance), same shape."""
    m = np.asarray(measured, dtype=np.float64)
    var = np.asarray(variance, dtype=np.float64).copy()
    if model_variance is not None:
        var = var + scale ** 2 * np.asarray(model_variance, dtype=np.float64)
    var = np.where(var > 0, var, np.inf)
    return (m - scale * np.asarray(model, dtype=np.float64)) / np.sqrt(var)


def fit_significance(r: np.ndarray, n_params: int, *, alpha: float = ALPHA,
                     min_excess: float = MIN_EXCESS) -> FitResiduals:
    """chi^2 test of a whole fit given its normalised residuals and fitted-parameter count."""
    rr = np.asarray(r, dtype=np.float64)
    finite = np.isfinite(rr)
    chi2 = float(np.sum(rr[finite] ** 2))
    dof = max(1, int(finite.sum()) - int(n_params))
    red = chi2 / dof
    p = float(stats.chi2.sf(chi2, dof))
    return FitResiduals(r=rr, chi2=chi2, dof=dof, reduced_chi2=red, p_value=p,
                        significant=bool(p < alpha and red > 1.0 + min_excess))


def _excess(r: np.ndarray) -> dict[str, float]:
    r = r[np.isfinite(r)]
    n = int(r.size)
    if n == 0:
        return {"pixels": 0, "reduced_chi2": float("nan"), "excess_sigma": 0.0}
    c = float(np.sum(r ** 2))
    return {"pixels": n, "reduced_chi2": c / n, "excess_sigma": (c - n) / np.sqrt(2.0 * n)}


def incidence_deg(phi_deg: float) -> float:
    """Angle between the beam and the slab normal (0 = normal, 90 = grazing), degrees."""
    a = abs(float(phi_deg)) % 360.0
    a = min(a, 360.0 - a)
    return min(a, 180.0 - a)


def localise(r: np.ndarray, angles_deg: np.ndarray, x_mm: np.ndarray, model: np.ndarray) -> dict[str, Any]:
    """Where a mismatch concentrates.

    Args:
        r: normalised residuals (angles, pixels).
        angles_deg: light angle phi of each row (deg).
        x_mm: pixel positions along the profile (mm).
        model: the fitted profile (same shape; any positive scale) for peak/tail and centroid.

    Returns a dict with `per_angle` (angle -> excess), region entries `front`, `back`,
    `grazing`, `normal`, `peak`, `tails` (each: pixels, reduced_chi2, excess_sigma),
    `asymmetry` (signed mean residual left and right of the spot and their difference in
    sigma), `dominant` (region pairs where one side carries clearly more excess) and
    `summary` (one plain sentence).
    """
    r = np.asarray(r, dtype=np.float64)
    ang = np.asarray(angles_deg, dtype=np.float64)
    x = np.asarray(x_mm, dtype=np.float64)
    mod = np.asarray(model, dtype=np.float64)
    out: dict[str, Any] = {"per_angle": {f"{a:g}": _excess(r[i]) for i, a in enumerate(ang)}}
    front = (ang % 360.0) < 90.0
    back = ~front
    inc = np.array([incidence_deg(a) for a in ang])
    grazing = inc > GRAZING_DEG
    rowmask = lambda m: r[m]
    out["front"] = _excess(rowmask(front))
    out["back"] = _excess(rowmask(back))
    out["grazing"] = _excess(rowmask(grazing))
    out["normal"] = _excess(rowmask(~grazing))
    peak = mod >= PEAK_FRACTION * np.max(mod, axis=1, keepdims=True)
    out["peak"] = _excess(r[peak])
    out["tails"] = _excess(r[~peak])
    # Left/right about each angle's centroid of the model profile.
    w = np.clip(mod, 0, None)
    cen = (w * x[None, :]).sum(axis=1) / np.maximum(w.sum(axis=1), 1e-300)
    left = x[None, :] < cen[:, None]
    fin = np.isfinite(r)
    lvals = r[left & fin]
    rvals = r[~left & fin]
    ml = float(lvals.mean()) if lvals.size else 0.0
    mr = float(rvals.mean()) if rvals.size else 0.0
    se = np.sqrt(1.0 / max(1, lvals.size) + 1.0 / max(1, rvals.size))
    out["asymmetry"] = {"mean_left": ml, "mean_right": mr, "difference_sigma": float((ml - mr) / se)}
    dominant = []
    for a, b in (("front", "back"), ("grazing", "normal"), ("peak", "tails")):
        ea, eb = out[a]["excess_sigma"], out[b]["excess_sigma"]
        if max(ea, eb) > 5.0:
            if ea > 3.0 * max(eb, 1.0):
                dominant.append(a)
            elif eb > 3.0 * max(ea, 1.0):
                dominant.append(b)
    if abs(out["asymmetry"]["difference_sigma"]) > 5.0:
        dominant.append("left" if out["asymmetry"]["difference_sigma"] > 0 else "right")
    out["dominant"] = dominant
    worst = max(out["per_angle"].items(), key=lambda kv: kv[1]["excess_sigma"])
    out["worst_angle_deg"] = float(worst[0])
    out["summary"] = _summary(out, dominant)
    return out


def _summary(loc: dict[str, Any], dominant: list[str]) -> str:
    words = {"front": "front-lit angles", "back": "back-lit angles", "grazing": "grazing angles",
             "normal": "near-normal angles", "peak": "the peak of the profiles",
             "tails": "the tails of the profiles", "left": "the left side of the spot (model too low there)",
             "right": "the right side of the spot (model too low there)"}
    if not dominant:
        where = "spread over all angles and the whole profile"
    else:
        where = "concentrated in " + ", ".join(words[d] for d in dominant)
    return f"{where}; worst angle {loc['worst_angle_deg']:g} deg"
