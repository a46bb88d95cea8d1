"""Planck band radiometry and the paper's grey map (groundsim.world.render.planck).

Independent references: scipy.integrate.quad of Planck's law in wavelength; the closed-form series
of the black-body fractional function F(0 -> lambda T) and its tabulated values (Incropera et al.,
Fundamentals of Heat and Mass Transfer, Table 12.2); Stefan-Boltzmann's law.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import quad

from groundsim.world.render import planck
from groundsim.world.render.planck import C1_W_M2, C2_M_K
from groundsim.world.render.settings import IrSettings
from onboard.core.errors import InputError

QUAD_RTOL = 1e-9  # our quadrature vs scipy's adaptive quad
SERIES_RTOL = 1e-9  # vs the fractional-function series (200 terms: exact to double precision)
TABLE_ATOL = 1e-4  # vs 6-digit table values (their own rounding of C2 and of lambda*T)
SIGMA_SB = 5.670374419e-8  # W m^-2 K^-4, CODATA 2018
SIGMA_RTOL = 1e-4  # C1, C2 are given to 5 digits
DERIV_RTOL = 1e-6  # analytic dL/dT vs a central difference of step 1e-4 T


def planck_quad(T_k: float, lo_um: float, hi_um: float) -> float:
    """Band exitance by scipy.integrate.quad of Planck's spectral exitance in wavelength (W m^-2)."""

    def spectral(lam_m: float) -> float:
        x = C2_M_K / (lam_m * T_k)
        return 0.0 if x > 700.0 else C1_W_M2 / (lam_m**5 * math.expm1(x))

    val, _ = quad(spectral, lo_um * 1e-6, hi_um * 1e-6, epsabs=0.0, epsrel=1e-12, limit=400)
    return val


def fraction_below(lambda_T_um_k: float, terms: int = 200) -> float:
    """F(0 -> lambda T): fraction of black-body exitance below lambda T (series, Chang & Rhee 1984)."""
    x = C2_M_K / (lambda_T_um_k * 1e-6)
    n = np.arange(1, terms + 1)
    return float(15.0 / math.pi**4 * np.sum(np.exp(-n * x) / n * (x**3 + 3 * x**2 / n + 6 * x / n**2 + 6 / n**3)))


def sigma_from_constants() -> float:
    return math.pi**4 * C1_W_M2 / (15.0 * C2_M_K**4)


# ---------------------------------------------------------------------------- band integral


@settings(max_examples=60, deadline=None)
@given(
    T_k=st.floats(30.0, 3000.0),
    lo_um=st.floats(0.5, 20.0),
    width_um=st.floats(0.05, 50.0),
)
def test_band_exitance_matches_scipy_quad(T_k, lo_um, width_um):
    ref = planck_quad(T_k, lo_um, lo_um + width_um)
    got = float(planck.band_exitance(T_k, (lo_um, lo_um + width_um)))
    if ref < 1e-250:  # deep Wien tail: both essentially zero
        assert got < 1e-240
    else:
        assert got == pytest.approx(ref, rel=QUAD_RTOL)


@pytest.mark.parametrize("T_k", [243.15, 300.0, 323.15, 1000.0])
@pytest.mark.parametrize("band_um", [(7.5, 13.5), (8.0, 14.0), (3.0, 5.0)])
def test_band_exitance_matches_fractional_function_series(T_k, band_um):
    expected = sigma_from_constants() * T_k**4 * (fraction_below(band_um[1] * T_k) - fraction_below(band_um[0] * T_k))
    assert float(planck.band_exitance(T_k, band_um)) == pytest.approx(expected, rel=SERIES_RTOL)


@pytest.mark.parametrize(
    "lambda_T_um_k, table_fraction",
    [(2898.0, 0.250108), (5000.0, 0.633747), (8000.0, 0.856288)],  # Incropera Table 12.2
)
def test_fraction_of_black_body_emission_matches_table(lambda_T_um_k, table_fraction):
    T_k = 1000.0
    band = (1e-3, lambda_T_um_k / T_k)  # from (effectively) zero wavelength
    frac = float(planck.band_exitance(T_k, band)) / (sigma_from_constants() * T_k**4)
    assert frac == pytest.approx(table_fraction, abs=TABLE_ATOL)
    assert fraction_below(lambda_T_um_k) == pytest.approx(table_fraction, abs=TABLE_ATOL)


def test_whole_spectrum_is_stefan_boltzmann():
    T_k = np.array([200.0, 300.0, 1500.0])
    total = planck.band_exitance(T_k, (1e-3, 1e7))
    np.testing.assert_allclose(total, SIGMA_SB * T_k**4, rtol=SIGMA_RTOL)


