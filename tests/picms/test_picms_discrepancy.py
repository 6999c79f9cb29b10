"""Pixel Probe discrepancy engine (issue 11): clean controls, a hidden effect, the offline command."""
import importlib.util
import json
import pathlib
from dataclasses import replace

import numpy as np
import pytest

from picms_nodes import discrepancy_cli
from picms_nodes.core import campaign, cell, pipeline
from picms_nodes.core import picms_discrepancy as pd
from picms_nodes.core.camera import Intrinsics

KEYS = {"verdict", "adequate", "noise_floor", "fit_before", "fit_after", "findings", "unexplained",
        "detection_limits", "catalogue"}


def test_catalogue_documented_and_complete():
    assert len(pd.CATALOGUE) >= 8 and len({t.id for t in pd.CATALOGUE}) == len(pd.CATALOGUE)
    # optics, the stage's linear axes, and the tracker are each covered by several terms
    assert sum(t.id.startswith(("lens_", "principal", "focal", "pixel", "sensor")) for t in pd.CATALOGUE) >= 5
    assert sum(t.id.startswith("stage_") for t in pd.CATALOGUE) >= 3
    assert sum(t.id.startswith(("tracker_", "smr_")) for t in pd.CATALOGUE) >= 4
    doc = (pathlib.Path(pd.__file__).parents[2] / "doc" / "picms_discrepancy.md")
    text = doc.read_text() if doc.exists() else ""
    for t in pd.CATALOGUE:
        assert len(t.params) == len(t.units)
        assert any(b is not None for b in (t.cam, t.trk, t.rot)), t.id
        assert f"`{t.id}`" in text, f"{t.id} not documented in {doc}"


def test_appendix_a_sessions_too_small_for_a_verdict(sessions):
    # 7 stations: 6 pose parameters per camera leave too few degrees of freedom for a data-driven
    # floor and held-out folds (on clean data the engine would see spurious 'time' structure)
    rec, _st, res, _ = sessions[0]
    with pytest.raises(ValueError, match="too few for a discrepancy verdict"):
        pd.run(res, rec.camera_info)
    out, state, text, settled = pd.judge(res, rec.camera_info, pd.motion_of(rec))
    assert out is None and state == "insufficient" and "too few" in text and not settled


def _bag_writer():
    p = pathlib.Path(__file__).with_name("test_picms_foreign_recording.py")
    spec = importlib.util.spec_from_file_location("_picms_foreign", p)
    m = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(m)
    return m._write


def test_offline_command_refuses_small_recording_and_bad_path(tmp_path, sessions, capsys):
    rec, *_ = sessions[0]
    bag = tmp_path / "bag"
    _bag_writer()(bag, rec)
    import yaml
    (tmp_path / "picms_cell.yaml").write_text(yaml.safe_dump({"stage": rec.cell["stage"], "tracker": rec.cell["tracker"]}))
    out = tmp_path / "disc"
    assert discrepancy_cli.main([str(bag), "--cell", str(tmp_path / "picms_cell.yaml"), "--out", str(out)]) == 1
    assert "too few for a discrepancy verdict" in capsys.readouterr().err
    assert not (out / "discrepancy.json").exists()
    assert discrepancy_cli.main([str(tmp_path / "missing"), "--out", str(out)]) == 2


def _grid_session(over=None, render=True):
    rng = np.random.default_rng(31)
    # a rigid stage: the simulator's default stage error motions are physics the calibration leaves out
    # (the engine names them as a stage axis scale error when they show): a clean control means only
    # modelled physics (picms_discrepancy.md, "Clean control")
    truth = cell.make_cell(rng, cell.make_physics(rng, distortion_k1=-0.3, stage_error_motions=False, **(over or {})))
    rec, _ = campaign.simulate_session(truth, rng, pattern=pd.grid_pattern(), dwell_s=1.2, mid_move_frames=0,
                                       render=render)
    return truth, rec


