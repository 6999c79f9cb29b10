"""PiCMS part programs and measurements (core/part_program.py, fitting.py, features.py,
measure.py) against the simulator's truth.

- part programs: the shipped examples load; bad input names the key / feature.
- fits: synthetic points with known covariances over many seeds: size errors / stated u give
  z-scores of rms ~1; fixed angles round-trip; the grid spacing categories count as Fig. 16.
- locators on rendered frames (true camera geometry, so only the image analysis is tested):
  part finding with the rotation unknown; edge points (bright field) on the true edge within
  4 sigma of their stated covariance + 0.3 um; dot centres on the projected true centres.
- end to end on a cell calibrated from a simulated session (conftest `sessions`, shared with the
  targeting tests): a short part program measured on a SimCell; sizes vs truth within the
  stated uncertainty (4 sigma) and 3 um.
"""
import math

import numpy as np
import pytest

from picms_nodes.core import camera, cellio, features, fitting, measure, part_program, render, scenes, targeting
from picms_nodes.measure_sim import FullFirstFrame, config_file
from picms_nodes.io.files import calibration_dict
from picms_programs import chrome_targets_program


def test_shipped_programs_load_and_plan():
    t = part_program.load(config_file("part_program_targets.yaml"))
    pts = part_program.plan(t)
    kinds = {}
    for p in pts:
        kinds[p.feature_id] = kinds.get(p.feature_id, 0) + 1
    assert kinds == {"sq5": 16, "sq7": 16, "c5": 8, "c7": 8, "grid": 25}
    # bright field: chrome inside -> normals point to the centre
    for p in pts:
        if p.kind == "edge":
            f = t.feature(p.feature_id)
            assert p.normal_part @ (np.asarray(f.center) - p.xy_part) > 0
    fl = part_program.load(config_file("part_program_flange.yaml"))
    for p in part_program.plan(fl):
        f = fl.feature(p.feature_id)
        inward = p.normal_part @ (np.asarray(f.center) - p.xy_part) > 0
        assert inward == (p.feature_id == "outer"), p.feature_id


@pytest.mark.parametrize("text, words", [
    ("part: x\nplacement: {origin_at_stage: [0,0,0]}\nfeatures: [{id: a, type: square, center: [0, 0]}]", ["'a'", "side"]),
    ("part: x\nplacement: {origin_at_stage: [0,0,0]}\nfeatures: [{id: a, type: hexagon, center: [0, 0]}]", ["'a'", "type"]),
    ("part: x\nplacement: {origin_at_stage: [0,0]}\nfeatures: [{id: a, type: plane}]", ["origin_at_stage"]),
    ("part: x\nplacement: {origin_at_stage: [0,0,0]}\nfeatures: [{id: a, type: circle, center: [0,0], diameter: -1}]",
     ["'a'", "diameter"]),
    ("part: x\nplacement: {origin_at_stage: [0,0,0]}\nfeatures: [{id: a, type: circle, center: [0,0], diameter: 1, colour: 2}]",
     ["'a'", "colour"]),
    ("part: x\nplacement: {origin_at_stage: [0,0,0]}\nfeatures:\n - {id: a, type: circle, center: [0,0], diameter: 1}\n"
     " - {id: a, type: circle, center: [0,0], diameter: 1}", ["'a'", "duplicate"]),
    ("part: x\nlighting: uv\nplacement: {origin_at_stage: [0,0,0]}\nfeatures: [{id: a, type: plane}]", ["lighting"]),
    ("part: x\nplacement: {origin_at_stage: [0,0,0]}\nfeatures: [{id: g, type: dot_grid, center: [0,0], rows: 2, "
     "cols: 2, pitch: 0.1, dot_diameter: 0.2}]", ["'g'", "pitch"]),
    ("part: [unclosed\n", ["YAML"]),
])
def test_bad_programs_name_the_problem(text, words):
    with pytest.raises(part_program.PartProgramError) as e:
        part_program.load(text + "\n")
    for w in words:
        assert w in str(e.value), (w, str(e.value))


def test_fixed_angles_round_trip():
    rng = np.random.default_rng(1)
    for _ in range(20):
        a = rng.uniform([-3, -1.5, -3], [3, 1.5, 3])
        R = fitting.from_fixed_angles(a)
        assert np.allclose(fitting.fixed_angles(R), a, atol=1e-12)


