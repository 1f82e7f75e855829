"""Gauss-Newton building blocks of the fit (`estimate.fit.fit_channel`, `estimate.polish`).

The fit steps in the optimiser's variables z (log sigma_t, logit albedo, bounded phase
parameters; `estimate.transforms`). Here: finite-difference Jacobians of the rendered
profiles in z (`gn_jacobian`, large secant steps `GN_DZ` / `secant_steps`), their columns as
log-residual derivatives (`gn_columns`, optionally smoothed along the row), the Gauss-Newton
matrix and its inverse (`gn_inverse`, eigenvalues floored at `GN_EIG_FLOOR` of the largest),
the cross product of two independent Jacobians held between bounds (`bounded_cross`), the
plain and the signal/noise-shrunk step (`gn_direction`, `snr_step`) and the step's predicted
decrease with its gradient-noise level (`predicted_decrease`).
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence

import numpy as np
from scipy.ndimage import gaussian_filter1d

from estimate.forward import ForwardModel
from estimate.model_protocols import ProfileModel
from estimate.problem import Problem
from estimate.transforms import Transform, transform_for

__all__ = ["CROSS_FLOOR", "GN_DB", "GN_DZ", "GN_EIG_FLOOR", "averaged_gradient_cov", "bounded_cross",
           "gn_columns", "gn_direction", "gn_inverse", "gn_jacobian", "predicted_decrease", "secant_steps",
           "smooth_rows", "snr_step"]


def averaged_gradient_cov(recent: Sequence[np.ndarray], momentum: float) -> np.ndarray | None:
    """Covariance of the momentum-averaged gradient: the per-iteration covariance C from
    successive differences of the recent gradients (C = mean(d d^T) / 2, which ignores slow
    trends), times (1 - m) / (1 + m) for an exponential average with momentum m; None with
    fewer than 3 gradients."""
    if len(recent) < 3:
        return None
    d = np.diff(np.asarray(recent), axis=0)
    return 0.5 * (d.T @ d) / len(d) * (1.0 - momentum) / (1.0 + momentum)


def predicted_decrease(h_inv: np.ndarray, g_avg: np.ndarray, recent: Sequence[np.ndarray],
                       momentum: float) -> tuple[float, float]:
    """The loss decrease the Gauss-Newton model predicts for a full step, 0.5 g^T H^-1 g with
    g the averaged gradient, and the part of it that the gradient's Monte Carlo noise alone
    would produce, 0.5 tr(H^-1 C_avg) (`averaged_gradient_cov`).
    """
    pred = 0.5 * float(g_avg @ h_inv @ g_avg)
    cov = averaged_gradient_cov(recent, momentum)
    return pred, float("nan") if cov is None else 0.5 * float(np.trace(h_inv @ cov))


#: Finite-difference steps, in the optimiser's variables z, for the Gauss-Newton matrix.
#: Large on purpose: with common random numbers the renders are not smooth functions of
#: the parameters (a free flight that crosses the slab boundary flips, and the rest of the
#: path decorrelates), so at the parameters' default steps the columns of one seed differed
#: from another seed's by up to 2x (sigma_t, b3) while the reverse-mode gradients agreed
#: within 10 %. Steps of 5 % in sigma_t and 0.5 in b_i bring the spread to ~15 %, enough
#: for a preconditioner: the gradient itself always comes from the reverse-mode pass.
GN_DZ = {"log": 0.05, "logit": 0.3, "tanh": 0.1}


GN_DB = 0.5


#: Smallest eigenvalue of the Gauss-Newton matrix, relative to its largest (see gn_direction).
GN_EIG_FLOOR = 1e-4


def smooth_rows(a: np.ndarray, valid: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian smoothing (sigma in pixels) of (N, W) columns along each row, over valid
    pixels only (normalised convolution); invalid pixels come back as 0."""
    if sigma_px <= 0.0:
        return np.where(valid, a, 0.0)
    w = valid.astype(float)
    num = gaussian_filter1d(np.where(valid, a, 0.0), sigma_px, axis=-1, mode="constant")
    norm = gaussian_filter1d(w, sigma_px, axis=-1, mode="constant")
    return np.where(valid & (norm > 0), num / np.where(norm > 0, norm, 1.0), 0.0)


