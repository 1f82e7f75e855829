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

Noise floor. The HDR variance holds the shot, read and dark noise of the merged bracket, not
pixel-to-pixel noise that is frozen into every frame: fixed-pattern noise, PRNU and dust on a
real sensor, the truth's Monte-Carlo render noise on the simulated bench (there 10^2..10^3 x
the HDR variance). Such noise is white (independent between pixels) but of unknown size, so
each angle gets an empirical noise scale f >= 1 from its normalised residuals r:

    d_i = r_i - r_{i+1}                  (adjacent pixels: a smooth mismatch cancels,
                                          white noise of variance f^2 gives var d = 2 f^2)
    f^2 = max(1, mean(min(d^2/2, c m)) / k_c)   m = median(d^2/2), c = `NOISE_CLIP`,
                                          k_c = E[min(X, c med X)] for X ~ chi^2(1)

a winsorised mean of the squared differences (efficient like a variance, robust to the few
steep pixels of a sharp mismatch and to fireflies), divided by its value under pure
Gaussian noise. It has m_eff ~ 2/3 (pixels - 1) degrees of freedom per angle (adjacent
d_i^2 correlate with coefficient 1/4).

Statistics of a fit (all reported):
* chi^2 with the HDR variance, sum r^2 ~ chi^2(dof) under a correct model *and* no excess
  noise (the classical test; with excess noise it rejects every fit).
