"""Band radiometry of the simulated thermal camera: Planck's law over a band, and the grey map.

Maths (Planck's law; the source paper's section 1, see ``PAPER.md`` in the project's shared reference folder)::

    M(T) = integral_{lambda1}^{lambda2} C1 / (lambda^5 (exp(C2 / (lambda T)) - 1)) d lambda   [W m^-2]
    L(T) = M(T) / pi                                                                        [W m^-2 sr^-1]

``C1 = 2 pi h c^2 = 3.7418e-16 W m^2`` and ``C2 = h c / k = 1.4388e-2 m K``.  ``M`` is the band
*exitance* of a black body (the paper's ``E``); ``L`` is its band *radiance* (a Lambertian black
body, ``M = pi L``).  The renderer works in radiance, ``W m^-2 sr^-1``; the grey map is a ratio,
so using ``M`` or ``L`` gives the same grey values.

Grey map (the paper's)::

    grey = full_scale * (L - L(t_min_k)) / (L(t_max_k) - L(t_min_k)),   clipped to [0, full_scale]

with ``full_scale = 255`` for ``mono8`` and ``65535`` for ``mono16``.

The band integral is taken in ``x = C2 / (lambda T)`` (Gauss-Legendre, ``QUAD_NODES`` nodes on
each of a fixed set of panels); the integrand ``x^3 / (e^x - 1)`` is analytic, so the quadrature
error is ~1e-12 relative for any band (``tests/groundsim/test_planck.py`` checks it against ``scipy.integrate.quad`` and
against the closed-form series of the black-body fractional emission).
Reference: M. Planck (1901); series for the fractional function: W. J. Smith, *Modern Optical
Engineering*, 4th ed., ch. 8 (or Chang & Rhee, Int. Comm. Heat Mass Transfer 11, 1984).
"""

from __future__ import annotations

import math

import numpy as np

from onboard.core.errors import InputError

__all__ = [
    "C1_W_M2",
    "C2_M_K",
    "QUAD_NODES",
    "X_MAX",
    "band_exitance",
    "band_radiance",
    "band_radiance_derivative",
    "grey_full_scale",
    "grey_float_from_radiance",
    "grey_from_radiance",
    "noise_sigma_grey",
]

C1_W_M2 = 3.7418e-16  # first radiation constant 2 pi h c^2, W m^2
C2_M_K = 1.4388e-2  # second radiation constant h c / k, m K
QUAD_NODES = 16  # Gauss-Legendre nodes per panel
# panels in x = C2 / (lambda T): the integrand x^3 / (e^x - 1) varies on a scale of ~1 near its peak
# (x = 2.82) and decays like e^-x: above X_MAX the band contributes < 1e-80 of the total
_X_EDGES = np.array([0.0, 0.5, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0, 48.0, 64.0, 96.0, 128.0, 200.0])
X_MAX = float(_X_EDGES[-1])

_GL_X, _GL_W = np.polynomial.legendre.leggauss(QUAD_NODES)


def _check_band(band_um) -> tuple[float, float]:
    try:
        lo, hi = (float(b) for b in band_um)
    except (TypeError, ValueError) as exc:
        raise InputError(f"band_um must be two wavelengths in micrometres, got {band_um!r}") from exc
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo < hi):
        raise InputError(f"band_um must satisfy 0 < lambda1 < lambda2 (micrometres), got {band_um!r}")
    return lo, hi


def _check_temperature(T_k) -> np.ndarray:
    T = np.asarray(T_k, dtype=float)
    if not np.all(np.isfinite(T)) or np.any(T <= 0.0):
        raise InputError("T_k must be finite and > 0 kelvin")
    return T


def _x_nodes(T: np.ndarray, band_um) -> tuple[np.ndarray, np.ndarray]:
    """Quadrature nodes and weights in x = C2 / (lambda T) over the band, shape T.shape + (panels * nodes,)."""
    lo_um, hi_um = _check_band(band_um)
    x_lo = (C2_M_K / (hi_um * 1e-6 * T))[..., None]
    x_hi = np.minimum(C2_M_K / (lo_um * 1e-6 * T), X_MAX)[..., None]
    a = np.clip(_X_EDGES[:-1], x_lo, np.maximum(x_lo, x_hi))  # (..., panels); empty panels have a == b
    b = np.clip(_X_EDGES[1:], x_lo, np.maximum(x_lo, x_hi))
    half = 0.5 * (b - a)
    x = (half[..., None] * _GL_X + (0.5 * (a + b))[..., None]).reshape(T.shape + (-1,))
    w = (half[..., None] * _GL_W).reshape(T.shape + (-1,))
    return x, w