def test_lazy_session_renders_the_same_frames_as_they_are_read():
    # a long revealing session (16 frames per station) does not fit in memory: its frames are rendered as
    # the detector reads them; they must be the eager session's, bit for bit, and the tracker stream too
    def run(lazy):
        rng = np.random.default_rng(7)
        truth = cell.make_cell(rng, cell.make_physics(rng, distortion_k1=-0.3, stage_error_motions=False))
        rec, _ = campaign.simulate_session(truth, rng, pattern=pd.grid_pattern(n_xy=2, n_z=1)[:2], dwell_s=1.2,
                                           mid_move_frames=0, frames_per_station=2, lazy=lazy)
        return rec
    eager, lazy = run(False), run(True)
    assert isinstance(eager.frames, list) and not isinstance(lazy.frames, list)
    frames = list(lazy.frames)
    assert len(frames) == len(eager.frames) == 12 and list(lazy.frames) == []      # one pass
    for (s0, c0, i0), (s1, c1, i1) in zip(eager.frames, frames):
        assert s0 == s1 and c0 == c1 and np.array_equal(i0, i1)
    assert all(np.array_equal(a[2], b[2]) for a, b in zip(eager.tracker, lazy.tracker))


@pytest.fixture(scope="module")
def grid_session():
    # one cell rendered once on the grid acquisition (~15 s)
    return _grid_session()


@pytest.mark.slow
def test_grid_clean_adequate_and_command_output(tmp_path, grid_session):
    truth, rec = grid_session
    res, _ = pipeline.calibrate_recording(rec)
    out = pd.run(res, rec.camera_info)
    assert out["adequate"], out["verdict"]
    assert out["verdict"].startswith("No significant discrepancy")
    f = out["noise_floor"]["factor_of_stated_sigma"]
    assert 0.4 < f["u"] < 2.5 and 0.4 < f["v"] < 2.5
    assert out["detection_limits"]["principal_point_error"]["limit"] is None or \
        out["detection_limits"]["principal_point_error"]["limit"] > 0
    bag = tmp_path / "bag"
    _bag_writer()(bag, rec)
    import yaml
    (tmp_path / "picms_cell.yaml").write_text(yaml.safe_dump({"stage": rec.cell["stage"], "tracker": rec.cell["tracker"]}))
    dest = tmp_path / "disc"
    assert discrepancy_cli.main([str(bag), "--cell", str(tmp_path / "picms_cell.yaml"), "--out", str(dest)]) == 0
    d = json.loads((dest / "discrepancy.json").read_text())
    assert set(d) >= KEYS and d["adequate"]
    # the bag's streams reach the clock-lag analysis: no lag on the clean session, a limit below 2 ms
    assert d["timing_lag"]["seen"] and abs(d["timing_lag"]["lag_s"]) < 4 * d["timing_lag"]["u_lag_s"]
    assert 0 < d["detection_limits"]["tracker_timing_lag"]["limit"] < 2.0
    assert (dest / "report.md").read_text().splitlines()[0] == d["verdict"]
    assert (dest / "residuals.png").stat().st_size > 1000


@pytest.mark.slow
def test_hidden_lens_distortion_named_and_measured(grid_session, grid_clean):
    # the same rendering; CameraInfo with D = 0 hides a k1 ~ -0.3 lens
    truth, rec = grid_session
    rec = __import__("copy").copy(rec)
    rec.camera_info = {k: Intrinsics(v.K, np.zeros(5), v.width, v.height) for k, v in rec.camera_info.items()}
    res, _ = pipeline.calibrate_recording(rec)
    out = pd.run(res, rec.camera_info)
    assert not out["adequate"]
    f0 = out["findings"][0]
    assert f0["term"] == "lens_radial_k1"
    k1_true = np.array([c.true_intrinsics.D[0] for c in truth.cameras])
    est = np.array([p["value"] for p in f0["parameters"]])
    u = np.array([p["u"] for p in f0["parameters"]])
    # magnitude within 15 %; each camera's k1 within 4 u of the truth (with the floor's scale)
    assert abs(f0["magnitude"] - np.sqrt(np.mean(k1_true ** 2))) < 0.15 * np.sqrt(np.mean(k1_true ** 2))
    assert np.all(np.abs(est - k1_true) < 4 * u + 0.05 * np.abs(k1_true))
    # the k1 term moves the detector's fitted silhouette cone, so the held-out rms comes down to the clean
    # control's (same rendering, true CameraInfo). Over seeds 1000-1049 of the validation benchmark the
    # ratio was 1.083 +- 0.040 (0.98-1.18; <= 1.25, the bound, on 50 of 50) since the refit is
    # stated under the floor after the terms (round 31; 1.141 +- 0.072 before, 47 of 50; 4.47 before the
    # silhouette basis); the bound here is the mean + 3 sd of that seed-to-seed spread
    _res, _info, clean = grid_clean
    ratio = out["fit_after"]["held_out_rms"] / clean["fit_before"]["held_out_rms"]
    assert ratio <= 1.083 + 3 * 0.040, (ratio, out["fit_after"], clean["fit_before"])
    # its size's u is stated under that floor too: within 4 u of the truth, and no longer ~7x the scatter
    # (validation: z rms 0.78 over 50 seeds; 0.13 before)
    assert abs(f0["magnitude"] - np.sqrt(np.mean(k1_true ** 2))) < 4 * f0["magnitude_u"]
    assert f0["magnitude_u"] < 0.03 * f0["magnitude"], f0


