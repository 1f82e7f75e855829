"""Score (Lagrange-multiplier) tests of the catalogue extensions at a base fit.

At the base optimum theta0 (extension absent), the whitened residual r and the whitened
derivative columns X of the base parameters (and of the scale) are known. A candidate
extension with parameters psi adds columns Z = d profile / d psi at psi = neutral. The score
test projects Z orthogonal to X in the noise metric, Z' = (I - X X^+) Z, and measures how
much of r lies in their span:

    LM = r^T Z' (Z'^T Z')^+ Z'^T r  ~  chi^2(k)  under "the extension is absent",

k = rank of Z'. No refit is needed: one set of derivative columns per candidate.

The chi^2(k) law assumes every whitened pixel has unit variance. Where the noise is
heavy-tailed or its level varies along the profile (the bench's render fireflies: a clean
fit's residuals had kurtosis ~200, and the plain LM of a blur reached 157 on 2 dof), the
statistic uses the heteroscedasticity-robust (sandwich) variance of the projections,

    LM = p^T (U^T diag(v) U)^-1 p,    p = U^T r,   U = orthonormal basis of Z',

with v the local noise variance of each pixel (`estimate.residuals.local_noise_variance`,
from second differences, so a smooth mismatch does not inflate it). With v = 1 it is the
classical statistic.

The metric is the noise-floor adjusted one (`estimate.residuals`): r = residual / (f sigma)
and columns whitened by f sigma, with f >= 1 the empirical white-noise scale of each angle.
With the HDR variance alone, excess pixel noise (fixed-pattern noise, the bench's frozen
render noise) would inflate every LM statistic by f^2 and make every candidate "significant".

Some extensions have a zero first derivative at their neutral value (a Gaussian blur of
width s changes the image by O(s^2); a symmetric band mixture by O(spread^2)), and some
neutral values sit on a bound (n = 1, fraction = 0) where only one-sided changes are
physical. Their columns are therefore secants to a small, realistic probe magnitude
(`PROBES`): the direction in which the profiles move when the effect appears. The test
statistic does not depend on the columns' scale.

`sensor_nonlinearity` acts on raw frames. With the recording's brackets its one column is
-I g, g the merge's mean squared fill of the well per pixel (`estimate.problem.
merge_fill_from_rows`: exact, the model's own form). Without them the columns of the
full-well form: -I (I / W)^2 with the well filled either at the brightest pixel of the
channel or of each angle (the bracket picks a short exposure per angle). The compression of
the beam calibration's own frame (`sensor_nonlinearity.calibration_gain`) adds
I sum_p w_p g_p, a multiple of the profiles, which the scale column absorbs: the columns
leave it out.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import stats

from estimate.extensions import EXTENSIONS
from estimate.extensions.lens_blur import LensBlur

if TYPE_CHECKING:
    from estimate.forward import ForwardModel

__all__ = ["PROBES", "RANK_LOG10_P_FLOOR", "CandidateScore", "candidate_columns", "ranked", "score_test", "screen"]

#: Below this log10 p a candidate's significance is beyond doubt, and the screening ranks
#: such candidates by their statistic (the excess chi^2 each could remove) instead. The
#: tail probabilities themselves stop meaning anything there: chi^2 tails underflow to
#: 0 (log10 p = -inf) while an F law, used where the model's render noise is estimated
#: from a few renders, keeps a finite p for the same statistic. On the light bench's
#: lens_blur-2 the blur (statistic 87 222 on 2 dof, log10 p -304 by its F law) ranked behind
#: four candidates at -inf that could remove 1-67 % of the excess against its 71 %, and
#: was never refitted.
RANK_LOG10_P_FLOOR = -50.0

#: Probe values (secant end points) of the scene extensions' parameters.
PROBES: dict[str, list[dict[str, float]]] = {
    "refractive_boundary": [{"refractive_boundary.n": 1.1}],
    "angle_offset": [{"angle_offset.delta_deg": 2.0}],
    "thickness_error": [{"thickness_error.e": 0.1}],
    "beam_halo": [{"beam_halo.fraction": 0.02, "beam_halo.sigma_mm": 0.5},
                  {"beam_halo.fraction": 0.02, "beam_halo.sigma_mm": 2.0}],
    "filter_bandwidth": [{"filter_bandwidth.spread": 0.3}],
    # Rendered only where the beam map was imaged through the lens (`ForwardModel.deblurs_beam`):
    # the blur then also reshapes the map the slab is lit by. The same probes as `image_columns`.
    "lens_blur": [{"lens_blur.core_sigma_px": 1.5}, {"lens_blur.tail_fraction": 0.02}],
}


@dataclass
class CandidateScore:
    """Screening result of one extension.

    Attributes:
        name: extension name.
        statistic: LM statistic; dof: its degrees of freedom (rank of the projected columns).
        p_value: chi^2(dof) tail probability; log10_p: its log10 (finite for huge statistics).
        explained: fraction of the fit's chi^2 excess (chi2 - dof) this candidate could remove
            to first order (LM / excess).
        coefficients: least-squares coefficients of the projected columns (probe units).
    """

    name: str
    statistic: float
    dof: int
    p_value: float
    log10_p: float
    explained: float
    coefficients: list[float] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "statistic": self.statistic, "dof": self.dof, "p_value": self.p_value,
                "log10_p": self.log10_p, "explained": self.explained}


def score_test(r: np.ndarray, X: np.ndarray, Z: np.ndarray, excess: float | None = None,
               name: str = "", noise_var: np.ndarray | None = None,
               noise_modes: np.ndarray | None = None) -> CandidateScore:
    """LM test of columns Z (n, k) given residual r (n,) and base columns X (n, p), all whitened.

    `noise_var` (n,): each pixel's noise variance in the whitened units (None: 1, the
    classical test); with it the projections' variance is the sandwich U^T diag(v) U.
    `noise_modes` (K, n): the model's correlated render noise in the units of r
    (`estimate.residuals.render_noise_modes`); its covariance between pixels (the modes'
    products less their diagonal, which `noise_var` already holds) joins the sandwich. The
    light engine's render noise is correlated along the row, and a smooth candidate column
    sums it coherently: without it, a clean demo session's beam halo scored 16 on 2 dof.
    """
    r = np.asarray(r, dtype=np.float64).ravel()
    X = np.asarray(X, dtype=np.float64).reshape(r.size, -1)
    Z = np.asarray(Z, dtype=np.float64).reshape(r.size, -1)
    v = np.ones(r.size) if noise_var is None else np.asarray(noise_var, dtype=np.float64).ravel()
    modes = None if noise_modes is None or not np.size(noise_modes) else \
        np.asarray(noise_modes, dtype=np.float64).reshape(-1, r.size)
    ok = np.isfinite(r) & np.all(np.isfinite(X), axis=1) & np.all(np.isfinite(Z), axis=1) & np.isfinite(v)
    r, X, Z, v = r[ok], X[ok], Z[ok], v[ok]
    if modes is not None:
        modes = np.nan_to_num(modes[:, ok])
    q, _ = np.linalg.qr(X / np.maximum(np.linalg.norm(X, axis=0), 1e-300))
    zp = Z - q @ (q.T @ Z)
    norms = np.linalg.norm(zp, axis=0)
    keep = norms > 1e-8 * np.maximum(np.linalg.norm(Z, axis=0), 1e-300)
    zp = zp[:, keep]
    if zp.shape[1] == 0:
        return CandidateScore(name, 0.0, 0, 1.0, 0.0, 0.0, [])
    u, s, vt = np.linalg.svd(zp / norms[keep], full_matrices=False)
    rank = int(np.sum(s > 1e-6 * s[0]))
    proj = u[:, :rank].T @ r
    # Degrees of freedom of the sandwich's estimate (Satterthwaite): infinite where it is
    # known, K - 1 over the square of the render noise's share where that share comes from
    # K renders (then lm / rank follows an F law rather than chi^2 / rank).
    nu = math.inf
    if noise_var is None and modes is None:
        lm = float(proj @ proj)
    else:
        ur = u[:, :rank]
        cov = ur.T @ (v[:, None] * ur)
        if modes is not None:
            w = ur.T @ modes.T
            cross = w @ w.T - ur.T @ (np.sum(modes ** 2, axis=0)[:, None] * ur)
            # An estimate from a few renders, only its positive part: where the render noise
            # is white (the camera engine) its true value is 0, and a negative estimate
            # would shrink the sandwich and raise the statistic (a clean 128-spp recording
            # tested significant through the stray light's score that way).
            ev, evec = np.linalg.eigh(cross)
            cov = cov + (evec * np.maximum(ev, 0.0)) @ evec.T
            share = float(np.sum(np.maximum(ev, 0.0))) / max(float(np.trace(cov)), 1e-300)
            if share > 0.0:
                nu = max(1.0, (modes.shape[0] - 1)) / share ** 2
        lm = float(proj @ np.linalg.solve(cov, proj))
    coef = np.zeros(Z.shape[1])
    coef[keep] = (vt[:rank].T @ (proj / s[:rank])) / norms[keep]
    if math.isfinite(nu):
        logsf = float(stats.f.logsf(lm / rank, rank, nu)) / np.log(10.0)
    else:
        logsf = float(stats.chi2.logsf(lm, rank)) / np.log(10.0)
    exc = excess if excess is not None else max(float(r @ r) - r.size, 1.0)
    return CandidateScore(name, lm, rank, float(10 ** logsf), logsf, lm / max(exc, 1.0), coef.tolist())


def image_columns(name: str, base: np.ndarray, pixel_mm: float,
                  y_shape: np.ndarray | None = None, merge_fill: np.ndarray | None = None) -> list[np.ndarray]:
    """Columns of an image-space extension from the base-fit render (unscaled), each (N, W).
    `y_shape`: the recording's shape across rows for the lens blur (`ForwardModel.y_shape_for`);
    `merge_fill`: the merge's fill for the sensor compression (`ForwardModel.merge_fill_for`)."""
    base = np.asarray(base, dtype=np.float64)
    if name == "stray_light":
        w = base.shape[-1]
        x = (np.arange(w) + 0.5 - 0.5 * w) * pixel_mm
        return [np.ones_like(base), np.broadcast_to(x, base.shape).copy()]
    if name == "lens_blur":
        img = base[:, None, :]
        d = LensBlur.parameters
        neutral = {p.name: p.neutral for p in d}
        core = dict(neutral, core_sigma_px=1.5)
        tail = dict(neutral, tail_fraction=0.02)
        return [(LensBlur.apply(img, v, pixel_mm=pixel_mm, profile_only=True, y_shape=y_shape)[:, 0, :] - base)
                for v in (core, tail)]
    if name == "sensor_nonlinearity":
        pos = np.clip(base, 0, None)
        if merge_fill is not None:
            return [-pos * np.asarray(merge_fill, dtype=np.float64).reshape(pos.shape)]
        w_all = max(float(pos.max()), 1e-300)
        w_ang = np.maximum(pos.max(axis=1, keepdims=True), 1e-300)
        return [-pos * (pos / w_all) ** 2, -pos * (pos / w_ang) ** 2]
    raise KeyError(name)


