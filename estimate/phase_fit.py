"""Fitting phase-function models to a tabulated phase function, in the log domain.

Error (the paper's, section 3.3): SAD = sum over the table's angles of
|ln p_model(mu_j) - ln p_table(mu_j)| (natural log; divide by ln 10 for decades).

Models (names parsed strictly): ``expM`` (exponential, degree M >= 0, b_0 from the
normalisation), ``polyN`` (polynomial, degree N >= 0, a_0 from the normalisation),
``hg``, ``tthg``. Every model is normalised over the sphere; none gets a free scale.

* exp: ln p is linear in b_0..b_M, so a linear least-squares fit and an exact L1 fit
  (iteratively reweighted least squares) with b_0 free give two starts; the better one,
  once b_0 is tied to the normalisation, is refined on the true SAD
  with b_0 tied to the normalisation (smoothed |r| -> sqrt(r^2 + eps^2) with eps
  decreasing, L-BFGS with the analytic gradient d b_0/d b_i = -<Q_i>_p). Internally the
  Legendre basis is used (better conditioned); results are reported in the paper's
  monomial basis too.
* poly: p is linear in a_1..a_N, so a relative least-squares fit and a relative L1 fit
  (IRLS) give starts; a start that is <= 0 at any grid angle cannot be
  scored in the log domain. Starts positive on the grid are refined (Powell) with the SAD
  set to +inf wherever the polynomial leaves the positive side. If no start is positive
  the fit is reported as failed (SAD None), never clipped.
* hg: a scan over atanh(g) and a bounded Brent refinement. tthg: a grid of starts over
  (g1 >= 0, g2 <= 0, w) and bounded Nelder-Mead from the best few.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.polynomial import legendre as _leg
from scipy import optimize

from estimate.errors import DataError, ModelParameterError
from estimate.phase_exponential import ExponentialPhase, log_norm_and_grad
from estimate.phase_hg import HenyeyGreenstein, TwoTermHG, hg_log_eval
from estimate.phase_polynomial import ISOTROPIC, PolynomialPhase, normalised_design
from estimate.phase_table import PhaseTable

__all__ = [
    "PAPER_MODELS",
    "FitResult",
    "ModelSpec",
    "fit_model",
    "fit_models",
    "parse_model",
    "parse_models",
    "sad",
]

#: The nine models of the paper's comparison, in its order.
PAPER_MODELS: tuple[str, ...] = ("poly7", "poly5", "poly3", "hg", "tthg", "exp7", "exp5", "exp3", "exp1")
_MAX_DEGREE = 20
_G_MAX = 0.99999
_NAME = re.compile(r"^(poly|exp)(-?\d+)$")


@dataclass(frozen=True)
class ModelSpec:
    """A parsed model name: kind in {"exp", "poly", "hg", "tthg"} and degree (0 for hg/tthg)."""

    kind: str
    degree: int = 0

    @property
    def name(self) -> str:
        """Canonical name (``exp7``, ``hg``...)."""
        return f"{self.kind}{self.degree}" if self.kind in ("exp", "poly") else self.kind


def parse_model(name: str) -> ModelSpec:
    """Parse ``polyN``, ``expN``, ``hg`` or ``tthg`` (case-insensitive, no spaces inside).

    Raises:
        ModelParameterError: unknown name, or a degree < 0 or > 20 (named).
    """
    if not isinstance(name, str):
        raise ModelParameterError(f"model name must be a string, got {name!r}")
    s = name.strip().lower()
    if s in ("hg", "tthg"):
        return ModelSpec(s)
    m = _NAME.match(s)
    if not m:
        raise ModelParameterError(
            f"unknown phase model {name!r}; expected polyN, expN (N = degree), hg or tthg")
    deg = int(m.group(2))
    if deg < 0:
        raise ModelParameterError(f"degree of {name!r} must be >= 0, got {deg}")
    if deg > _MAX_DEGREE:
        raise ModelParameterError(f"degree of {name!r} must be <= {_MAX_DEGREE}, got {deg}")
    return ModelSpec(m.group(1), deg)


def parse_models(names: str | Sequence[str]) -> list[ModelSpec]:
    """Parse a comma-separated list (or a sequence) of model names; duplicates dropped.

    Raises:
        ModelParameterError: empty list or a bad name.
    """
    items = names.split(",") if isinstance(names, str) else list(names)
    out: list[ModelSpec] = []
    for it in items:
        if isinstance(it, str) and not it.strip():
            raise ModelParameterError(f"empty model name in {names!r}")
        spec = parse_model(it)
        if spec not in out:
            out.append(spec)
    if not out:
        raise ModelParameterError("no phase model given")
    return out


@dataclass
class FitResult:
    """Outcome of one fit.

    Attributes:
        model: canonical model name.
        sad: SAD of ln p over the table, or None when the fit failed.
        params: the fitted parameters (JSON-ready): exp -> b (monomial b_0..b_M) and
            b_legendre; poly -> a (a_0..a_N) and positive_on_sphere; hg -> g;
            tthg -> g1, g2, w. Also the model's asymmetry "g".
        message: why a fit failed, or "" on success.
        phase: the fitted phase-function object (None when failed).
    """

    model: str
    sad: float | None
    params: dict[str, Any] = field(default_factory=dict)
    message: str = ""
    phase: Any = None

    @property
    def ok(self) -> bool:
        """True when the fit succeeded."""
        return self.sad is not None

    def log_eval(self, mu: np.ndarray) -> np.ndarray:
        """ln p of the fitted model at mu."""
        if self.phase is None:
            raise ModelParameterError(f"{self.model}: fit failed, nothing to evaluate")
        if hasattr(self.phase, "log_eval"):
            return self.phase.log_eval(mu)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.log(self.phase.eval(mu))

    def to_json(self) -> dict[str, Any]:
        """{"model", "sad", "params", "message"}."""
        return {"model": self.model, "sad": self.sad, "params": self.params, "message": self.message}


def sad(log_model: np.ndarray, log_data: np.ndarray) -> float:
    """Sum of absolute differences of two log phase functions on the same grid."""
    return float(np.sum(np.abs(np.asarray(log_model) - np.asarray(log_data))))


def _check_table(table: PhaseTable) -> tuple[np.ndarray, np.ndarray]:
    mu = np.asarray(table.mu, dtype=float)
    p = np.asarray(table.p, dtype=float)
    if mu.shape != p.shape or mu.size < 3:
        raise DataError(f"{table.label or 'table'}: needs >= 3 angles with one p each")
    if np.any(~np.isfinite(p)) or np.any(p <= 0):
        raise DataError(f"{table.label or 'table'}: p must be finite and > 0 to fit in the log domain")
    return mu, np.log(p)


# -- exponential ---------------------------------------------------------------------------

def _l1_linear(X: np.ndarray, y: np.ndarray, iters: int = 60) -> np.ndarray | None:
    """argmin_c sum |X c - y| by iteratively reweighted least squares (weights 1/|r|,
    floored); returns None if the iteration breaks down."""
    c, *_ = np.linalg.lstsq(X, y, rcond=None)
    scale = float(np.median(np.abs(y - X @ c))) or 1.0
    floor = 1e-8 * max(scale, 1e-12)
    for _ in range(iters):
        r = np.abs(X @ c - y)
        w = 1.0 / np.sqrt(np.maximum(r, floor))
        c_new, *_ = np.linalg.lstsq(X * w[:, None], y * w, rcond=None)
        if not np.all(np.isfinite(c_new)):
            return None
        done = np.max(np.abs(c_new - c)) <= 1e-10 * (1.0 + np.max(np.abs(c)))
        c = c_new
        if done:
            break
    return c


def _fit_exp(mu: np.ndarray, y: np.ndarray, degree: int) -> FitResult:
    name = f"exp{degree}"
    if degree == 0:
        e = ExponentialPhase.isotropic()
        return FitResult(name, sad(e.log_eval(mu), y), {"b": [e.b0], "b_legendre": [e.b0], "g": 0.0},
                         phase=e)
    X = _leg.legvander(mu, degree)
    starts = []
    c_ls, *_ = np.linalg.lstsq(X, y, rcond=None)
    starts.append(c_ls[1:])
    c_l1 = _l1_linear(X, y)
    if c_l1 is not None:
        starts.append(c_l1[1:])
    Xr = X[:, 1:]

    def residual(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        b0, db0 = log_norm_and_grad(c, "legendre")
        return b0 + Xr @ c - y, db0

    def smooth(c: np.ndarray, eps: float) -> tuple[float, np.ndarray]:
        r, db0 = residual(c)
        s = np.sqrt(r * r + eps * eps)
        d = r / s
        return float(np.sum(s)), d @ Xr + np.sum(d) * db0

    best_c, best_sad = None, math.inf
    for c0 in starts:
        c0 = np.asarray(c0, dtype=float)
        if np.max(np.abs(c0)) > 5e4:
            continue
        s0 = float(np.sum(np.abs(residual(c0)[0])))
        if s0 < best_sad:
            best_c, best_sad = c0, s0
    if best_c is not None:
        c = best_c
        scale = best_sad / y.size
        for eps in (0.3 * scale, 0.03 * scale, 1e-3 * scale, 1e-5 * scale):
            res = optimize.minimize(smooth, c, args=(max(eps, 1e-9),), jac=True, method="L-BFGS-B",
                                    options={"maxiter": 300, "gtol": 1e-9, "ftol": 1e-12})
            if np.all(np.isfinite(res.x)) and np.max(np.abs(res.x)) < 5e4:
                c = res.x
        s_exact = float(np.sum(np.abs(residual(c)[0])))
        if s_exact < best_sad:
            best_c, best_sad = c, s_exact
    if best_c is None:
        return FitResult(name, None, {}, "no usable start (coefficients out of range)")
    e = ExponentialPhase(best_c, "legendre")
    mono = e.full_coeffs("monomial")
    return FitResult(name, best_sad, {"b": mono.tolist(), "b_legendre": e.full_coeffs("legendre").tolist(),
                                      "g": e.g}, phase=ExponentialPhase(mono[1:], "monomial"))


# -- polynomial ----------------------------------------------------------------------------

def _fit_poly(mu: np.ndarray, y: np.ndarray, degree: int) -> FitResult:
    name = f"poly{degree}"
    p = np.exp(y)
    if degree == 0:
        ph = PolynomialPhase([])
        return FitResult(name, sad(np.full_like(y, math.log(ISOTROPIC)), y),
                         {"a": ph.full_coeffs().tolist(), "positive_on_sphere": True, "g": 0.0}, phase=ph)
    D = normalised_design(mu, degree)
    # relative residual (p_fit - p)/p ~ ln p_fit - ln p where the fit is close
    Dw = D / p[:, None]
    rhs = (p - ISOTROPIC) / p
    starts = [np.linalg.lstsq(Dw, rhs, rcond=None)[0]]
    a_l1 = _l1_linear(Dw, rhs)
    if a_l1 is not None:
        starts.append(a_l1)

    def objective(a: np.ndarray) -> float:
        q = ISOTROPIC + D @ a
        if np.any(q <= 0) or not np.all(np.isfinite(q)):
            return math.inf
        return float(np.sum(np.abs(np.log(q) - y)))

    def smooth(a: np.ndarray, eps: float) -> tuple[float, np.ndarray]:
        q = ISOTROPIC + D @ a
        if np.any(q <= 0) or not np.all(np.isfinite(q)):
            # outside the region where ln p exists: a wall the line search backs off from
            return 1e300, np.zeros_like(a)
        r = np.log(q) - y
        sq = np.sqrt(r * r + eps * eps)
        return float(np.sum(sq)), ((r / sq) / q) @ D

    best_a, best_sad, worst = None, math.inf, None
    for a0 in starts:
        f0 = objective(a0)
        if not math.isfinite(f0):
            q = ISOTROPIC + D @ a0
            j = int(np.argmin(q))
            worst = (float(np.degrees(np.arccos(np.clip(mu[j], -1, 1)))), float(q[j]))
            continue
        if f0 < best_sad:
            best_a, best_sad = np.asarray(a0, dtype=float), f0
    if best_a is not None:
        a = best_a
        scale = best_sad / y.size
        for eps in (0.3 * scale, 0.03 * scale, 1e-3 * scale, 1e-5 * scale):
            res = optimize.minimize(smooth, a, args=(max(eps, 1e-12),), jac=True, method="L-BFGS-B",
                                    options={"maxiter": 300, "gtol": 1e-12, "ftol": 1e-13})
            if math.isfinite(objective(res.x)):
                a = res.x
        f = objective(a)
        if f < best_sad:
            best_a, best_sad = a, f
    if best_a is None:
        where = f" (p = {worst[1]:.3g} at theta = {worst[0]:.1f} deg)" if worst else ""
        return FitResult(name, None, {}, f"polynomial fit is <= 0 on the grid{where}; cannot fit in the log domain")
    ph = PolynomialPhase(best_a)
    m, _ = ph.min_value()
    return FitResult(name, best_sad, {"a": ph.full_coeffs().tolist(), "positive_on_sphere": bool(m > 0),
                                      "min_on_sphere": m, "g": ph.g}, phase=ph)


# -- Henyey-Greenstein ---------------------------------------------------------------------

def _fit_hg(mu: np.ndarray, y: np.ndarray) -> FitResult:
    smax = math.atanh(_G_MAX)

    def f(s: float) -> float:
        return sad(hg_log_eval(mu, math.tanh(s)), y)

    grid = np.linspace(-smax, smax, 241)
    vals = np.array([f(s) for s in grid])
    i = int(np.argmin(vals))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    res = optimize.minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"xatol": 1e-10})
    s = float(res.x) if res.fun <= vals[i] else float(grid[i])
    h = HenyeyGreenstein(math.tanh(s))
    return FitResult("hg", f(s), {"g": h.g}, phase=h)


def _tthg_log(mu: np.ndarray, g1: float, g2: float, w: float) -> np.ndarray:
    with np.errstate(divide="ignore"):
        a = math.log(w) if w > 0 else -np.inf
        b = math.log1p(-w) if w < 1 else -np.inf
    return np.logaddexp(a + hg_log_eval(mu, g1), b + hg_log_eval(mu, g2))


def _fit_tthg(mu: np.ndarray, y: np.ndarray) -> FitResult:
    bounds = [(0.0, _G_MAX), (-_G_MAX, 0.0), (0.0, 1.0)]

    def f(v: np.ndarray) -> float:
        g1, g2, w = (float(np.clip(v[i], *bounds[i])) for i in range(3))
        return sad(_tthg_log(mu, g1, g2, w), y)

    starts = [np.array([g1, g2, w]) for g1 in (0.3, 0.7, 0.9, 0.97, 0.99, 0.998)
              for g2 in (-0.1, -0.4, -0.8) for w in (0.6, 0.9, 0.99)]
    hg = _fit_hg(mu, y).params["g"]          # the one-lobe optimum is a two-term start (w = 1)
    if hg >= 0:
        starts.append(np.array([hg, -0.3, 1.0]))
    vals = np.array([f(s) for s in starts])
    best_v, best_f = None, math.inf
    for k in np.argsort(vals)[:3]:
        res = optimize.minimize(f, starts[k], method="Nelder-Mead", bounds=bounds,
                                options={"xatol": 1e-9, "fatol": 1e-10, "maxiter": 3000, "maxfev": 3000})
        v, fv = (res.x, float(res.fun)) if res.fun < vals[k] else (starts[k], float(vals[k]))
        if fv < best_f:
            best_v, best_f = v, fv
    assert best_v is not None  # the starts' own values bound the best from above
    g1, g2, w = (float(np.clip(best_v[i], *bounds[i])) for i in range(3))
    t = TwoTermHG(g1, g2, w)
    return FitResult("tthg", best_f, {"g1": g1, "g2": g2, "w": w, "g": t.asymmetry}, phase=t)


# -- entry points --------------------------------------------------------------------------

_BLAS_THREAD_SYMBOLS = (
    ("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),   # numpy wheels
    ("scipy_openblas_get_num_threads", "scipy_openblas_set_num_threads"),         # scipy wheels
    ("openblas_get_num_threads", "openblas_set_num_threads"),                     # system OpenBLAS
)


@contextlib.contextmanager
def _single_threaded_blas() -> Iterator[None]:
    """Run OpenBLAS single-threaded inside the block (best effort, Linux only).

    The fits solve thousands of tiny problems (1801 x 8 least squares, L-BFGS updates);
    OpenBLAS threads spinning on a shared 2-core machine made them 10-20x slower.
    """
    restore: list[tuple[Any, int]] = []
    try:
        with open("/proc/self/maps", encoding="utf-8") as fh:
            paths = {line.split()[-1] for line in fh if "openblas" in line.lower() and "/" in line}
    except OSError:
        paths = set()
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for get_name, set_name in _BLAS_THREAD_SYMBOLS:
            getter, setter = getattr(lib, get_name, None), getattr(lib, set_name, None)
            if getter is None or setter is None:
                continue
            getter.restype = ctypes.c_int
            old = int(getter())
            setter.argtypes = [ctypes.c_int]
            setter(1)
            restore.append((setter, old))
            break
    try:
        yield
    finally:
        for setter, old in restore:
            setter(old)


def fit_model(table: PhaseTable, model: str | ModelSpec) -> FitResult:
    """Fit one model to a table (see the module doc).

    Raises:
        ModelParameterError: unknown model name.
        DataError: the table has non-positive or non-finite values.
    """
    spec = model if isinstance(model, ModelSpec) else parse_model(model)
    mu, y = _check_table(table)
    with _single_threaded_blas():
        if spec.kind == "exp":
            return _fit_exp(mu, y, spec.degree)
        if spec.kind == "poly":
            return _fit_poly(mu, y, spec.degree)
        if spec.kind == "hg":
            return _fit_hg(mu, y)
        return _fit_tthg(mu, y)


def fit_models(table: PhaseTable, models: str | Sequence[str | ModelSpec] = PAPER_MODELS
               ) -> list[FitResult]:
    """Fit several models (names parsed first, so a bad name fails before any work)."""
    specs = parse_models(models) if isinstance(models, str) else [
        m if isinstance(m, ModelSpec) else parse_model(m) for m in models]
    return [fit_model(table, s) for s in specs]