def _silhouette_rays(rng):
    """A 12.7 mm sphere 170-190 mm from the camera near its axis, seen with a nest sector of 60-100 deg
    missing: (centre in the camera frame, angular radius, unit rays of the visible outline every 2 deg)."""
    pc = np.array([rng.uniform(-0.012, 0.012), rng.uniform(-0.012, 0.012), rng.uniform(0.17, 0.19)])
    a = pc / np.linalg.norm(pc)
    alpha = np.arcsin(0.00635 / np.linalg.norm(pc))
    e1 = np.cross(a, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    phi = np.deg2rad(np.arange(0.0, 360.0, 2.0))
    gap, half = rng.uniform(0, 2 * np.pi), np.deg2rad(rng.uniform(30, 50))
    phi = phi[np.abs((phi - gap + np.pi) % (2 * np.pi) - np.pi) > half]
    return pc, alpha, np.cos(alpha) * a + np.sin(alpha) * (np.outer(np.cos(phi), e1) + np.outer(np.sin(phi), e2))


def test_k1_basis_moves_the_fitted_silhouette_cone():
    # exact physics, no renderer: the silhouette of a 12.7 mm sphere 170-190 mm away, a nest sector of
    # 60-100 deg missing, every edge point bent by a lens k1 that CameraInfo (D = 0) leaves out, and the
    # detector's own cone fit. The k1 basis (shift of the cone fitted to the edge points) must predict the
    # fitted centre's shift: as a tangent (k1 -> 0) to its second-order remainder (~1 % of the shift), as
    # the secant at the lens's k1 exactly; the centre point's own shift k1 r^2 n, which ignores the disc's
    # size, is off by a third of the shift or more
    from picms_nodes.core.detect import fit_cone
    f, W, H = 8182.0, 2592, 1944
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    info = Intrinsics(K, np.zeros(5), W, H)
    rng = np.random.default_rng(7)
    worst_tangent, worst_secant, worst_old = 0.0, 0.0, np.inf
    for k1 in (-0.3, -0.1, 0.1, 0.3):
        for _ in range(4):
            pc, alpha, rays = _silhouette_rays(rng)
            x = rays[:, :2] / rays[:, 2:3]
            xo = x * (1 + k1 * (x * x).sum(1, keepdims=True))          # what the lens does
            ro = np.column_stack([xo, np.ones(len(xo))])
            ro /= np.linalg.norm(ro, axis=1, keepdims=True)
            n_true = pc[:2] / pc[2]
            p, _, _ = fit_cone(ro, [n_true[0], n_true[1], alpha])       # what the detector reports
            shift = (p[:2] - n_true) * f
            px = xo * f + K[:2, 2]
            tangent = f * pd._silhouette_shift(info, px, p[:2], 1e-4)
            secant = f * pd._silhouette_shift(info, px, p[:2], k1)
            old = f * n_true * (n_true @ n_true)
            nrm = np.linalg.norm(shift) + 0.01           # px; a disc near the image centre hardly moves
            worst_tangent = max(worst_tangent, np.linalg.norm(shift - k1 * tangent) / nrm)
            worst_secant = max(worst_secant, np.linalg.norm(shift - k1 * secant))
            worst_old = min(worst_old, np.linalg.norm(shift - k1 * old) / nrm)
    assert worst_tangent < 0.03, worst_tangent
    assert worst_secant < 1e-4, worst_secant          # px: the secant at the lens's k1 is the response
    assert worst_old > 0.2, worst_old


@pytest.mark.parametrize("kind", ["decentring", "aspect"])
def test_decentring_and_aspect_bases_move_the_fitted_silhouette_cone(kind):
    # as the k1 test above, for what CameraInfo gets wrong at the validated sizes: decentring (p1, p2 of
    # 8e-4) or the pixel aspect (fx off by 1e-3), with and without a lens k1 CameraInfo does carry. The basis
    # (the cone's shift per unit parameter, as for k1) must predict the detector's fitted centre; the
    # centre point's own shift misses the outline's stretch (by rho grad(T), or affine), which moves the
    # cone fitted to a partial outline. Measured: 0.05 % (decentring) and 0.12 % (aspect) of the shift at
    # worst with the cone's shift; with the centre point's, 12-81 % (median 45 %) and 3-90 % (median 20 %).
    # In the validation (50 seeds) the decentring rows' held-out rms went from 1.069 to 1.014 x the clean
    # control's (doc/picms_discrepancy.md)
    from picms_nodes.core.detect import fit_cone
    f, W, H = 8182.0, 2592, 1944
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    rng = np.random.default_rng(8)
    rel_cone, rel_point = [], []
    for k1 in (-0.3, 0.0):
        info = Intrinsics(K, np.array([k1, 0, 0, 0, 0.0]), W, H)
        for _ in range(8):
            a = rng.uniform(0, 2 * np.pi)
            theta = 8e-4 * np.array([np.cos(a), np.sin(a)]) if kind == "decentring" else np.array([1e-3])
            pc, alpha, rays = _silhouette_rays(rng)
            n_true = pc[:2] / pc[2]
            if kind == "decentring":                        # what the lens does; CameraInfo's p are 0
                xd = pd._distort_n(np.array([k1, 0, theta[0], theta[1], 0]), rays[:, :2] / rays[:, 2:3])
                px = xd * f + K[:2, 2]
            else:                                           # the true fx is (1 + theta) times CameraInfo's
                xd = pd._distort_n(info.D, rays[:, :2] / rays[:, 2:3])
                px = np.column_stack([xd[:, 0] * f * (1 + theta[0]), xd[:, 1] * f]) + K[:2, 2]
            ro = np.column_stack([info.undistort(px), np.ones(len(px))])
            ro /= np.linalg.norm(ro, axis=1, keepdims=True)
            p, _, _ = fit_cone(ro, [n_true[0], n_true[1], alpha])       # what the detector reports
            shift = (p[:2] - n_true) * f
            names = ["p1", "p2"] if kind == "decentring" else ["fx"]
            cone = f * pd._silhouette_shifts(info, px, p[:2], pd._steps(info, names))
            c = {"n": [n_true[None]], "f": [f], "edge": [None]}
            point = (pd._b_tangential(c, 0) if kind == "decentring" else pd._b_aspect(c, 0))[0]
            rel_cone.append(np.linalg.norm(shift - cone @ theta) / np.linalg.norm(shift))
            rel_point.append(np.linalg.norm(shift - point @ theta) / np.linalg.norm(shift))
    assert max(rel_cone) < 0.005, max(rel_cone)
    assert np.median(rel_point) > 0.1, np.median(rel_point)


@pytest.fixture(scope="module")
def grid_clean(grid_session):
    truth, rec = grid_session
    res, _ = pipeline.calibrate_recording(rec)
    return res, rec.camera_info, pd.run(res, rec.camera_info)


@pytest.mark.slow
def test_clean_tracker_terms_limits_and_blind_reasons(grid_clean):
    _res, _info, out = grid_clean
    lim = out["detection_limits"]
    # a realistic tracker scale error (a few ppm) is far below what a +-6 mm travel can show
    assert lim["tracker_length_scale"]["limit"] > 50.0
    assert lim["smr_centring"]["limit"] is None and "absorbed by X*" in lim["smr_centring"]["cannot_see"]
    assert lim["tracker_timing_lag"]["limit"] is None and "settled" in lim["tracker_timing_lag"]["cannot_see"]
    assert lim["principal_point_error"]["limit"] is None
    assert out["n_tracker_residuals"] > 0 and set(out["noise_floor"]["independent_sd"]) >= {"u", "v", "tracker_x"}
    assert not any(out["noise_floor"]["shared_per_projection_sd"].values())     # no station-shared part


@pytest.mark.slow
def test_hidden_pixel_aspect_named_and_measured(grid_session):
    truth, rec = grid_session
    rec = __import__("copy").copy(rec)
    e = np.array([1.1e-3, -0.9e-3, 1.0e-3])
    info = {}
    for j, (k, v) in enumerate(sorted(rec.camera_info.items())):
        K = v.K.copy()
        K[0, 0] *= 1 + e[j]
        info[k] = Intrinsics(K, v.D, v.width, v.height)
    rec.camera_info = info
    res, _ = pipeline.calibrate_recording(rec)
    out = pd.run(res, rec.camera_info)
    f0 = out["findings"][0]
    assert f0["term"] == "pixel_aspect_error", out["verdict"]
    true = np.sqrt(np.mean((1 / (1 + e) - 1) ** 2))
    assert abs(f0["magnitude"] - true) < 0.15 * true
    assert out["fit_after"]["held_out_rms"] < 0.3 * out["fit_before"]["held_out_rms"]


def _inject(res, stage_scale=None, tilt_urad=None, angular=None):
    """The calibration's design with a stage scale error, camera tilt drift or carriage rotation added to its
    observations (exact projection through the calibrated poses; the tracker link moves with the stage).
    angular: G (3, 3) rad per m, the carriage turning by w = G q about X* (no Abbe offset): the cameras ride
    on it and see the fixed SMR* turned by -w, the tracker sees the constellation turn by w."""
    import copy
    from picms_nodes.core.calibrate import travel_matrix
    from picms_nodes.core.camera import rotvec_to_matrix
    res = copy.deepcopy(res)
    d = res.design
    U, obs = np.asarray(d["U"]), np.asarray(d["obs"])
    A = travel_matrix(d["sq"])
    dq = -U @ np.linalg.inv(A).T
    t = (d["t_ns"] - d["t_ns"][0]) / np.ptp(d["t_ns"]) - 0.5
    for j, c in enumerate(d["cameras"]):
        R, C = res.cameras[c].R_stage_camera, res.cameras[c].p_stage_centre
        pc = (U - C) @ R
        n0 = pc[:, :2] / pc[:, 2:3]
        if stage_scale is not None:
            pc = (-(dq * (1 + stage_scale)) @ A.T - C) @ R
        elif angular is not None:
            pc = np.stack([(rotvec_to_matrix(angular @ dq[i]).T @ U[i] - C) @ R for i in range(len(U))])
        else:
            a = 1.3 + 2.1 * j
            w = (R[:, 0] * np.cos(a) + R[:, 1] * np.sin(a)) * tilt_urad * 1e-6
            pc = np.stack([(U[i] - C) @ (rotvec_to_matrix(w * t[i]) @ R) for i in range(len(U))])
        obs[j] += pc[:, :2] / pc[:, 2:3] - n0
    if stage_scale is not None:
        d["X_T"] = d["X_T"] + (dq * stage_scale) @ (res.R_tracker_stage @ A).T
    if angular is not None:                     # since the reference station (the first)
        d["W_T"] = d["W_T"] + (dq - dq[0]) @ (res.R_tracker_stage @ angular).T
    return res


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["stage_axis_scale", "camera_rotation_drift"])
def test_injected_stage_scale_and_tilt_drift_named_and_measured(grid_clean, kind):
    res, info, _ = grid_clean
    if kind == "stage_axis_scale":
        s = np.array([60e-6, -40e-6, -20e-6])              # traceless: the cameras see all of it
        out = pd.run(_inject(res, stage_scale=s), info)
        true = np.sqrt(np.mean(s ** 2)) * 1e6
    else:
        out = pd.run(_inject(res, tilt_urad=8.0), info)
        true = 8.0
    f0 = out["findings"][0]
    assert f0["term"] == kind, out["verdict"]
    assert abs(f0["magnitude"] - true) < 0.15 * true, (f0["magnitude"], true)
    assert out["fit_after"]["held_out_rms"] < out["fit_before"]["held_out_rms"]