def band_exitance(T_k, band_um=(7.5, 13.5)) -> np.ndarray:
    """Black-body band exitance ``M(T)`` in W m^-2 over ``band_um`` (micrometres); the paper's ``E``.

    Integrated in ``x = C2 / (lambda T)``: ``M = C1 T^4 / C2^4 * integral x^3 / (e^x - 1) dx`` between
    ``C2 / (lambda2 T)`` and ``C2 / (lambda1 T)``, Gauss-Legendre on fixed panels, so any band
    (narrow or 0 to infinity) is integrated to ~1e-12 relative.  ``T_k`` in kelvin, any shape.
    """
    T = _check_temperature(T_k)
    x, w = _x_nodes(T, band_um)
    with np.errstate(over="ignore"):  # a band far in the Wien tail of a few-kelvin body: e^x = inf -> 0
        integral = np.sum(x**3 / np.expm1(x) * w, axis=-1)
    return C1_W_M2 * T**4 / C2_M_K**4 * integral


def band_radiance(T_k, band_um=(7.5, 13.5)) -> np.ndarray:
    """Black-body band radiance ``L(T) = M(T) / pi`` in W m^-2 sr^-1 over ``band_um`` (micrometres)."""
    return band_exitance(T_k, band_um) / math.pi


def band_radiance_derivative(T_k, band_um=(7.5, 13.5)) -> np.ndarray:
    """``dL/dT`` in W m^-2 sr^-1 K^-1: ``C1 T^3 / (pi C2^4) * integral x^4 e^x / (e^x - 1)^2 dx`` (same limits)."""
    T = _check_temperature(T_k)
    x, w = _x_nodes(T, band_um)
    with np.errstate(over="ignore"):
        em1 = np.expm1(x)
        integral = np.sum(x**4 / em1 * (1.0 + 1.0 / em1) * w, axis=-1)
    return C1_W_M2 * T**3 / C2_M_K**4 * integral / math.pi


def grey_full_scale(encoding: str) -> int:
    """255 for ``mono8``, 65535 for ``mono16``."""
    if encoding == "mono8":
        return 255
    if encoding == "mono16":
        return 65535
    raise InputError(f"encoding must be 'mono8' or 'mono16', got {encoding!r}")


def _radiance_span(settings) -> tuple[float, float]:
    lo = float(band_radiance(settings.t_min_k, settings.band_um))
    hi = float(band_radiance(settings.t_max_k, settings.band_um))
    return lo, hi


def grey_float_from_radiance(L, settings) -> np.ndarray:
    """The paper's linear grey map, unclipped and unquantised (float): ``fs (L - Lmin) / (Lmax - Lmin)``.

    ``L`` in W m^-2 sr^-1 (from :func:`band_radiance`); ``settings`` an ``IrSettings``.
    """
    lo, hi = _radiance_span(settings)
    fs = grey_full_scale(settings.encoding)
    return (np.asarray(L, dtype=float) - lo) * (fs / (hi - lo))


def grey_from_radiance(L, settings) -> np.ndarray:
    """The paper's grey map, rounded and clipped: uint8 in [0, 255] (mono8) or uint16 in [0, 65535] (mono16).

    ``L(t_min_k) -> 0`` and ``L(t_max_k) -> full scale``.  Non-finite radiance -> InputError.
    """
    L = np.asarray(L, dtype=float)
    if not np.all(np.isfinite(L)):
        raise InputError("radiance L must be finite")
    fs = grey_full_scale(settings.encoding)
    g = np.clip(np.rint(grey_float_from_radiance(L, settings)), 0, fs)
    return g.astype(np.uint8 if fs == 255 else np.uint16)


def noise_sigma_grey(settings) -> float:
    """Temporal noise, 1 sigma, in grey levels: ``netd_k * dL/dT(netd_reference_k)`` through the grey map.

    A detector's noise is (to first order) constant in radiance; its NETD is quoted at a reference
    scene temperature (FLIR Vue Pro: < 40 mK at 30 C), so the radiance noise is NETD times the
    slope of ``L(T)`` there.
    """
    lo, hi = _radiance_span(settings)
    fs = grey_full_scale(settings.encoding)
    dL_dT = float(band_radiance_derivative(settings.netd_reference_k, settings.band_um))
    return float(settings.netd_k) * dL_dT * fs / (hi - lo)
