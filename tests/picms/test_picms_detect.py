"""Disc centre x_j*: rendered frames (true perspective, true distortion) vs the projected sphere
centre, over seeds with varied physics and off-axis positions; bad images named."""
import numpy as np
import pytest

from picms_nodes.core import camera, cell, render
from picms_nodes.core.detect import DetectionError, detect_disc


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_centre_is_projected_sphere_centre(seed):
    rng = np.random.default_rng(seed)
    c = cell.make_cell(rng, cell.make_physics(rng))
    offsets = [np.zeros(3), np.array([0.006, -0.004, 0.003]), np.array([-0.007, 0.005, -0.004])]
    for j, cam in enumerate(c.cameras):
        s = c.smr_star_stage + offsets[j]
        truth = camera.project(cam.pose, cam.true_intrinsics, s)[0]
        img = render.render_frame(cam.pose, cam.true_intrinsics, c.physics, rng, sphere_stage=s)
        d = detect_disc(img, cam.info_intrinsics)
        u = np.sqrt(np.diag(d.cov_px))
        err = d.centre_px - truth
        # tolerance: 4 sigma of the stated uncertainty plus 0.005 px for the rendering's own
        # approximations (box-filtered anti-aliasing, bilinear profile sampling)
        assert np.all(np.abs(err) < 4 * u + 0.005), (err, u)
        assert 0.001 < u.max() < 0.05
        # the nest is found and excluded (a sector is left out), most of the rim is used
        assert 120 <= len(d.edges_px) <= 175
        if j > 0:
            # off axis, the silhouette-ellipse centre is NOT the sphere centre's image
            # (expected offset ~ 0.1-0.5 px here); the cone axis is
            assert np.linalg.norm(d.ellipse_centre_px - truth) > 5 * np.linalg.norm(err)


def test_no_disc_and_cut_disc_are_named():
    rng = np.random.default_rng(5)
    c = cell.make_cell(rng)
    cam = c.cameras[0]
    blank = render.render_frame(cam.pose, cam.true_intrinsics, c.physics, rng, sphere_stage=None)
    with pytest.raises(DetectionError, match="no disc"):
        detect_disc(blank, cam.info_intrinsics)
    # move the sphere so its image is cut by the left edge of the frame
    R = cam.pose.R_stage_camera
    far = c.smr_star_stage - R[:, 0] * 0.028
    cut = render.render_frame(cam.pose, cam.true_intrinsics, c.physics, rng, sphere_stage=far)
    with pytest.raises(DetectionError, match="cut by the image edge"):
        detect_disc(cut, cam.info_intrinsics)
    with pytest.raises(DetectionError, match="CameraInfo says"):
        detect_disc(blank[:, :-2], cam.info_intrinsics)


@pytest.mark.parametrize("seed", [11, 12])
def test_defocused_disc_next_to_the_nest_is_not_pulled_towards_it(seed):
    """At the ends of a wide stage travel the disc is 10 mm nearer or farther than focus (blur 3-4.5 px sd).
    Pass 1's circle takes in part of the nest post and sits ~3 px off towards it; an edge annulus centred
    there put one end of each profile on the blurred edge and pulled the centre 0.06-0.23 px towards the nest
    (measured on the validation cells). Noise as rendered; tolerance 4 sigma of the stated uncertainty plus
    0.015 px (the residual blur-curvature effect of a perspective outline, measured noise-free: <= 0.014 px)."""
    rng = np.random.default_rng(seed)
    c = cell.make_cell(rng, cell.make_physics(rng, stage_error_motions=False))
    corners = [np.array([sx * 0.008, sy * 0.008, sz * 0.005]) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
    cases = []
    for q in corners:
        for j, cam in enumerate(c.cameras):
            pose = c.camera_pose_at(j, q)
            depth = float(np.linalg.norm(pose.to_camera(c.smr_star_stage[None])[0]))
            blur = render.defocus_sigma_px(c.physics, depth, c.physics.working_distance_m)
            cases.append((blur, j, q))
    cases.sort(key=lambda x: -x[0])
    assert cases[0][0] > 3.0          # the worst corners are strongly defocused
    for blur, j, q in cases[:4]:
        cam = c.cameras[j]
        pose = c.camera_pose_at(j, q)
        truth = camera.project(pose, cam.true_intrinsics, c.smr_star_stage)[0]
        img = render.render_frame(pose, cam.true_intrinsics, c.physics, rng, sphere_stage=c.smr_star_stage,
                                  nest_axis_stage=c.nest_axis_stage)
        d = detect_disc(img, cam.info_intrinsics)
        u = np.sqrt(np.diag(d.cov_px))
        err = d.centre_px - truth
        assert np.all(np.abs(err) < 4 * u + 0.015), (blur, err, u)