@pytest.mark.slow
def test_carriage_rotation_named_from_both_its_tracker_and_camera_signatures(grid_clean, monkeypatch):
    # The carriage turning by w = G q (150 urad per 25 mm rms, about X*): the tracker sees the constellation
    # turn; the cameras, riding on the carriage, see the travel turned with it (w x A q, bilinear in q).
    res, info, clean = grid_clean
    G = np.random.default_rng(5).normal(0, 150e-6 / 0.025, (3, 3))
    true = np.sqrt(np.mean(G ** 2)) * 0.025e6
    ho_clean = clean["fit_before"]["held_out_rms"]
    out = pd.run(_inject(res, angular=G), info)
    assert [f["term"] for f in out["findings"]] == ["stage_angular"], out["verdict"]
    f0 = out["findings"][0]
    assert abs(f0["magnitude"] - true) < min(0.15 * true, 4 * f0["magnitude_u"]), (f0["magnitude"], true)
    assert out["fit_after"]["held_out_rms"] < 1.15 * ho_clean < out["fit_before"]["held_out_rms"]
    # without the camera block the cameras' part is left over and is taken for a principal-point error of
    # tens of px (a false name), and the held-out residual stays up
    cat = tuple(replace(t, cam=None) if t.id == "stage_angular" else t for t in pd.CATALOGUE)
    monkeypatch.setattr(pd, "CATALOGUE", cat)
    monkeypatch.setattr(pd, "CATALOGUE_BY_ID", {t.id: t for t in cat})
    out2 = pd.run(_inject(res, angular=G), info)
    assert "principal_point_error" in [f["term"] for f in out2["findings"]]
    assert out2["fit_after"]["held_out_rms"] > 1.5 * ho_clean



