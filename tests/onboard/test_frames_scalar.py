"""The single-quaternion / single-point paths of onboard.core.frames agree with the vectorised ones
(and the one-point geodetic conversions with pymap3d), including their errors."""

import math

import numpy as np
import pymap3d
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.core import frames as F

finite = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False)
quats = st.tuples(finite, finite, finite, finite).filter(lambda q: math.sqrt(sum(c * c for c in q)) > 1e-6)


@settings(max_examples=300, deadline=None)
@given(quats, quats, st.floats(-0.5, 1.5))
def test_single_quaternion_paths_equal_the_vectorised_ones(q0, q1, alpha):
    a, b = np.array(q0), np.array(q1)
    np.testing.assert_allclose(F.quat_normalize(a), F.quat_normalize(a[None])[0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(F.quat_multiply(a, b), F.quat_multiply(a[None], b[None])[0], rtol=1e-14, atol=1e-13)
    ua, ub = F.quat_normalize(a), F.quat_normalize(b)
    np.testing.assert_allclose(F.rotmat_from_quat(ua), F.rotmat_from_quat(ua[None])[0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(F.check_unit_quat(ua, "q"), F.check_unit_quat(ua[None], "q")[0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(
        F.quat_slerp(ua, ub, alpha), F.quat_slerp(ua[None], ub[None], np.array([alpha]))[0], rtol=0, atol=1e-14
    )
    phi = np.array(q0[:3]) * 0.3
    np.testing.assert_allclose(F.quat_from_rotvec(phi), F.quat_from_rotvec(phi[None])[0], rtol=0, atol=1e-15)
    assert F.quat_normalize(a).shape == (4,) and F.rotmat_from_quat(ua).shape == (3, 3)


@pytest.mark.parametrize("q", [(0, 0, 0, 0), (math.nan, 0, 0, 1), (math.inf, 0, 0, 0), (1.01, 0, 0, 0)])
def test_single_quaternion_paths_refuse_what_the_vectorised_ones_refuse(q):
    messages = []
    for arg in (np.array(q, float), np.array([q], float)):
        if not all(math.isfinite(c) for c in q) or not any(q):
            with pytest.raises(F.FrameError, match="zero or not finite"):
                F.quat_normalize(arg)
        with pytest.raises(F.FrameError) as info:
            F.check_unit_quat(arg, "PoseSample.q")
        messages.append(str(info.value))
    assert messages[0] == messages[1]


@pytest.mark.parametrize(
    "q, norm",
    [((1.01, 0, 0, 0), "1.01"), ((0.99, 0, 0, 0), "0.99"), ((0, 0, 0, 0), "0"), ((0.5, 0, 0, 0), "0.5")],
)
def test_single_quaternion_norm_error_names_the_norm(q, norm):
    """The norm itself, below 1 as above it (it had printed |norm - 1| + 1: a zero quaternion read 'norm 2')."""
    for arg in (np.array(q, float), np.array([q, (1.0, 0, 0, 0)], float)):
        with pytest.raises(F.FrameError) as info:
            F.check_unit_quat(arg, "PoseSample.q")
        assert str(info.value) == f"PoseSample.q: quaternion norm {norm} is not 1 within 0.001"


@settings(max_examples=300, deadline=None)
@given(st.floats(-89.99, 89.99), st.floats(-180.0, 180.0), st.floats(-1000.0, 50_000.0))
def test_one_point_geodetic_conversions_equal_pymap3d(lat, lon, alt):
    ell = pymap3d.Ellipsoid.from_name("wgs84")
    e = F.ecef_from_geodetic(lat, lon, alt)
    np.testing.assert_allclose(e, pymap3d.geodetic2ecef(lat, lon, alt, ell=ell, deg=True), rtol=0, atol=1e-8)
    got = F.geodetic_from_ecef(e)
    want = pymap3d.ecef2geodetic(*e, ell=ell, deg=True)
    np.testing.assert_allclose([float(g) for g in got], want, rtol=0, atol=1e-8)
    assert all(np.ndim(g) == 0 for g in got)
    # and the vectorised path (pymap3d) for the same point
    many = F.geodetic_from_ecef(e[None])
    np.testing.assert_allclose([float(g[0]) for g in many], [float(g) for g in got], rtol=0, atol=1e-8)


def test_one_point_geodetic_near_the_polar_axis_falls_back_to_pymap3d():
    p = np.array([0.0, 0.0, 6_356_852.0])
    got = [float(g) for g in F.geodetic_from_ecef(p)]
    want = pymap3d.ecef2geodetic(*p, ell=pymap3d.Ellipsoid.from_name("wgs84"), deg=True)
    assert got == pytest.approx(list(want), abs=1e-9) and got[0] == pytest.approx(90.0)


ATOL_DEG = 1e-11  # ~1 um on the ground
ATOL_M = 1e-6  # 1 um


@settings(max_examples=300, deadline=None)
@given(
    st.floats(-89.9, 89.9),
    st.floats(-180.0, 180.0),
    st.floats(-500.0, 5_000.0),
    st.tuples(*[st.floats(-3e5, 3e5)] * 2, st.floats(-5e4, 1e4)),
)
def test_one_point_ned_to_geodetic_equals_the_vectorised_conversion(lat0, lon0, alt0, p_ned_m):
    origin = F.GeodeticOrigin(lat0, lon0, alt0)
    want = [float(v) for v in F.geodetic_from_ned(np.array(p_ned_m), origin)]
    got = F.geodetic_from_ned1(*p_ned_m, origin)
    assert all(type(v) is float for v in got)
    assert got[0] == pytest.approx(want[0], abs=ATOL_DEG) and got[1] == pytest.approx(want[1], abs=ATOL_DEG)
    assert got[2] == pytest.approx(want[2], abs=ATOL_M)


def test_one_point_ned_to_geodetic_over_the_pole_falls_back_to_pymap3d():
    origin = F.GeodeticOrigin(90.0, 0.0, 100.0)
    got = F.geodetic_from_ned1(0.0, 0.0, -50.0, origin)
    want = [float(v) for v in F.geodetic_from_ned(np.zeros(3) + [0.0, 0.0, -50.0], origin)]
    assert got == pytest.approx(want, abs=1e-9) and got[0] == pytest.approx(90.0) and got[2] == pytest.approx(150.0)
