"""Error-map definitions checked against numbers worked out by hand from the paper's sentences.

Nothing here goes through scenario.py: each case states a physical stage motion, and the expected
numbers are computed on paper (comments) from Ferrucci et al. 2020:
- section 4.1: "a positive positioning error corresponds to the sample stage travelling less than
  its indexed displacement";
- section 3.3: positioning = difference between measured dz_R and the SRD reading change;
  straightness = residuals of straight-line fits;
- ISO 230-1: positioning along the axis' own travel; straightness perpendicular to it.
"""

import numpy as np
import pytest

from ct_calib_nodes.core.error_map import error_map

UM = 1e-6
ARCSEC = np.pi / 648000.0


def motions_from(dx, dy, dz, yaw=None):
    m = np.zeros((len(dz), 6))
    m[:, 0], m[:, 1], m[:, 2] = dx, dy, dz
    if yaw is not None:
        m[:, 4] = yaw
    return m


def test_stage_travelling_less_than_indexed_is_positive():
    # indexed 0, 20, 40 mm; the stage really moves 0, 19.990, 39.970 mm, straight along the normal.
    # travelled less by 10 and 30 um -> positioning +10, +30 um, in both definitions.
    srd = np.array([0.364, 0.384, 0.404])
    m = motions_from([0, 0, 0], [0, 0, 0], [0.0, 0.019990, 0.039970])
    for definition in ("travel", "detector"):
        em = error_map(srd, m, definition=definition)
        assert em.positioning_m == pytest.approx([0.0, 10 * UM, 30 * UM], abs=1e-12)
        assert em.straightness_x_m == pytest.approx([0, 0, 0], abs=1e-12)
        assert em.straightness_y_m == pytest.approx([0, 0, 0], abs=1e-12)


def test_travel_tilted_from_the_detector_normal():
    # The stage travels exactly its indexed 20 and 40 mm, along a direction 1 degree from the
    # detector normal in the X-Z plane: d = s (sin 1deg, 0, cos 1deg).
    # ISO: positioning 0 (it travelled what it was told), angle travel-normal = 1 deg.
    # Paper (detector frame): s - s cos(1 deg) = s * 1.5230484e-4 -> 3.0460969 um at 20 mm,
    # 6.0921937 um at 40 mm. dx = s sin(1 deg) is linear, so its straightness residual is 0.
    srd = np.array([0.364, 0.384, 0.404])
    s = np.array([0.0, 0.020, 0.040])
    m = motions_from(s * np.sin(np.radians(1.0)), 0 * s, s * np.cos(np.radians(1.0)))
    iso = error_map(srd, m, definition="travel")
    paper = error_map(srd, m, definition="detector")
    assert iso.positioning_m == pytest.approx([0, 0, 0], abs=1e-13)
    assert np.degrees(iso.angle_travel_normal_rad) == pytest.approx(1.0, abs=1e-9)
    assert paper.positioning_m == pytest.approx([0.0, 3.0460969 * UM, 6.0921937 * UM], abs=1e-12)
    assert paper.straightness_x_m == pytest.approx([0, 0, 0], abs=1e-12)
    assert iso.travel_direction_df == pytest.approx([np.sin(np.radians(1)), 0, np.cos(np.radians(1))], abs=1e-12)


def test_straightness_residual_of_a_line_fit():
    # Along the normal, readings 0, 10, 20 mm, dx = 0, +6, 0 um. Line fit of (0, 6, 0) against
    # (0, 1, 2): slope 0, intercept 2 -> residuals -2, +4, -2 um. The fitted travel is the normal,
    # so ISO gives the same. dy = 0, 0, -3 um: slope -1.5 um per step, intercept +0.5 ->
    # fitted 0.5, -1, -2.5 -> residuals -0.5, +1, -0.5 um.
    srd = np.array([0.5, 0.51, 0.52])
    m = motions_from(np.array([0, 6, 0]) * UM, np.array([0, 0, -3]) * UM, [0.0, 0.010, 0.020])
    for definition in ("travel", "detector"):
        em = error_map(srd, m, definition=definition)
        assert em.straightness_x_m == pytest.approx(np.array([-2, 4, -2]) * UM, abs=1e-6 * UM)
        assert em.straightness_y_m == pytest.approx(np.array([-0.5, 1, -0.5]) * UM, abs=1e-6 * UM)


def test_yaw_uncertainty_includes_the_rotary_index_repeatability():
    # With a rotary zero-index repeatability of 5 arcsec, yaw_k (k > 1) = gamma_Y + e_k - e_1:
    # u = 5 sqrt(2) arcsec, covariance between positions 2 and 3 = 25 arcsec^2 (e_1 shared).
    srd = np.array([0.364, 0.384, 0.404])
    m = motions_from([0, 0, 0], [0, 0, 0], [0.0, 0.02, 0.04], yaw=[0.0, 3 * ARCSEC, -2 * ARCSEC])
    cov = np.zeros((3, 6, 6))
    em = error_map(srd, m, cov, index_repeatability_rad=5 * ARCSEC)
    assert em.u_yaw_rad / ARCSEC == pytest.approx([0.0, 5 * np.sqrt(2), 5 * np.sqrt(2)], rel=1e-12)
    assert em.covariance[6 + 4, 12 + 4] / ARCSEC ** 2 == pytest.approx(25.0, rel=1e-12)
    assert any("includes a rotary indexing repeatability" in n for n in em.notes)
    unknown = error_map(srd, m, cov)
    assert unknown.u_yaw_rad == pytest.approx([0, 0, 0])
    assert any("rotary indexing repeatability is unknown" in n for n in unknown.notes)
    assert any("zero-index error" in n for n in unknown.notes)