def test_floor_not_shrunk_by_structure_shared_across_a_stations_cameras():
    # Validation seed 1005: stage lead errors below their limit left a structure linear in the stage
    # position, alike in the three cameras' v; on the serpentine grid it alternates between neighbouring
    # stations, so it entered both the differences of one camera's consecutive residuals and those of the
    # stations' means. The MAD of a two-signed structure plus noise is not additive, so the shared-shift
    # estimate took nearly all of it and the independent floor fell to 0.37 of the stated sigma; a
    # focal-length error was then named at 14 sigma. Three cameras, no physical shared pixel shift: the
    # Pixel Probe adapter turns the shared part off, and the floor covers the noise.
    from ct_calib_nodes.core.discrepancy import Dataset, noise_floor
    rng = np.random.default_rng(5)
    n_st, n_cam = 33, 3
    st = np.repeat(np.arange(n_st), n_cam)
    cam = np.tile(np.arange(n_cam), n_st)
    structure = 0.5 * np.where(np.arange(n_st) % 2 == 0, 1.0, -1.0)        # +-0.5 sigma, station-alternating
    pairs = [(i, i + n_cam) for i in range(n_cam * (n_st - 1))]             # same camera, next station
    factors = {True: [], False: []}
    for _ in range(40):
        r = rng.normal(0.0, 1.0, n_st * n_cam) + structure[st]
        for shared in (True, False):
            ds = Dataset(residual=r, jac=np.zeros((r.size, 1)), nominal_names=("p",), sigma=np.ones(r.size),
                         component=np.zeros(r.size, int), group=st, neighbours=np.array(pairs),
                         fold=st * 5 // n_st, shared_shift=shared)
            factors[shared].append(noise_floor(ds).factor[0])
    low = {k: np.mean(np.array(v) < 0.8) for k, v in factors.items()}
    # measured: 40 % of the draws below 0.8 of the noise (min 0.25) with the shared part, none without
    # (min 1.03: the structure's own scatter stays in the floor, which is conservative)
    assert low[True] > 0.2 and low[False] == 0.0, low


def test_uncertainty_of_a_strong_term_stated_under_the_floor_after_it():
    # On the serpentine grid neighbouring stations are 4 mm apart, so a strong effect (a lens k1 moving the
    # discs by tens of px) enters the neighbour differences and inflates the floor; under that floor the
    # validation's k1 sizes had z rms 0.13 over 20 seeds (their u ~7x too large). The refit and the u are
    # therefore stated under the floor of the residuals after the terms (Dataset.refloor_after, the Pixel
    # Probe's setting); naming keeps the floor before. Synthetic: 33 stations x 3 cameras, unit noise, a
    # term quadratic in the station's x, 20 sigma at the grid's edge; z = (estimate - truth) / u over draws.
    from ct_calib_nodes.core.discrepancy import Candidate, Dataset, analyse
    rng = np.random.default_rng(11)
    pts = pd.grid_pattern()[1:]
    n_st, n_cam = len(pts), 3
    st = np.repeat(np.arange(n_st), n_cam)
    cam = np.tile(np.arange(n_cam), n_st)
    xq = (pts[:, 0] / np.abs(pts[:, 0]).max()) ** 2
    basis = (xq[st] * (1.0 + 0.3 * cam))[:, None]
    jac = np.eye(n_cam)[cam]                                   # one offset per camera (the nominal model)
    pairs = np.array([(i, i + n_cam) for i in range(n_cam * (n_st - 1))])
    z, floors = {True: [], False: []}, {True: [], False: []}
    for _ in range(150):
        a = 20.0 * rng.choice([-1.0, 1.0])
        r = rng.normal(0.0, 1.0, st.size) + a * basis[:, 0] + jac @ rng.normal(0, 5, n_cam)
        for refloor in (False, True):
            ds = Dataset(residual=r, jac=jac, nominal_names=("c0", "c1", "c2"), sigma=np.ones(r.size),
                         component=np.zeros(r.size, int), group=st, neighbours=pairs, fold=st * 5 // n_st,
                         shared_shift=False, refloor_after=refloor)
            cand = Candidate("quad", "quadratic term", "test", ("a",), ("1",), basis, "1", np.ones(1), "-")
            res = analyse(ds, [cand], max_terms=1)
            f = res["findings"][0]
            assert f["term"] == "quad"
            z[refloor].append((f["theta"][0] - a) / np.sqrt(f["theta_cov"][0, 0]))
            floors[refloor].append((res["floor_after"] or res["floor"]).factor[0])
    zr = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in z.items()}
    # 150 draws: the z rms of a correct u lies within 1 +- 0.15 (2.6 sd of its sampling spread). Measured:
    # 1.01 with the floor after the term (floor 1.02 of the noise), 0.06 without (floor 16.7)
    assert 0.85 < zr[True] < 1.15, zr
    assert zr[False] < 0.5, zr                                  # the effect's floor: u several times too large
    assert abs(np.median(floors[True]) - 1.0) < 0.1 and np.median(floors[False]) > 2.0, floors