def snr_step(h_inv: np.ndarray, g_avg: np.ndarray, recent: Sequence[np.ndarray], momentum: float) -> np.ndarray:
    """H^-1 g_avg with each eigen-direction of H^-1 shrunk by s = m^2 / (m^2 + v): m the
    averaged gradient's component along it, v that component's Monte Carlo variance
    (`averaged_gradient_cov`). Directions where the
    gradient is mostly noise (the sigma_t / phase valley's floor, b2 against b3) get short
    steps instead of H^-1's amplification of that noise; well-measured directions keep the
    full Gauss-Newton step. With fewer than 3 gradients there is no noise estimate: s = 1."""
    mu, V = np.linalg.eigh(0.5 * (h_inv + h_inv.T))
    proj = V.T @ g_avg
    cov = averaged_gradient_cov(recent, momentum)
    if cov is None:
        return V @ (mu * proj)
    var = np.einsum("ik,ij,jk->k", V, cov, V)
    shrink = proj ** 2 / np.maximum(proj ** 2 + var, 1e-300)
    return V @ (mu * shrink * proj)


def secant_steps(fm: ProfileModel, params: Mapping[str, float], names: Sequence[str]) -> dict[str, float]:
    """Finite-difference steps (in each parameter's own units) for Jacobians that must
    describe the mean trend of Monte Carlo renders rather than one seed's jagged surface:
    5 % in sigma_t, 0.3 in logit albedo, 0.1 in atanh g, 0.5 in b_i, 3x the default
    otherwise, and never below the parameter's default step."""
    steps: dict[str, float] = {}
    for n in names:
        spec = fm.specs[n]
        x = float(params[n])
        default = spec.fd_step * max(1.0, abs(x))
        t = transform_for(n, spec)
        if t.kind in GN_DZ:
            steps[n] = max(default, GN_DZ[t.kind] * t.dx_dz(t.to_z(x)))
        elif n.startswith("phase.b"):
            steps[n] = GN_DB
        else:
            steps[n] = 3.0 * default
    return steps


def gn_jacobian(fm: ForwardModel, problem: Problem, p: Mapping[str, float], names: Sequence[str],
                *, spp: int, seed: int) -> dict[str, np.ndarray]:
    """d profiles / d x at `p` for the Gauss-Newton matrix (central differences, large steps)."""
    return fm.jacobian(p, problem.angles_deg, list(names), spp=spp, seed=seed, steps=secant_steps(fm, p, names))


def gn_direction(jac: Mapping[str, np.ndarray], names: Sequence[str], tr: Sequence[Transform], z: np.ndarray,
                 problem: Problem, mean: np.ndarray, dl: float, m: np.ndarray, profiled_scale: bool,
                 grad_z: np.ndarray, damping: float = 1e-3, eig_floor: float | None = None) -> np.ndarray:
    """Gauss-Newton step in z for the log loss mean(r^2) given its gradient `grad_z`
    (-H^-1 grad_z with H^-1 from `gn_inverse`)."""
    return -(gn_inverse(jac, names, tr, z, problem, mean, dl, m, profiled_scale, damping, eig_floor) @ grad_z)


