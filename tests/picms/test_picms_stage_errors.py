"""Stage error motions of the simulated Pixel Probe cell (core/stage_errors.py)."""
import numpy as np
import pytest

from picms_nodes.core import cell
from picms_nodes.core.camera import project
from picms_nodes.core.stage_errors import StageErrorSpec, make_stage_errors


def test_on_by_default_and_rest_of_cell_unchanged():
    a = cell.cell_from_seed(3)
    b = cell.cell_from_seed(3, stage_error_motions=False)
    assert a.stage_errors is not None and b.stage_errors is None
    # the error draws use their own generator: the rest of the seeded cell is identical
    assert np.array_equal(a.A_travel, b.A_travel)
    assert np.array_equal(a.cameras[0].pose.R_stage_camera, b.cameras[0].pose.R_stage_camera)


def test_body_moves_rigidly_cameras_and_points_together():
    c = cell.cell_from_seed(5)
    b = np.array([0.003, -0.002, 0.001])
    q = np.array([0.02, -0.015, 0.01])
    for j, cam in enumerate(c.cameras):
        x0 = project(c.camera_pose_at(j, np.zeros(3)), cam.true_intrinsics, c.body_point_stage(b, np.zeros(3)))
        xq = project(c.camera_pose_at(j, q), cam.true_intrinsics, c.body_point_stage(b, q))
        assert np.allclose(x0, xq, atol=1e-9)


def test_magnitudes_match_the_spec():
    # over many draws, the deviation of X* from the rigid path A q at 25 mm on one axis has the rms
    # predicted by the spec: scale + bow (perpendicular) + Abbe (angular x offset)
    s = StageErrorSpec()
    q = np.array([s.ref_travel_m, 0.0, 0.0])
    A = np.eye(3)
    dev = np.array([make_stage_errors(k).point(A, np.zeros(3), q) - q for k in range(400)])
    rms = np.sqrt(np.mean(np.sum(dev ** 2, axis=1)))
    off = np.asarray(s.abbe_offset_m)
    # angular: 3 independent rotations of sd a: E|w x off|^2 = 2 a^2 |off|^2
    expect = np.sqrt((s.scale_ppm_sd * 1e-6 * s.ref_travel_m) ** 2 + 2 * s.straightness_m_sd ** 2
                     + 2 * s.angular_rad_sd ** 2 * off @ off)
    assert rms == pytest.approx(expect, rel=0.12)     # 400 draws of 3 components: ~4 % sd
    assert 1e-6 < expect < 5e-6                       # a few um over 25 mm: a precision stage


def test_explicit_scale_replaces_only_the_scale_draw():
    drawn = make_stage_errors(7, StageErrorSpec())
    fixed = make_stage_errors(7, StageErrorSpec(scale_ppm=(40.0, -10.0, 25.0)))
    assert np.allclose(fixed.scale, [40e-6, -10e-6, 25e-6], rtol=0, atol=1e-15)
    # the rest of the seeded draw (straightness, angular motions) is the same
    assert np.array_equal(fixed.straight, drawn.straight) and np.array_equal(fixed.G, drawn.G)