def test_floor_after_the_terms_leaves_names_limits_and_unexplained_alone():
    # Dataset.refloor_after changes only the refit and its u: the names, the detection limits and the
    # structure left unexplained are decided under the floor before. Two components; a strong term mostly in
    # the first (it inflates that component's floor 20-30x, not the second's, so the two whitenings span
    # different model spaces); a sensor-field locate axis that overlaps the term and carries a real
    # structure in the second component. Testing that axis against the model whitened under the floor after
    # the term (a slip of the first version) leaked the term into it: delta BIC 41.5 instead of 14.0 at 30
    # sigma, a spurious 57.9 at 60 sigma.
    from ct_calib_nodes.core.discrepancy import Candidate, Dataset, analyse
    rng = np.random.default_rng(12)
    pts = pd.grid_pattern()[1:]
    n_st, n_cam = len(pts), 3
    st = np.repeat(np.arange(n_st), 2 * n_cam)
    cam = np.tile(np.repeat(np.arange(n_cam), 2), n_st)
    comp = np.tile([0, 1], n_st * n_cam)
    xs, ys = (pts[:, k] / np.abs(pts[:, k]).max() for k in (0, 1))
    basis = ((xs ** 2)[st] * np.where(comp == 0, 1.0, 0.2))[:, None]
    jac = np.eye(2 * n_cam)[2 * cam + comp]
    field = {"sensor field": np.column_stack([(xs ** 2)[st] * (comp == 0), (ys ** 2)[st] * (comp == 1)])}
    pairs = np.array([(i, i + 2 * n_cam) for i in range(2 * n_cam * (n_st - 1))])
    for amp in (30.0, 60.0):
        r = rng.normal(0.0, 1.0, st.size) * (1.0 + 1.5 * comp) + amp * basis[:, 0] + 4.0 * (ys ** 2)[st] * (comp == 1)
        out = {}
        for refloor in (False, True):
            ds = Dataset(residual=r, jac=jac, nominal_names=tuple(f"c{i}" for i in range(2 * n_cam)),
                         sigma=np.ones(r.size), component=comp, group=st, neighbours=pairs, fold=st * 5 // n_st,
                         empirical=field, shared_shift=False, refloor_after=refloor)
            cand = Candidate("quad", "quadratic term", "test", ("a",), ("1",), basis, "1", np.ones(1), "-")
            out[refloor] = analyse(ds, [cand], max_terms=1)
        a, b = out[False], out[True]
        assert a["chosen"] == b["chosen"] == ["quad"]
        assert b["floor_after"].factor[0] < 0.2 * b["floor"].factor[0]          # the whitenings differ
        assert [e["axis"] for e in a["unexplained"]] == [e["axis"] for e in b["unexplained"]]
        assert np.allclose([e["delta_bic"] for e in a["unexplained"]], [e["delta_bic"] for e in b["unexplained"]],
                           rtol=1e-9)
        assert np.isclose(a["limits"]["quad"]["limit"], b["limits"]["quad"]["limit"], rtol=1e-12)
        # the second component's structure is found at 30 sigma (under the 60 sigma term's floor it is not)
        assert [e["axis"] for e in a["unexplained"]] == (["sensor field"] if amp == 30.0 else [])