def candidate_columns(model: ForwardModel, params: Mapping[str, float], angles_deg: Sequence[float],
                      base: np.ndarray, names: Sequence[str], *, spp: int, seed: int,
                      render: Callable[..., np.ndarray] | None = None) -> dict[str, list[np.ndarray]]:
    """Derivative (secant) columns of each candidate at the base fit, unscaled profiles (N, W).

    `model` is a ForwardModel factory result with every scene candidate switched on
    (extensions at neutral values reproduce the base model); `base` its render at `params`
    with the same `spp` and `seed` (common random numbers for the secants). The lens blur's
    columns are rendered too when `model` includes it with a beam map imaged through the lens
    (`ForwardModel.deblurs_beam`): the calibration frame carries that blur already, and what
    the recording shows of it is only where the slab's image does not repeat the map's (the
    oblique footprint, the scattered light).
    """
    out: dict[str, list[np.ndarray]] = {}
    pm = model.geometry.pixel_mm
    for name in names:
        if EXTENSIONS[name].kind == "image" and not (name == "lens_blur" and getattr(model, "deblurs_beam", False)):
            out[name] = image_columns(name, base, pm, model.y_shape_for(angles_deg) if name == "lens_blur" else None,
                                      getattr(model, "merge_fill_for", lambda a: None)(angles_deg)
                                      if name == "sensor_nonlinearity" else None)
            continue
        cols = []
        for probe in PROBES[name]:
            p = dict(params)
            p.update(probe)
            prof = model.render_profiles(p, angles_deg, spp=spp, seed=seed)
            cols.append(prof - base)
        out[name] = cols
    return out