def gn_columns(jac: Mapping[str, np.ndarray], names: Sequence[str], tr: Sequence[Transform], z: np.ndarray,
               problem: Problem, mean: np.ndarray, d: float, m: np.ndarray, profiled_scale: bool,
               profiled_columns: Sequence[np.ndarray] = (), smooth_px: float = 0.0,
               exact: Collection[str] = ()) -> np.ndarray:
    """A = d r / d z (pixels x len(names)) of the log residuals r = log(m + d) - log(I + d)
    at absolute delta `d`, with the profiled directions (scale, additive columns) projected
    out; see `gn_inverse`."""
    valid = problem.valid
    den = np.clip(mean, 0.0, None) + d
    cols = [smooth_rows(np.where(valid, -jac[nm] / den, 0.0), valid, 0.0 if nm in exact else smooth_px).ravel()
            * t.dx_dz(float(zz)) for nm, t, zz in zip(names, tr, z)]
    A = np.stack(cols, axis=1)
    A = np.where(np.isfinite(A), A, 0.0)
    out_cols = [np.where(valid, -np.asarray(c) / den, 0.0).ravel() for c in profiled_columns]
    if profiled_scale:
        out_cols.append(np.where(valid, -m / (np.clip(m, -0.5 * d, None) + d), 0.0).ravel())
    if out_cols:
        Q, R = np.linalg.qr(np.stack(out_cols, axis=1))
        keep = np.abs(np.diag(R)) > 1e-12 * max(1e-300, float(np.max(np.abs(np.diag(R)))))
        Q = Q[:, keep]
        A = A - Q @ (Q.T @ A)
    return A


#: Smallest generalised eigenvalue of the cross-product matrix against the two Jacobians'
#: mean's (see bounded_cross).
CROSS_FLOOR = 0.5


def bounded_cross(h_cross: np.ndarray, h_mean: np.ndarray, floor: float) -> np.ndarray:
    """The cross-product Gauss-Newton matrix held between `floor` x and 1 x the matrix of the
    two Jacobians' mean, in the generalised eigenvalues of one against the other.

    Noise only adds to a Gram matrix, so the noise-free matrix lies below the mean's (the
    cross product's generalised eigenvalues above 1 are noise). Below, the cross product's
    weak directions are themselves noisy, and near zero its inverse turned noise into steps
    that threw sigma_t from 3.45 to 1.8 (truth 3.0) on the fit tests' small session with
    128-spp halves; `floor` keeps each step within 1 / `floor` x the mean matrix's step
    (at 0.5 the first steps there ended 2.56-2.91 at three seeds, at 0.25 1.97-2.61, the
    mean matrix's 3.05-3.08; on the benchmark the cross product's sigma_t step was 1.3x the
    mean's, session 17).
    """
    lam_m, V = np.linalg.eigh(0.5 * (h_mean + h_mean.T))
    if lam_m.size == 0 or not np.all(np.isfinite(lam_m)) or lam_m[-1] <= 0.0:
        return h_cross
    root = V * np.sqrt(np.clip(lam_m, 1e-12 * lam_m[-1], None))       # h_mean = root root^T
    inv_root = np.linalg.inv(root)
    lam, U = np.linalg.eigh(inv_root @ (0.5 * (h_cross + h_cross.T)) @ inv_root.T)
    lam = np.clip(lam, floor, 1.0)
    return root @ (U * lam) @ U.T @ root.T