@pytest.mark.slow
def test_realistic_tracker_errors_reported_and_the_lag_measured_on_the_moves(grid_session, grid_clean):
    # the grid session again, with realistic tracker errors at once: a 5 ppm length scale, 2 ppm encoder
    # scales, an SMR* 8 um off-centre, and stamps 30 ms early (an unsynchronised clock). The frames, stage
    # and tracker noise are the clean session's (same generator stream). None of them can show at the
    # settled stations over the cell's 12 mm travel: there the engine must name nothing, state limits
    # above these magnitudes for the two visible-in-principle terms and say why the other two are blind.
    # The moves between stations show the lag (30 ms at up to 5 mm/s is up to 150 um against ~15 um of
    # reading noise): given the streams, the engine must name it and measure it, and nothing else
    truth, rec = grid_session
    over = dict(tracker_scale_ppm=5.0, tracker_encoder_ppm=(2.0, -2.0), smr_centring_m=(8e-6, -5e-6, 3e-6),
                tracker_lag_s=-0.030)
    truth2, rec2 = _grid_session(over, render=False)
    assert rec2.joint_positions.tobytes() == rec.joint_positions.tobytes()
    assert [r[0] for r in rec2.tracker] == [r[0] - 30_000_000 for r in rec.tracker]
    rec2.frames = rec.frames
    res, _ = pipeline.calibrate_recording(rec2)
    out = pd.run(res, rec2.camera_info)
    assert out["adequate"], out["verdict"]
    lim = out["detection_limits"]
    assert lim["tracker_length_scale"]["limit"] > 5.0 * 10
    assert lim["tracker_angular_encoder"]["limit"] > 2.0 * 10
    assert lim["smr_centring"]["limit"] is None and "absorbed" in lim["smr_centring"]["cannot_see"]
    assert lim["tracker_timing_lag"]["limit"] is None and "settled" in lim["tracker_timing_lag"]["cannot_see"]
    # as the catalogue says: the calibrated X* is where this tracker reads the SMR*'s optical centre
    from picms_nodes.core.instruments import tracker_errors
    ph = truth2.physics
    x_read = tracker_errors(truth.to_tracker(truth.smr_star_stage)[0] + np.asarray(ph.smr_centring_m),
                            ph.tracker_scale_ppm, ph.tracker_encoder_ppm)
    u = np.sqrt(np.diag(res.cov_p_tracker))
    assert np.all(np.abs(res.p_tracker - x_read) < 4 * u)
    assert np.linalg.norm(res.p_tracker - truth.to_tracker(truth.smr_star_stage)[0]) > 5e-6
    # with the moves (the live node's judgement): the lag named and measured, the other three below their
    # limits; inadequate, but the settled stations (the calibration's data) are not in doubt
    out, state, text, settled = pd.judge(res, rec2.camera_info, pd.motion_of(rec2))
    assert state == "inadequate" and not settled and text == out["verdict"]
    assert not out["adequate"] and [f["term"] for f in out["findings"]] == ["tracker_timing_lag"], out["verdict"]
    p = out["findings"][0]["parameters"][0]
    assert abs(p["value"] - (-0.030)) < 4 * p["u"] and p["u"] < 1e-3, p
    assert out["verdict"].startswith("The nominal model leaves out a clock offset") and "early" in out["verdict"]
    assert out["findings"][0]["held_out_rms_after_um"] < 0.5 * out["findings"][0]["held_out_rms_before_um"]
    # and on the clean session the moves show no lag: a limit below 2 ms instead
    res_clean, info, _ = grid_clean
    clean = pd.run(res_clean, info, motion=pd.motion_of(rec))
    assert clean["adequate"], clean["verdict"]
    assert 0 < clean["detection_limits"]["tracker_timing_lag"]["limit"] < 2.0