def test_vue_pro_band_at_room_temperature():
    # 7.5-13.5 um holds ~37 % of a 300 K black body's 459 W m^-2 (series above), i.e. ~172 W m^-2
    M = float(planck.band_exitance(300.0))
    assert 165.0 < M < 180.0
    assert float(planck.band_radiance(300.0)) == pytest.approx(M / math.pi, rel=1e-15)


def test_band_exitance_is_vectorised_and_monotonic():
    T = np.linspace(200.0, 400.0, 41).reshape(41, 1) * np.ones((1, 3))
    M = planck.band_exitance(T)
    assert M.shape == (41, 3)
    assert np.all(np.diff(M[:, 0]) > 0.0)
    # a body of a few kelvin emits nothing at 10 um, without overflow warnings becoming errors
    assert float(planck.band_exitance(2.0)) == 0.0


@settings(max_examples=40, deadline=None)
@given(T_k=st.floats(150.0, 1000.0))
def test_derivative_matches_central_difference(T_k):
    h = 1e-4 * T_k
    fd = (float(planck.band_radiance(T_k + h)) - float(planck.band_radiance(T_k - h))) / (2 * h)
    # central difference error ~ (h/T)^2 x^2 / 6 relative (x = C2 / (lambda T) <= 13 here): < 3e-7
    assert float(planck.band_radiance_derivative(T_k)) == pytest.approx(fd, rel=DERIV_RTOL)


@pytest.mark.parametrize("bad_T", [0.0, -5.0, float("nan"), float("inf")])
def test_bad_temperature_rejected(bad_T):
    with pytest.raises(InputError, match="T_k"):
        planck.band_radiance(bad_T)


@pytest.mark.parametrize("bad_band", [(13.5, 7.5), (0.0, 10.0), (7.5,), "abc", (7.5, float("nan"))])
def test_bad_band_rejected(bad_band):
    with pytest.raises(InputError, match="band_um"):
        planck.band_radiance(300.0, bad_band)


# ---------------------------------------------------------------------------- grey map


@pytest.mark.parametrize("encoding, full_scale, dtype", [("mono8", 255, np.uint8), ("mono16", 65535, np.uint16)])
def test_grey_map_end_points(encoding, full_scale, dtype):
    s = IrSettings(encoding=encoding)
    L = planck.band_radiance(np.array([s.t_min_k, s.t_max_k, s.t_min_k - 20.0, s.t_max_k + 20.0]), s.band_um)
    g = planck.grey_from_radiance(L, s)
    assert g.dtype == dtype
    assert g.tolist() == [0, full_scale, 0, full_scale]  # end points, then clipped below and above
    gf = planck.grey_float_from_radiance(L[:2], s)
    np.testing.assert_allclose(gf, [0.0, full_scale], atol=1e-9 * full_scale)


def test_grey_map_is_linear_in_radiance_not_temperature():
    s = IrSettings(encoding="mono16")
    L_lo, L_hi = planck.band_radiance(np.array([s.t_min_k, s.t_max_k]), s.band_um)
    L_mid = 0.5 * (L_lo + L_hi)
    assert float(planck.grey_float_from_radiance(L_mid, s)) == pytest.approx(65535 / 2, abs=1e-6)
    # the mid-temperature is below the mid-radiance (Planck is convex here): grey < half scale
    T_mid = 0.5 * (s.t_min_k + s.t_max_k)
    assert float(planck.grey_float_from_radiance(planck.band_radiance(T_mid, s.band_um), s)) < 65535 / 2 - 1000
    assert planck.grey_from_radiance(L_mid, s).item() in (32767, 32768)


def test_grey_map_rejects_non_finite_radiance():
    with pytest.raises(InputError, match="radiance"):
        planck.grey_from_radiance(np.array([1.0, np.nan]), IrSettings())


def test_noise_sigma_in_grey_levels():
    s = IrSettings()
    L_lo, L_hi = planck.band_radiance(np.array([s.t_min_k, s.t_max_k]), s.band_um)
    expected = s.netd_k * float(planck.band_radiance_derivative(s.netd_reference_k)) * 255 / (L_hi - L_lo)
    assert planck.noise_sigma_grey(s) == pytest.approx(expected, rel=1e-12)
    # 40 mK over an 80 K span is ~0.15 grey in mono8 (slope at 30 C steeper than the mean slope)
    assert 0.12 < planck.noise_sigma_grey(s) < 0.2
    assert planck.noise_sigma_grey(replace(s, encoding="mono16")) == pytest.approx(expected * 257, rel=1e-12)
    assert planck.noise_sigma_grey(replace(s, netd_k=0.0)) == 0.0