def test_fits_unbiased_with_calibrated_uncertainty():
    """Square, rectangle, circle on a tilted plane with anisotropic point noise; 300 trials:
    the size z-scores have rms ~1 and the mean error is within 4 standard errors of 0."""
    rng = np.random.default_rng(7)
    R = fitting.from_fixed_angles([0.03, -0.02, 0.7])
    p = np.array([0.01, -0.02, 0.003])
    z = {"square": [], "rectangle": [], "circle": []}
    for _ in range(300):
        for typ in z:
            n = 16 if typ != "circle" else 8
            sd = rng.uniform(0.5e-6, 3e-6, n)
            if typ == "circle":
                a = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(0, 1)
                xy = np.column_stack([np.cos(a), np.sin(a)]) * 0.0025 + [0.001, 0.002]
                nrm = np.column_stack([np.cos(a), np.sin(a)])
                true = 0.005
            else:
                sx, sy = (0.005, 0.005) if typ == "square" else (0.004, 0.002)
                sides = np.repeat(np.arange(4), 4)
                t = np.tile(np.linspace(-0.35, 0.35, 4), 4)
                nrm = fitting._SIDE_N[sides]
                half = np.where(sides % 2 == 0, sx / 2, sy / 2)
                along = np.column_stack([-nrm[:, 1], nrm[:, 0]]) * np.where(sides % 2 == 0, sy, sx)[:, None] * t[:, None]
                xy = nrm * half[:, None] + along
                true = np.array([sx, sy])
            xy = xy + nrm * (sd * rng.standard_normal(n))[:, None]
            P = np.column_stack([xy, np.zeros(n)]) @ R.T + p
            # covariance: sd along the in-plane normal, 5x larger out of plane / along the edge
            N3 = np.column_stack([nrm, np.zeros(n)]) @ R.T
            covs = np.array([s * s * np.outer(v, v) + (5 * s) ** 2 * (np.eye(3) - np.outer(v, v)) for s, v in zip(sd, N3)])
            pl = fitting.fit_plane(P, up=R[:, 2], x_hint=R[:, 0])
            c2 = pl.cov_2d(covs)
            q = pl.to_2d(P)
            if typ == "circle":
                f = fitting.fit_circle(q, cov2d=c2)
                z[typ].append((f.size[0] - true) / f.u("diameter"))
            else:
                f = fitting.fit_rectangle(q, sides, cov2d=c2, square=typ == "square")
                z[typ].append((f.size[0] - true[0]) / f.u("sx"))
                z[typ].append((f.size[1] - true[1]) / f.u("sy"))
    for typ, v in z.items():
        v = np.array(v)
        assert 0.85 < np.sqrt(np.mean(v ** 2)) < 1.15, (typ, np.sqrt(np.mean(v ** 2)))
        assert abs(v.mean()) < 4 / np.sqrt(len(v)), (typ, v.mean())


def test_grid_spacing_categories():
    rc = np.array([(r, c) for r in range(5) for c in range(5)])
    xy = (rc[:, ::-1] - 2) * 0.0005
    sp = fitting.grid_spacings(xy, rc, 0.0005)
    assert [s["n"] for s in sp] == [40, 30, 20, 10]          # 100 in all, as the paper's Fig. 16
    assert all(abs(s["mean"] - s["nominal"]) < 1e-15 and s["sd"] < 1e-15 for s in sp)


class _TruthViews:
    """Views from the TRUE cell geometry (image analysis isolated from calibration)."""
    def __init__(self, truth, q):
        self.v = {c.name: features.View(c.name, truth.camera_pose_at(j, q), c.true_intrinsics)
                  for j, c in enumerate(truth.cameras)}


@pytest.fixture(scope="module")
def rendered_targets():
    from picms_nodes.core import cell
    rng = np.random.default_rng(31)
    truth = cell.make_cell(rng, cell.make_physics(rng))
    part = scenes.chrome_targets((2.5e-4, -1.5e-4, 1e-4), (0.025, -0.02), 2.2)
    imgs = {c.name: render.render_frame(truth.camera_pose_at(j, np.zeros(3)), c.true_intrinsics, truth.physics, rng,
                                        part=part) for j, c in enumerate(truth.cameras)}
    return truth, part, imgs


