"""Mie phase functions of spheres: one diameter (mono-dispersion) or a log-normal
distribution of diameters (poly-dispersion), tabulated on scattering angles.

Physics: a sphere of (vacuum) index ``n_particle`` in a medium of index ``n_medium`` lit
at vacuum wavelength ``lambda``; size parameter x = pi D n_medium / lambda, relative index
m = n_particle / n_medium. The Mie coefficients a_n, b_n come from miepython
(``miepython.an_bn``, Wiscombe's truncation); the amplitudes S1, S2 are summed here
with the angular functions pi_n, tau_n tabulated once per grid, so many sizes cost one
matrix product. The unpolarised phase function per steradian is

    p(theta) = (|S1|^2 + |S2|^2) / 2 / (pi x^2 Q_sca),     2 pi int p dmu = 1 exactly,

and a poly-dispersion averages the differential cross-sections over the number
distribution n(D): p = sum n_k (|S1|^2+|S2|^2)/2 / sum n_k pi x_k^2 Q_sca,k (i.e. each
size weighted by its scattering cross-section), g likewise weighted by C_sca.

Settings that reproduce the paper's table (section 3.3, mono and poly g for 30..0.01 um
at 600 nm), found in the source of the toolbox it used, MieSimulatorGUI v1 (Virtual
Photonics, github.com/VirtualPhotonics/MieSimulatorGUI, the state of 2020-10, before the
paper; no commits until 2024):

* particle index 1.377, medium index 1.333 (the GUI's defaults: scatterers in water);
  x uses the wavelength in the medium.
* angular grid 0..180 deg in 0.1 deg steps (1801 angles, the GUI's "0.1 deg" option). The
  default 0.5 deg grid gives g = 0.9913 at 30 um (paper: 0.9905) because the GUI
  integrates g with Simpson's rule over that grid and misses the forward peak.
* poly-dispersion: the GUI v1's log-normal takes a "Std. Deviation (in um)" but uses it
  as sigma of ln(r) (dimensionless); the paper's "10 % of the mean diameter" was typed in
  as 0.1 x D [um], i.e. sigma_ln = 0.1 D/um (3.0 at 30 um, the GUI's upper limit; 0.001 at
  10 nm). The GUI samples 31 radii evenly between cut-offs found on the mu = 0 standard
  curve scaled by the mean radius, weights them by the log-normal density, integrates g
  per radius with Simpson's rule and averages with scattering-coefficient weights. With
  that reproduction (``poly_model="miesimulatorgui"``) every printed g is matched to
  within one unit of its last printed digit (the paper rounds some values and truncates
  others). This is not a 10 % spread of diameters: at 30 um the sampled radii run from
  ~0 to 10.7 um.
* ``poly_model="lognormal"`` (the default) is what the paper's words describe: a
  log-normal number distribution of diameters with mean D and standard deviation
  ``spread`` x D, integrated on a uniform grid in ln D over +-4 sigma, fine enough in x to
  follow the Mie ripple.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from functools import lru_cache
from typing import Literal

import numpy as np

from estimate.errors import ModelParameterError
from estimate.phase_table import PhaseTable, simpson_weights

__all__ = [
    "PAPER_DIAMETERS_UM",
    "PAPER_G_MONO",
    "PAPER_G_POLY",
    "PAPER_SETTINGS",
    "MieSettings",
    "PolyModel",
    "mie_coefficients",
    "mie_dataset",
    "mie_mono",
    "mie_poly",
]

PolyModel = Literal["lognormal", "miesimulatorgui"]

#: The paper's Table: diameters [um] and the printed asymmetries (reference data).
PAPER_DIAMETERS_UM: tuple[float, ...] = (30, 20, 15, 10, 5, 3, 2, 1, 0.5, 0.3, 0.2, 0.1, 0.01)
PAPER_G_MONO: tuple[str, ...] = ("0.9905", "0.9929", "0.9923", "0.9963", "0.9953", "0.9907", "0.982",
                                 "0.95", "0.84", "0.65", "0.33", "0.08", "0.000789")
PAPER_G_POLY: tuple[str, ...] = ("0.9939", "0.9909", "0.9911", "0.9917", "0.9956", "0.9932", "0.985",
                                 "0.95", "0.84", "0.65", "0.33", "0.08", "0.000789")


@dataclass(frozen=True)
class MieSettings:
    """Optical settings of a Mie computation.

    Attributes:
        wavelength_nm: vacuum wavelength [nm].
        n_particle: particle index (vacuum); a complex value n + ik with k >= 0 absorbs.
        n_medium: real index of the surrounding medium (>= 1).
        n_theta: number of scattering angles, evenly spaced over [0, 180] deg (odd, so
            that Simpson's rule applies as in the GUI).
    """

    wavelength_nm: float = 600.0
    n_particle: complex = 1.377
    n_medium: float = 1.333
    n_theta: int = 1801

    def __post_init__(self) -> None:
        wl = self.wavelength_nm
        if not (isinstance(wl, (int, float)) and math.isfinite(wl) and 50.0 <= wl <= 1e5):
            raise ModelParameterError(f"wavelength_nm must be in [50, 1e5] nm, got {wl!r}")
        npart = complex(self.n_particle)
        if not (math.isfinite(npart.real) and math.isfinite(npart.imag)) or npart.real <= 0 or npart.imag < 0:
            raise ModelParameterError(f"n_particle must have a positive real part and imag >= 0, got {self.n_particle!r}")
        nm = self.n_medium
        if not (isinstance(nm, (int, float)) and math.isfinite(nm) and nm >= 1.0):
            raise ModelParameterError(f"n_medium must be a real number >= 1, got {nm!r}")
        if npart.imag == 0 and abs(npart.real / nm - 1.0) < 1e-9:
            raise ModelParameterError("n_particle equals n_medium: the particles do not scatter")
        nt = self.n_theta
        if isinstance(nt, bool) or not isinstance(nt, (int, np.integer)) or nt < 19 or nt % 2 == 0:
            raise ModelParameterError(f"n_theta must be an odd integer >= 19, got {nt!r}")

    @property
    def relative_index(self) -> complex:
        """m = n_particle / n_medium, with miepython's sign convention (n - ik)."""
        n = complex(self.n_particle)
        return complex(n.real, -n.imag) / self.n_medium

    def size_parameter(self, diameter_um: float | np.ndarray) -> np.ndarray:
        """x = pi D n_medium / lambda."""
        return np.pi * np.asarray(diameter_um, dtype=float) * self.n_medium / (self.wavelength_nm * 1e-3)

    def theta_deg(self) -> np.ndarray:
        """The angular grid [deg]."""
        return np.linspace(0.0, 180.0, self.n_theta)


#: The settings that reproduce the paper's table (see the module doc).
PAPER_SETTINGS = MieSettings(wavelength_nm=600.0, n_particle=1.377, n_medium=1.333, n_theta=1801)


def _check_diameter(d: float, name: str = "diameter_um") -> float:
    try:
        d = float(d)
    except (TypeError, ValueError):
        raise ModelParameterError(f"{name} must be a number, got {d!r}") from None
    if not (math.isfinite(d) and 1e-4 <= d <= 1000.0):
        raise ModelParameterError(f"{name} must be in [1e-4, 1000] um, got {d!r}")
    return d


def mie_coefficients(m: complex, x: float) -> tuple[np.ndarray, np.ndarray]:
    """Mie a_n, b_n (n = 1..N, Wiscombe's N) from miepython (index n - ik)."""
    import miepython

    a, b = miepython.an_bn(complex(m), float(x), 0)
    return np.asarray(a, dtype=complex), np.asarray(b, dtype=complex)


def _efficiency_and_g(a: np.ndarray, b: np.ndarray, x: float) -> tuple[float, float]:
    """Q_sca and g from the coefficients (Bohren & Huffman 4.61 and 4.62 / Wiscombe)."""
    n = np.arange(1, a.size + 1, dtype=float)
    qsca = 2.0 / x**2 * float(np.sum((2 * n + 1) * (np.abs(a) ** 2 + np.abs(b) ** 2)))
    t1 = np.sum(n[:-1] * (n[:-1] + 2) / (n[:-1] + 1) * np.real(a[:-1] * np.conj(a[1:]) + b[:-1] * np.conj(b[1:])))
    t2 = np.sum((2 * n + 1) / (n * (n + 1)) * np.real(a * np.conj(b)))
    g = 4.0 / (x**2 * qsca) * float(t1 + t2)
    return qsca, g


@lru_cache(maxsize=8)
def _pi_tau(n_theta: int, nmax: int) -> tuple[np.ndarray, np.ndarray]:
    """pi_n(mu), tau_n(mu) for n = 1..nmax on the grid (arrays nmax x n_theta)."""
    mu = np.cos(np.radians(np.linspace(0.0, 180.0, n_theta)))
    pi = np.zeros((nmax + 1, n_theta))
    tau = np.zeros((nmax + 1, n_theta))
    pi[1] = 1.0
    tau[1] = mu
    for n in range(2, nmax + 1):
        pi[n] = ((2 * n - 1) * mu * pi[n - 1] - n * pi[n - 2]) / (n - 1)
        tau[n] = n * mu * pi[n] - (n + 1) * pi[n - 1]
    pi.setflags(write=False)
    tau.setflags(write=False)
    return pi[1:], tau[1:]


def _size_batch(settings: MieSettings, x: np.ndarray) -> dict[str, np.ndarray]:
    """For size parameters x (K,): the unpolarised differential quantity
    (|S1|^2+|S2|^2)/2 (K, n_theta), Q_sca (K,), g (K,)."""
    m = settings.relative_index
    coeffs = [mie_coefficients(m, xi) for xi in x]
    nmax = max(c[0].size for c in coeffs)
    k = x.size
    A = np.zeros((k, nmax), dtype=complex)
    B = np.zeros((k, nmax), dtype=complex)
    qsca = np.empty(k)
    g = np.empty(k)
    for i, (a, b) in enumerate(coeffs):
        A[i, : a.size] = a
        B[i, : b.size] = b
        qsca[i], g[i] = _efficiency_and_g(a, b, float(x[i]))
    n = np.arange(1, nmax + 1)
    f = (2 * n + 1) / (n * (n + 1.0))
    pi, tau = _pi_tau(settings.n_theta, nmax)
    Af, Bf = A * f, B * f
    s1 = (Af.real @ pi + Bf.real @ tau) + 1j * (Af.imag @ pi + Bf.imag @ tau)
    s2 = (Af.real @ tau + Bf.real @ pi) + 1j * (Af.imag @ tau + Bf.imag @ pi)
    intensity = 0.5 * (np.abs(s1) ** 2 + np.abs(s2) ** 2)
    return {"intensity": intensity, "qsca": qsca, "g": g}


def _settings_meta(settings: MieSettings) -> dict:
    d = asdict(settings)
    d["n_particle"] = str(complex(settings.n_particle)) if complex(settings.n_particle).imag else float(
        complex(settings.n_particle).real)
    return d


def mie_mono(diameter_um: float, settings: MieSettings = PAPER_SETTINGS) -> PhaseTable:
    """Phase function of identical spheres of the given diameter [um]; g exact (from a_n, b_n)."""
    d = _check_diameter(diameter_um)
    x = settings.size_parameter(np.array([d]))
    r = _size_batch(settings, x)
    p = r["intensity"][0] / (np.pi * x[0] ** 2 * r["qsca"][0])
    return PhaseTable(theta_deg=settings.theta_deg(), p=p, g=float(r["g"][0]), label=f"mono {d:g} um",
                      diameter_um=d, meta={"kind": "mono", "x": float(x[0]), **_settings_meta(settings)})


def _lognormal_pdf(r: np.ndarray, median: float, sigma: float) -> np.ndarray:
    z = np.log(r) - math.log(median)
    return np.exp(-(z * z) / (2.0 * sigma * sigma)) / (r * sigma * math.sqrt(2.0 * math.pi))


def _gui_radius_range(mean_r: float, sigma: float, n_radius: int) -> tuple[float, float]:
    """MieSimulatorGUI v1 ``DiameterRangeSetting`` (log-normal): cut-offs where the
    standard (median 1) density falls to a size-count dependent fraction of its peak,
    scaled by the mean radius."""
    cut = -0.0005 * n_radius + 0.031 if n_radius < 52 else -0.00009 * n_radius + 0.00968
    mode = math.exp(-sigma * sigma)
    y_min = float(_lognormal_pdf(np.array([mode]), 1.0, sigma)[0]) * cut
    step = sigma * mode / 1e3
    # The GUI walks from the mode in steps of sigma*mode/1000 until the density is no
    # longer above y_min (or r <= 0, where its log gives NaN); the walk ends on the first
    # step past the crossing, which is found here by root finding instead of ~1e6 steps.
    from scipy.optimize import brentq

    def excess(r: float) -> float:
        lr = math.log(r)   # log of the median-1 density, safe far in the tails
        return -lr * lr / (2.0 * sigma * sigma) - lr - math.log(sigma * math.sqrt(2.0 * math.pi)) - math.log(y_min)

    hi_end = mode * 2.0
    while excess(hi_end) > 0:
        hi_end *= 2.0
    r_hi_star = brentq(excess, mode, hi_end, xtol=1e-15 * hi_end, rtol=1e-14)
    r_hi = mode + math.ceil((r_hi_star - mode) / step) * step
    lo_end = mode * 1e-300 if mode > 0 else 1e-300
    if excess(lo_end) < 0:
        r_lo_star = brentq(excess, lo_end, mode, xtol=1e-300, rtol=1e-14)
        r_lo = mode - math.ceil((mode - r_lo_star) / step) * step
    else:
        r_lo = 0.0
    r_min = r_lo * mean_r
    if r_min <= 0.0:
        r_min = 1e-10
    return r_min, r_hi * mean_r


def mie_poly(
    diameter_um: float,
    spread: float = 0.1,
    settings: MieSettings = PAPER_SETTINGS,
    poly_model: PolyModel = "lognormal",
    n_radius: int = 31,
) -> PhaseTable:
    """Phase function of a log-normal poly-dispersion of spheres.

    Args:
        diameter_um: mean diameter [um].
        spread: "lognormal": standard deviation of the diameters relative to their mean
            (0.1 = 10 %). "miesimulatorgui": the GUI's std-dev field is spread x D [um],
            used as sigma of ln r (the paper's datasets; see the module doc).
        settings: optical settings.
        poly_model: "lognormal" (physical) or "miesimulatorgui" (the paper's tool, v1).
        n_radius: number of radii of the GUI model (its default 31); ignored otherwise.

    Raises:
        ModelParameterError: a bad diameter, spread or model (named).
    """
    d = _check_diameter(diameter_um)
    try:
        spread = float(spread)
    except (TypeError, ValueError):
        raise ModelParameterError(f"spread must be a number, got {spread!r}") from None
    if not (math.isfinite(spread) and 0.0 < spread <= 3.0):
        raise ModelParameterError(f"spread must be in (0, 3], got {spread!r}")
    meta = {"kind": "poly", "spread": spread, "poly_model": poly_model, **_settings_meta(settings)}
    if poly_model == "lognormal":
        s_ln = math.sqrt(math.log1p(spread * spread))
        mu_ln = math.log(d) - 0.5 * s_ln * s_ln
        x_lo, x_hi = settings.size_parameter(np.exp([mu_ln - 4 * s_ln, mu_ln + 4 * s_ln]))
        # the Mie ripple has a period ~1 in x: sample it at <= 0.2
        n = int(min(4001, max(81, math.ceil((x_hi - x_lo) / 0.2) + 1)))
        n += 1 - n % 2
        z = np.linspace(-4.0, 4.0, n)
        diam = np.exp(mu_ln + s_ln * z)
        weights = np.exp(-0.5 * z * z)            # number density per unit ln D on a uniform grid
        g_source = "exact"
        meta.update(sigma_ln=s_ln, n_sizes=n)
    elif poly_model == "miesimulatorgui":
        if isinstance(n_radius, bool) or not isinstance(n_radius, int) or n_radius < 2:
            raise ModelParameterError(f"n_radius must be an integer >= 2, got {n_radius!r}")
        sigma = spread * d      # what the GUI user typed, used as sigma of ln r
        mean_r = 0.5 * d
        r_min, r_max = _gui_radius_range(mean_r, sigma, n_radius)
        r = np.linspace(r_min, r_max, n_radius)
        weights = _lognormal_pdf(r, mean_r, sigma)
        diam = 2.0 * r
        g_source = "simpson"
        meta.update(sigma_ln=sigma, n_sizes=n_radius, r_min_um=r_min, r_max_um=r_max)
    else:
        raise ModelParameterError(f"poly_model must be 'lognormal' or 'miesimulatorgui', got {poly_model!r}")
    x = settings.size_parameter(diam)
    p_acc = np.zeros(settings.n_theta)
    csca_acc = 0.0
    g_acc = 0.0
    chunk = max(1, int(4e6 // (settings.n_theta * max(1.0, float(x.max())))))
    theta = np.radians(settings.theta_deg())
    wq = simpson_weights(theta.size) * np.sin(theta)
    for s in range(0, x.size, chunk):
        xs, ws = x[s: s + chunk], weights[s: s + chunk]
        batch = _size_batch(settings, xs)
        csca = ws * np.pi * xs**2 * batch["qsca"]     # number x cross-section (common 1/k^2 dropped)
        p_acc += ws @ batch["intensity"]
        csca_acc += float(np.sum(csca))
        if g_source == "exact":
            g_k = batch["g"]
        else:   # the GUI: Simpson's rule over the angular grid, per radius
            it = batch["intensity"]
            g_k = (it @ (wq * np.cos(theta))) / (it @ wq)
        g_acc += float(np.sum(csca * g_k))
    p = p_acc / csca_acc
    return PhaseTable(theta_deg=settings.theta_deg(), p=p, g=g_acc / csca_acc, label=f"poly {d:g} um",
                      diameter_um=d, meta=meta)


def mie_dataset(
    kind: Literal["mono", "poly"],
    diameters_um: Sequence[float] = PAPER_DIAMETERS_UM,
    settings: MieSettings = PAPER_SETTINGS,
    spread: float = 0.1,
    poly_model: PolyModel = "lognormal",
) -> list[PhaseTable]:
    """Tables for several diameters, in the given order."""
    if kind == "mono":
        return [mie_mono(d, settings) for d in diameters_um]
    if kind == "poly":
        return [mie_poly(d, spread, settings, poly_model) for d in diameters_um]
    raise ModelParameterError(f"kind must be 'mono' or 'poly', got {kind!r}")