* the noise-floor adjusted chi^2_f = sum (r / f)^2: the same with the variance scaled by f^2.
* the smooth-structure test, which decides `significant`: a variance-ratio test of the
  adjusted residual r/f, per bin width B (`smooth_test`). Each row is cut into bins of B
  adjacent pixels; with S_b the bin's sum and Q_b its sum of squares,

      T_B = sum_b S_b^2 / B      against its mean under the null   mu_B = sum_b Q_b / B.

  Under a correct model the residuals are independent with zero mean, so E[S_b^2] = E[Q_b]
  whatever the size and distribution of each pixel's noise: heavy tails (the bench's
  render fireflies, kurtosis ~200), a noise level that varies along the profile, an angle
  with its own excess. A smooth mismatch of level L adds up coherently in S_b (B^2 L^2)
  but only B L^2 to Q_b, so T_B / mu_B = (1 + B L^2) / (1 + L^2) up to B. The reference
  distribution is that of T_B under independent random signs of the pixels given their
  sizes (a randomisation test): mean mu_B and variance sum_b (2 Q_b^2 - 2 sum_i r_i^4) / B^2,
  approximated by a shifted gamma with those moments and a skewness sqrt(2) x that of the
  equivalent scaled chi^2 (few dominating fireflies give few effective degrees of freedom;
  the extra skew covers skewed render noise, see `smooth_test`). Fitted
  parameters remove smooth directions from r, which only lowers T_B (conservative). Scales
  B in `SMOOTH_BINS_PX` are tested (a blur changes the spot over a few pixels, stray light
  over the whole profile), each at alpha / scales (Bonferroni). A scale is significant
  when p < that and T_B / mu_B > 1 + `MIN_SMOOTH_EXCESS` (huge pixel counts make tiny
  structure "significant"; a 20 % excess of coherent power is the smallest we report).
  (Dividing the binned sum by the winsorised floor f^2 instead, as this test once did,
  turned heavy-tailed white noise into "structure": T/dof 7-10 on a clean simulated-bench
  fit whose variance ratio is 0.99-1.03.)

  Correlated render noise. The model's render is a Monte Carlo mean, and with the light
  engine (`estimate.light_paths`) one path adds to every column its vertices land in, a
  mean free path apart (several pixels): the render's noise is correlated along the row,
  and the pixels of a bin are not independent under the null. Its cross terms
  C_b = sum_{i != j in b} cov(r_i, r_j) are estimated from independent renders of the same
  model (`render_noise_modes`: modes M_k with cov(r_i, r_j) = sum_k M_ki M_kj) and added to
  the null, mu_B = sum_b (Q_b + C_b) / B, and to its variance (`smooth_test`'s
  `noise_modes`). Without them, a clean bench session fitted with the light engine tested
  significant on its own render noise (the demo's channel b: 16-px variance ratio 1.5, p
  1e-4; the model's noise alone, 6 x 256 spp against a 131072-spp truth, 1.55).
  A recording made by the simulated camera holds the same engine's noise, frozen: the
  difference of two demo recordings of one world (render seeds 1 and 2, no model) had a
  16-px variance ratio 1.7 and p 1e-5 on channel g. The camera twin declares it
  (`Problem.recording_paths`) and its covariance, one model render's scaled by their
  paths, joins the null too (`render_noise_modes`' `recorded`). A real camera declares
  none, and its excess noise (fixed pattern, PRNU) is white, which the floor f measures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

__all__ = [
    "ALPHA",
    "GRAZING_DEG",
    "MIN_EXCESS",
    "MIN_SMOOTH_EXCESS",
    "NOISE_CLIP",
    "PEAK_FRACTION",
    "SMOOTH_BINS_PX",
    "FitResiduals",
    "fit_significance",
    "local_noise_variance",
    "localise",
    "noise_floor",
    "normalised_residuals",
    "project_out",
    "render_noise_modes",
    "smooth_structure",
    "smooth_test",
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
#: Squared adjacent differences are winsorised at this multiple of their median.
NOISE_CLIP = 20.0
#: Bin widths (pixels) of the smooth-structure test.
SMOOTH_BINS_PX: tuple[int, ...] = (4, 16)
#: The smooth-structure test calls a mismatch significant only when T_B / mu_B exceeds 1 by
#: more than this (besides its p-value).
MIN_SMOOTH_EXCESS = 0.2


@dataclass
class FitResiduals:
    """Residuals of one channel's fit, arrays shaped (angles, pixels).

    Attributes:
        r: noise-normalised residuals with the HDR variance (dimensionless).
        chi2: sum of r^2; dof: pixels - n_params; reduced_chi2: chi2 / dof; p_value: chi^2
            tail probability (the classical test, no excess noise allowed).
        noise_scale: empirical noise scale f >= 1 per angle (`noise_floor`).
        chi2_adjusted, reduced_chi2_adjusted: the same with the variance scaled by f^2.
        smooth: the smooth-structure test per bin width (`smooth_test`).
        p_value_smooth: smallest p of the smooth test over bin widths, Bonferroni-corrected.
        significant: the smooth test rejects a correct model at level alpha with an excess
            above MIN_SMOOTH_EXCESS at some bin width.
    """

    r: np.ndarray
    chi2: float
    dof: int
    reduced_chi2: float
    p_value: float
    significant: bool
    noise_scale: np.ndarray = field(default_factory=lambda: np.ones(0))
    chi2_adjusted: float = float("nan")
    reduced_chi2_adjusted: float = float("nan")
    smooth: list[dict[str, float]] = field(default_factory=list)
    p_value_smooth: float = 1.0
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def r_adjusted(self) -> np.ndarray:
        """r / f (the residuals in units of the noise floor), shape of r."""
        r2 = np.atleast_2d(self.r)
        f = self.noise_scale if self.noise_scale.size == r2.shape[0] else np.ones(r2.shape[0])
        return (r2 / f[:, None]).reshape(np.shape(self.r))

    def summary(self) -> dict[str, Any]:
        """Plain numbers for reports."""
        f = self.noise_scale
        return {"chi2": self.chi2, "dof": self.dof, "reduced_chi2": self.reduced_chi2, "p_value": self.p_value,
                "chi2_adjusted": self.chi2_adjusted, "reduced_chi2_adjusted": self.reduced_chi2_adjusted,
                "noise_scale_median": float(np.median(f)) if f.size else 1.0,
                "noise_scale_max": float(np.max(f)) if f.size else 1.0,
                "smooth": [dict(t) for t in self.smooth], "p_value_smooth": self.p_value_smooth,
                "significant": self.significant,
                **({"smooth_as_fitted": self.extra["smooth_as_fitted"]} if "smooth_as_fitted" in self.extra else {})}


def normalised_residuals(measured: np.ndarray, variance: np.ndarray, model: np.ndarray, scale: float = 1.0,
                         model_variance: np.ndarray | None = None) -> np.ndarray:
    """(measured - scale*model) / sqrt(variance + scale^2 * model_variance), same shape."""
    m = np.asarray(measured, dtype=np.float64)
    var = np.asarray(variance, dtype=np.float64).copy()
    if model_variance is not None:
        var = var + scale ** 2 * np.asarray(model_variance, dtype=np.float64)
    var = np.where(var > 0, var, np.inf)
    return (m - scale * np.asarray(model, dtype=np.float64)) / np.sqrt(var)


def _clip_factor(c: float) -> float:
    """E[min(X, c * median X)] for X ~ chi^2(1)."""
    t = c * float(stats.chi2.ppf(0.5, 1))
    return float(stats.chi2.cdf(t, 3) + t * stats.chi2.sf(t, 1))


def noise_floor(r: np.ndarray, *, clip: float = NOISE_CLIP) -> tuple[np.ndarray, np.ndarray]:
    """Empirical white-noise scale of normalised residuals, per row (angle).

    Args:
        r: normalised residuals (angles, pixels) or (pixels,); NaN marks unused pixels
            (a difference needs both of its pixels).
        clip: winsorising multiple of the median squared difference.

    Returns:
        (f, m_eff): f >= 1 per row (dimensionless, 1 = the HDR variance is complete) and the
        effective degrees of freedom of each f^2 estimate (2/3 of its differences; 0 when a
        row has fewer than 3, then f = 1).
    """
    r2 = np.atleast_2d(np.asarray(r, dtype=np.float64))
    k = _clip_factor(clip)
    f = np.ones(r2.shape[0])
    m = np.zeros(r2.shape[0])
    for i, row in enumerate(r2):
        d = np.diff(row)
        q = 0.5 * d[np.isfinite(d)] ** 2
        if q.size < 3:
            continue
        med = float(np.median(q))
        est = float(np.mean(np.minimum(q, clip * med))) / k
        f[i] = math.sqrt(max(1.0, est))
        m[i] = 2.0 * q.size / 3.0
    return f, m


#: Reach (pixels) over which the smooth test counts the render noise's coupling of
#: neighbouring bins (`smooth_test`): a few mean free paths of the light engine's paths.
_COUPLED_PX = 32


def render_noise_modes(renders: np.ndarray, scale: float, sigma: np.ndarray, n_mean: int,
                       recorded: float = 0.0) -> np.ndarray:
    """Modes of the noise that a mean of `n_mean` renders puts into residuals divided by
    `sigma`: M (K, angles, pixels) with cov(r_i, r_j) ~ sum_k M_ki M_kj (module docstring).

    `renders` (K >= 2, angles, pixels): independent renders of the model in unit-power units,
    not necessarily the ones averaged (the same model, seeds and spp give the same
    covariance); `scale`: the fit's scale; `sigma`: each pixel's noise standard deviation
    in measured units (the residual's divisor, noise floor included). Pixels with a
    non-finite sigma get 0. `recorded`: the recording's own frozen render noise, when it
    was made by the same engine, as its variance in units of one of these renders' (their
    paths over the recording's; `estimate.refit.recorded_noise_share`): it is in the
    residual with the model's, independent of it and correlated the same way, so the
    covariance is one render's times 1 / n_mean + recorded.
    """
    rr = np.asarray(renders, dtype=np.float64)
    k = rr.shape[0]
    if k < 2:
        return np.zeros((0,) + rr.shape[1:])
    share = 1.0 / max(1, int(n_mean)) + max(0.0, float(recorded))
    dev = (rr - rr.mean(axis=0)) * (float(scale) * math.sqrt(share / (k - 1)))
    with np.errstate(invalid="ignore", divide="ignore"):
        m = dev / np.asarray(sigma, dtype=np.float64)[None]
    return np.where(np.isfinite(m), m, 0.0)


def smooth_test(r_adjusted: np.ndarray, bin_px: int, noise_modes: np.ndarray | None = None) -> dict[str, float]:
    """Variance-ratio test of adjusted residuals r/f at bin width `bin_px` (module docstring).

    Bins are contiguous pixels of one row; a bin needs all its pixels finite (bins cut by
    invalid pixels are dropped). `noise_modes` (K, angles, pixels; `render_noise_modes`, in
    the units of `r_adjusted`): the correlated part of the model's render noise, whose
    cross terms within each bin join the null. Returns bin_px, bins, statistic T,
    null_mean mu, cross (the cross terms' share of mu), reduced (T / mu), dof (shape of the
    gamma reference law: its effective degrees of freedom) and log10_p.
    """
    r2 = np.atleast_2d(np.asarray(r_adjusted, dtype=np.float64))
    w = r2.shape[1] // bin_px
    rb = r2[:, :w * bin_px].reshape(r2.shape[0], w, bin_px)
    ok = np.all(np.isfinite(rb), axis=2)
    rb = rb[ok]
    # Per bin: S = sum r (p1), Q = sum r^2 (p2), sum r^4 (q2). T - mu is (2/B) x the sum over
    # bins of their pixel-pair products r_i r_j, whose variance under independent signs is
    # (2/B^2) sum_b (Q^2 - sum r^4).
    p1, p2 = rb.sum(axis=1), (rb ** 2).sum(axis=1)
    q2 = (rb ** 4).sum(axis=1)
    t = float(np.sum(p1 ** 2) / bin_px)
    # The render noise's cross terms per bin, sum_k ((sum_b M_k)^2 - sum_b M_k^2): unbiased,
    # so a bin's estimate may be negative. The null takes their sum where it is positive
    # (white render noise, the camera engine's, has none, and a negative estimate would
    # lower the null), the variance each bin's positive part.
    cross = np.zeros_like(p2)
    between = 0.0
    if noise_modes is not None and np.size(noise_modes):
        nm = np.asarray(noise_modes, dtype=np.float64)
        k = nm.shape[0]
        mfull = nm[:, :, :w * bin_px].reshape(k, r2.shape[0], w, bin_px)
        a = mfull.sum(axis=3)                            # (K, angles, bins): each bin's sum
        mb = mfull[:, ok]
        cross = np.sum(mb.sum(axis=2) ** 2 - (mb ** 2).sum(axis=2), axis=0)
        # Correlated noise also couples neighbouring bins of a row, which adds
        # 2 sum_{b != b'} cov(S_b, S_b')^2 to the variance of sum_b S_b^2. Estimated over lags
        # up to `_COUPLED_PX` pixels, each squared covariance less the part that the few
        # renders' own scatter adds to it (var(C^) ~ v_b v_b' / (K - 1)).
        vm = np.sum(a ** 2, axis=0)
        for lag in range(1, max(1, math.ceil(_COUPLED_PX / bin_px)) + 1):
            if lag >= w:
                break
            both = ok[:, :-lag] & ok[:, lag:]
            c = np.sum(a[:, :, :-lag] * a[:, :, lag:], axis=0)
            c2 = np.maximum(c ** 2 - vm[:, :-lag] * vm[:, lag:] / max(1, k - 1), 0.0)
            between += 4.0 * float(np.sum(c2[both]))
    mu = float((p2.sum() + max(float(cross.sum()), 0.0)) / bin_px)
    var = float((np.sum(2.0 * ((p2 + np.maximum(cross, 0.0)) ** 2 - q2)) + between) / bin_px ** 2)
    if not (mu > 0 and var > 0):
        # One pixel per bin, or nothing finite: no coherent structure can be seen.
        return {"bin_px": int(bin_px), "bins": int(rb.shape[0]), "statistic": t, "null_mean": mu,
                "cross": 0.0, "dof": 0, "reduced": 1.0, "log10_p": 0.0}
    # Reference law: a shifted gamma with mean mu and this variance (Pearson type III) whose
    # skewness is sqrt(2) x that of the chi^2 with the same two moments. The margin covers
    # skewed pixel noise (render fireflies), whose pair products make the right tail of
    # T heavier than the sign-flip law: on pixels that each average 64 lognormal(0, 1.5)
    # path contributions it held 0.10 % false positives at alpha = 1e-3 in 4000 trials
    # (0.28 % without it), and 0.03 % on Gaussian noise.
    skew = 2.0 * math.sqrt(2.0 * var) / mu
    shape = 4.0 / skew ** 2
    theta = math.sqrt(var / shape)
    z = (t - (mu - shape * theta)) / theta
    logp = float(stats.gamma.logsf(max(z, 0.0), shape))
    return {"bin_px": int(bin_px), "bins": int(rb.shape[0]), "statistic": t, "null_mean": mu,
            "cross": max(float(cross.sum()), 0.0) / bin_px / mu, "dof": round(shape), "reduced": t / mu,
            "log10_p": logp / math.log(10.0)}


def local_noise_variance(r: np.ndarray, window_px: int = 5) -> np.ndarray:
    """Per-pixel variance of the white noise in r, from second differences (shape of r).

    d_i = r_{i-1} - 2 r_i + r_{i+1} has variance 6 s^2 for white noise of variance s^2 and
    cancels any mismatch that is linear over three pixels, so d_i^2 / 6, averaged over
    `window_px` pixels, follows the noise (fireflies included: a single bright pixel F
    gives sum d^2 / 6 = F^2 over its three differences) and not the smooth part of r.
    Pixels without a finite difference get the row's mean; rows without any get 1.
    Values are floored at 0.05 (a noiseless stretch would otherwise weigh infinitely).
    """
    r2 = np.atleast_2d(np.asarray(r, dtype=np.float64))
    out = np.ones_like(r2)
    for i, row in enumerate(r2):
        if row.size < 3:
            continue
        d = row[:-2] - 2.0 * row[1:-1] + row[2:]
        e = np.full(row.size, np.nan)
        e[1:-1] = d ** 2 / 6.0
        fin = np.isfinite(e)
        if not fin.any():
            continue
        k = np.ones(window_px)
        num = np.convolve(np.where(fin, e, 0.0), k, mode="same")
        den = np.convolve(fin.astype(np.float64), k, mode="same")
        est = np.where(den > 0, num / np.maximum(den, 1.0), float(np.mean(e[fin])))
        out[i] = np.maximum(est, 0.05)
    return out.reshape(np.shape(r))


def fit_significance(r: np.ndarray, n_params: int, *, alpha: float = ALPHA, min_excess: float = MIN_SMOOTH_EXCESS,
                     noise_scale: np.ndarray | None = None, bins_px: tuple[int, ...] = SMOOTH_BINS_PX,
                     noise_modes: np.ndarray | None = None) -> FitResiduals:
    """Tests of a whole fit given its normalised residuals and fitted-parameter count.

    Args:
        r: normalised residuals with the HDR variance (angles, pixels); NaN = unused pixel.
        n_params: fitted parameters (the scale counts as one).
        alpha: significance level of the smooth test (split over the bin widths).
        min_excess: smallest T_B / mu_B - 1 called significant.
        noise_scale: f per row to use instead of estimating it (to compare models on the
            same noise metric).
        bins_px: bin widths of the smooth test (widths above half a row are skipped).
        noise_modes: the model's correlated render noise in the units of r
            (`render_noise_modes`), scaled by the noise floor like r.
    """
    rr = np.asarray(r, dtype=np.float64)
    r2 = np.atleast_2d(rr)
    finite = np.isfinite(r2)
    chi2 = float(np.sum(r2[finite] ** 2))
    dof = max(1, int(finite.sum()) - int(n_params))
    red = chi2 / dof
    p = float(stats.chi2.sf(chi2, dof))
    if noise_scale is None:
        f, _ = noise_floor(r2)
    else:
        f = np.broadcast_to(np.asarray(noise_scale, dtype=np.float64), (r2.shape[0],)).copy()
    ra = r2 / f[:, None]
    chi2a = float(np.sum(ra[finite] ** 2))
    modes = None if noise_modes is None else np.asarray(noise_modes, dtype=np.float64) / f[None, :, None]
    tests, p_smooth, sig = smooth_structure(ra, alpha=alpha, min_excess=min_excess, bins_px=bins_px,
                                            noise_modes=modes)
    return FitResiduals(r=rr, chi2=chi2, dof=dof, reduced_chi2=red, p_value=p, significant=sig,
                        noise_scale=f, chi2_adjusted=chi2a, reduced_chi2_adjusted=chi2a / dof, smooth=tests,
                        p_value_smooth=p_smooth)


def smooth_structure(r_adjusted: np.ndarray, *, alpha: float = ALPHA, min_excess: float = MIN_SMOOTH_EXCESS,
                     bins_px: tuple[int, ...] = SMOOTH_BINS_PX, noise_modes: np.ndarray | None = None
                     ) -> tuple[list[dict[str, float]], float, bool]:
    """The smooth-structure test at every bin width (widths above half a row are skipped),
    with the model's correlated render noise (`noise_modes`, as `smooth_test` takes them).

    Returns (tests per width as `smooth_test` gives them, the smallest p over widths
    Bonferroni-corrected, significant: some width has p < alpha / widths and T / mu above
    1 + min_excess).
    """
    ra = np.atleast_2d(np.asarray(r_adjusted, dtype=np.float64))
    widths = [b for b in bins_px if 2 * b <= ra.shape[1]] or [1]
    tests = [smooth_test(ra, b, noise_modes) for b in widths]
    corr = math.log10(len(tests))
    best = min(t["log10_p"] for t in tests) + corr
    sig = any(t["log10_p"] + corr < math.log10(alpha) and t["reduced"] > 1.0 + min_excess for t in tests)
    return tests, float(min(1.0, 10 ** best)), bool(sig)


def project_out(r: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """r less its least-squares projection on `columns` (pixels, k), over finite pixels.

    Both in the same whitened metric; r of any shape (raveled like the columns' rows),
    NaN pixels stay NaN and take no part.
    """
    rr = np.asarray(r, dtype=np.float64)
    x = np.asarray(columns, dtype=np.float64).reshape(rr.size, -1)
    flat = rr.ravel().copy()
    ok = np.isfinite(flat) & np.all(np.isfinite(x), axis=1)
    xs = x[ok]
    norms = np.linalg.norm(xs, axis=0)
    xs = xs[:, norms > 0] / norms[norms > 0]
    if xs.shape[1]:
        coef, *_ = np.linalg.lstsq(xs, flat[ok], rcond=1e-10)
        flat[ok] = flat[ok] - xs @ coef
    return flat.reshape(rr.shape)


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