def test_find_part_with_unknown_rotation(rendered_targets):
    truth, part, imgs = rendered_targets
    prog = part_program.load(config_file("part_program_targets.yaml"))
    views = _TruthViews(truth, np.zeros(3)).v
    pp = features.find_part(imgs, views, prog, np.zeros(3))
    assert camera.rotation_angle_rad(pp.R_stage_part, part.R_stage_part) < 4e-3, pp.message
    assert np.linalg.norm(pp.p_stage_part - part.p_stage_part) < 30e-6, pp.p_stage_part - part.p_stage_part


def test_edge_points_and_dots_on_the_true_geometry(rendered_targets):
    truth, part, imgs = rendered_targets
    prog = part_program.load(config_file("part_program_targets.yaml"))
    views = _TruthViews(truth, np.zeros(3)).v
    # start from a deliberately imperfect pose (30 um, 3 mrad off): the point definition is the
    # plane PI, not the pose, so the located points must still lie on the true edges
    R = camera.rotvec_to_matrix([0.0, 0.0, 3e-3]) @ part.R_stage_part
    p = part.p_stage_part + [30e-6, -20e-6, 15e-6]
    tf = {f.id: f for f in part.features}
    n_edge = 0
    for pt in part_program.plan(prog)[::3]:
        spec = prog.feature(pt.feature_id)
        tgt = measure._target_for(pt, spec, R, p, prog.lighting)
        if pt.kind == "edge":
            ep = features.locate_edge_point(imgs, views, tgt)
            xp = part.R_stage_part.T @ (ep.X - part.p_stage_part)
            d = float(tf[pt.feature_id].sdf(xp[0], xp[1]))          # distance to the true edge
            n_in = R[:, :2] @ pt.normal_part
            sd = math.sqrt(n_in @ ep.cov @ n_in)
            assert abs(d) < 4 * sd + 0.3e-6, (pt.feature_id, pt.index, d, sd)
            assert abs(xp[2]) < 4 * math.sqrt(np.trace(ep.cov)) + 1e-6       # in the true plane
            n_edge += 1
        else:
            fix = features.locate_dot(imgs, views, tgt["centre"], tgt["diameter"])
            true = part.to_stage(tf["grid"].dots_part()[pt.index])
            for j, c in enumerate(truth.cameras):
                u = camera.project(truth.cameras[j].pose, c.true_intrinsics, true)[0]
                assert np.hypot(*(np.array(fix.pixels[c.name]) - u)) < 0.08, (pt.index, c.name)
    assert n_edge >= 12