def gn_inverse(jac: Mapping[str, np.ndarray], names: Sequence[str], tr: Sequence[Transform], z: np.ndarray,
               problem: Problem, mean: np.ndarray, dl: float | Sequence[float], m: np.ndarray, profiled_scale: bool,
               damping: float = 1e-3, eig_floor: float | None = None,
               profiled_columns: Sequence[np.ndarray] = (), smooth_px: float = 0.0,
               exact: Collection[str] = (), jac_cross: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
    """Inverse of the Gauss-Newton matrix of the log loss mean(r^2) in the variables z.

    `profiled_columns`: d profiles / d p (N, W) of parameters solved at every iteration
    outside z (additive ones); like a profiled scale, their directions are projected out.

    The matrix is 2/n A^T A with A = dr/dz = -J / (I + delta) dx/dz at this iteration's delta
    and profiles; with a profiled scale the scale's column is projected out (the scale is
    re-optimised at every iteration, so the other parameters move in its orthogonal
    complement). The gradient is the reverse-mode one (unbiased); only the matrix comes from
    finite differences. The Monte Carlo noise of a finite-difference Jacobian adds its own
    Gram matrix to A^T A: at the one-channel benchmark's end point one 256-spp Jacobian gave
    eigenvalues 2-13x those of two independent Jacobians' cross product (A1^T A2 + A2^T A1)
    / n, whose expectation is the noise-free matrix, so the steps are that much shorter than
    Newton steps. The cross product was tried as the matrix (session 4, with a trust region
    capping the predicted decrease at the loss): its small eigenvalues are noise, and the
    fit diverged both times (sigma_t 2 -> 11 and 18). The inflated matrix is kept in the
    iterations: it makes the steps short but safe. The polish after them uses the cross
    product (`jac_cross`: the second Jacobian's columns B, matrix (A^T B + B^T A) / n), where
    the smoothing and higher spp keep its noise small; see `gn_polish`.

    `dl` (absolute delta) may be several values: the matrix is then the mean of theirs, the
    Gauss-Newton matrix of the loss averaged over delta. The fit draws delta at random per
    iteration and averages the gradients over iterations (momentum), so its averaged gradient
    is that of the delta-averaged loss; a matrix at the iteration's own delta did not match
    it. Over the default range (0.01-0.2) the matrix's weakest eigenvalue changed by up to 25x
    from one iteration to the next, and when a large-delta matrix met gradients averaged
    over small deltas the step along the weakest direction (b2 against b3) was up to 50x
    the usual, capped per component (the benchmark at seed 3: b2 -1.7 -> -5, sigma_t 21 %
    high at the end).

    `smooth_px` > 0 smooths each column of A along the row first (`smooth_rows`, Gaussian,
    valid pixels only), except those named in `exact` (image-space parameters such as the
    lens blur's, whose columns are exact and may be sharp). The finite-difference columns are smooth functions of x and the noise is nearly
    independent per pixel, so this removes most of the noise Gram matrix: at the benchmark's
    end point the generalised eigenvalues of one 256-spp matrix against a smoothed
    4096-spp one fell from 1.2-63 to 0.9-5.8 with 3 px (the 4096-spp matrix smoothed with
    3 px moves by 0.79-0.99 against itself smoothed with 2 px: the bias is small).
    """
    eig_floor = GN_EIG_FLOOR if eig_floor is None else eig_floor
    n = max(1, int(problem.valid.sum()))
    dls = [float(dl)] if np.isscalar(dl) else [float(x) for x in dl]  # type: ignore[arg-type, union-attr]
    H = np.zeros((len(names), len(names)))
    H_mean = np.zeros((len(names), len(names)))
    for d in dls:
        A = gn_columns(jac, names, tr, z, problem, mean, d, m, profiled_scale, profiled_columns, smooth_px, exact)
        if jac_cross is None:
            H += 2.0 * (A.T @ A) / n / len(dls)
        else:
            B = gn_columns(jac_cross, names, tr, z, problem, mean, d, m, profiled_scale, profiled_columns,
                           smooth_px, exact)
            H += (A.T @ B + B.T @ A) / n / len(dls)
            H_mean += 0.5 * ((A + B).T @ (A + B)) / n / len(dls)
    if jac_cross is not None:
        H = bounded_cross(H, H_mean, CROSS_FLOOR)
    H = H + damping * np.diag(np.diag(H)) + 1e-12 * np.eye(len(names))
    # Eigenvalue floor: directions the data barely constrain (two-term HG with the
    # forward lobe's weight -> 1 leaves g_backward free; albedo -> 1) have eigenvalues near
    # zero, and H^-1 would turn the gradient's Monte Carlo noise there into full-size steps.
    # Flooring them at `eig_floor` x the largest turns those components into short
    # gradient steps; exp3's well-posed matrices (condition ~1e3) are left unchanged.
    lam, V = np.linalg.eigh(0.5 * (H + H.T))
    lam_max = float(lam[-1]) if lam.size else 0.0
    if not np.isfinite(lam_max) or lam_max <= 0.0:
        return np.eye(len(names))
    lam = np.maximum(lam, eig_floor * lam_max)
    return (V / lam) @ V.T