def screen(r: np.ndarray, sigma: np.ndarray, base_columns: Sequence[np.ndarray], scale: float,
           candidates: Mapping[str, Sequence[np.ndarray]], excess: float,
           noise_var: np.ndarray | None = None, noise_modes: np.ndarray | None = None) -> list[CandidateScore]:
    """Rank candidates by their score test (smallest p-value first; beyond doubt, largest
    statistic first: `ranked`).

    Args:
        r: normalised residuals (N, W), in units of the noise floor (r / f).
        sigma: noise standard deviation per pixel (N, W) used to whiten columns, including
            the noise floor (f sigma).
        base_columns: d(measured model)/d(base parameter) incl. the scale column, each (N, W).
        scale: fitted scale (candidate columns are unscaled renders).
        candidates: name -> unscaled columns.
        excess: chi2 - dof of the base fit (the adjusted chi2).
        noise_var: local noise variance of each pixel in units of the floor (N, W), for the
            robust statistic (`score_test`); None: the classical one.
        noise_modes: the model's correlated render noise (K, N, W) in the units of r
            (`score_test`).
    """
    X = np.stack([np.ravel(c / sigma) for c in base_columns], axis=1)
    out = []
    for name, cols in candidates.items():
        Z = np.stack([np.ravel(scale * c / sigma) for c in cols], axis=1)
        out.append(score_test(np.ravel(r), X, Z, excess, name,
                              None if noise_var is None else np.ravel(noise_var), noise_modes))
    return ranked(out)


def ranked(scores: Sequence[CandidateScore]) -> list[CandidateScore]:
    """The screening's order: smallest p first, and below `RANK_LOG10_P_FLOOR` (significance
    beyond doubt) the largest statistic first."""
    return sorted(scores, key=lambda c: (max(c.log10_p, RANK_LOG10_P_FLOOR), -c.statistic))