def test_measure_short_program_end_to_end(sessions, tmp_path):
    """A calibrated cell (probe from the calibration only) measures a square (2 points per side),
    a circle (6 points) and the middle 3 x 3 dots; sizes within 4 sigma + 1 um and 3 um of the truth."""
    rec, st, res, _ = sessions[0]
    truth = st.truth
    probe = targeting.Probe.from_calibration_yaml(calibration_dict(res), rec.camera_info)
    text = chrome_targets_program(
        "{id: sq5, type: square, center: [-0.009, 0.008], side: 0.005, points_per_side: 2}",
        "{id: c7, type: circle, center: [0.009, -0.008], diameter: 0.007, points: 6}",
        "{id: grid, type: dot_grid, center: [0.0, 0.0], rows: 3, cols: 3, pitch: 0.0005, dot_diameter: 0.00025}",
        "{id: face, type: plane}")
    prog = part_program.load(text)
    rng = np.random.default_rng(5)
    part = scenes.chrome_targets((1.5e-4, 2e-4, -1e-4), (-0.02, 0.015), -1.0)
    cell = FullFirstFrame(cellio.SimCell(truth, rng, part), 90)
    seen = []
    run = measure.measure(cell, probe, prog, progress=seen.append)
    assert all(mp.ok for mp in run.points), [mp.reason for mp in run.points if not mp.ok]
    assert len([d for d in seen if d.get("event") == "point"]) == 8 + 6 + 9
    doc = measure.measurement_document(run, probe, mode="stage", calibration=calibration_dict(res))
    path = measure.write_json_atomic(doc, tmp_path / "measurement.json")
    assert path.is_file()
    f = {d["id"]: d for d in doc["features"]}
    e_sq = np.array(f["sq5"]["sides"]) - 0.005
    assert np.all(np.abs(e_sq) < 4 * np.array(f["sq5"]["u_sides"]) + 1e-6) and np.all(np.abs(e_sq) < 3e-6), e_sq
    e_c = f["c7"]["size"] - 0.007
    assert abs(e_c) < 4 * f["c7"]["u_size"] + 1e-6 and abs(e_c) < 3e-6, e_c
    sp = doc["dot_grids"][0]["spacings"]
    assert [s["n"] for s in sp] == [12, 6]          # the middle 3 x 3 dots of the plate's 5 x 5
    for s in sp:
        assert abs(s["mean"] - s["nominal"]) < 2e-6, s
    # the part pose: the plane normal against the true one
    assert camera.rotation_angle_rad(np.array(doc["R_frame_part"]), part.R_stage_part) < 2e-3
    # tracker mode fit of the same points exists and is coarser
    assert "features" in doc["other_mode"]
    # offline refit of the recorded points gives the same result
    from picms_nodes import measure_offline
    measure.write_crops(run, tmp_path / "measurement.crops.npz")
    assert measure_offline.main([str(path), "--out", str(tmp_path / "refit.json")]) == 0
    assert measure_offline.main([str(path), "--out", str(tmp_path / "reloc.json"), "--relocate"]) == 0
    import json
    re = {d["id"]: d for d in json.loads((tmp_path / "reloc.json").read_text())["features"]}
    assert abs(re["c7"]["size"] - f["c7"]["size"]) < 0.5e-6
    # both recomputes are in the calibration history (kind picms_measurement, source offline)
    import os

    from ct_calib_nodes.io.history import History
    recs = History(os.environ["METRO_HISTORY_DB"]).list(kind="picms_measurement", with_details=True)
    assert [(r.source, r.status) for r in recs] == [("offline", "success")] * 2
    q = {x.name: x for x in recs[1].quantities}
    assert q["size_c7"].value == pytest.approx(re["c7"]["size"]) and q["size_c7"].u == pytest.approx(re["c7"]["u_size"])
    assert q["side_x_sq5"].unit == "m" and "spacing_grid_1" in q and q["n_ok"].value == 23
    assert {i.role for i in recs[1].inputs} == {"measurement_json", "measurement_json_out"}


def test_dark_field_edges_with_the_band_width_given():
    """Flange face (bright bands on a dark face), true camera geometry: with the band width of
    the drawing fixed, hole, aperture and outer edges land on the true edge (the band's boundary
    away from the material) within 4 sigma + 0.5 um."""
    from picms_nodes.core import cell
    rng = np.random.default_rng(44)
    truth = cell.make_cell(rng, cell.make_physics(rng))
    part = scenes.flange_face((-1.5e-4, 1e-4, 5e-5), (-0.015, 0.02), 0.9)
    imgs = {c.name: render.render_frame(truth.camera_pose_at(j, np.zeros(3)), c.true_intrinsics, truth.physics, rng,
                                        part=part) for j, c in enumerate(truth.cameras)}
    prog = part_program.load(config_file("part_program_flange.yaml"))
    views = _TruthViews(truth, np.zeros(3)).v
    R, p = part.R_stage_part, part.p_stage_part + [20e-6, -10e-6, 10e-6]
    tf = {f.id: f for f in list(part.features) + [part.outer]}
    n = 0
    for pt in part_program.plan(prog)[::5]:
        spec = prog.feature(pt.feature_id)
        tgt = measure._target_for(pt, spec, R, p, prog.lighting, spec.band_m)
        ep = features.locate_edge_point(imgs, views, tgt)
        xp = part.R_stage_part.T @ (ep.X - part.p_stage_part)
        d = float(tf[pt.feature_id].sdf(xp[0], xp[1]))
        n_in = R[:, :2] @ pt.normal_part
        sd = math.sqrt(n_in @ ep.cov @ n_in)
        assert abs(d) < 4 * sd + 0.5e-6, (pt.feature_id, pt.index, d, sd)
        n += 1
    assert n >= 10
