"""Discrepancy engine (issue 11, CT): forward model, hidden physics truth, noise floor, naming, clean controls.

Feature-level recordings come from the renderer's exact truth (render.frame_truth with the hidden physics on,
no image) plus noise of a random size, a random per-projection shared shift and a misstated sigma
(campaign.truth_campaign); one image-level recording goes through rendering and detection. The engine is told
nothing. The full campaign (every effect over seeds, 50+ clean controls, rendered) is
tests/benchmarks/validate_ct_discrepancy.py.
"""

import numpy as np
import pytest

from campaign import DET, EFFECTS, analyse_campaign, analyse_truth_campaign, truth_campaign
from ct_calib_nodes.core import ct_discrepancy, render_effects as fx
from ct_calib_nodes.core.ct_model import StaticKernel
from ct_calib_nodes.core.discrepancy import Dataset, Floor, Whitener, noise_floor
from ct_calib_nodes.core.geometry import forward_df, project_df
from ct_calib_nodes.core.phantom import helix49
from ct_calib_nodes.core.render import RenderSettings, frame_truth
from ct_calib_nodes.core.static_solver import solve_static

#: effects that the recording cannot tell from another catalogue term: the engine must name the group
DEGENERATE = {"object_thermal_expansion": {"focal_spot_drift_axial", "stage_drift_axial"},
              "stage_drift": {"focal_spot_drift", "detector_drift"}}


def test_catalogue_is_documented_and_large_enough():
    assert len(ct_discrepancy.CATALOGUE) >= 10
    ids = [t.id for t in ct_discrepancy.CATALOGUE]
    assert len(set(ids)) == len(ids)
    for t in ct_discrepancy.CATALOGUE:
        assert t.name and t.mechanism and t.reveal_by and len(t.param_names) == len(t.param_units) == len(t.fd_step)


def test_forward_model_equals_the_solver_kernel():
    obs, tr = truth_campaign(3, "clean", n_views=24)
    st = solve_static(obs, tr["ref"].centres_of_m, DET, tr["srd"], tr["sdd"])
    f, _ = StaticKernel(obs, st.centres_of_m, DET).evaluate(st.x)
    q = obs.n_obs
    modelled = obs.uv_px + np.stack([f[:q], f[q:]], axis=1)
    zero = {t.id: np.zeros(len(t.param_names)) for t in ct_discrepancy.CATALOGUE}
    for thetas in (None, zero):
        p = ct_discrepancy.predict_px(st.x, obs, st.centres_of_m, DET, thetas)
        assert np.max(np.abs(p - modelled)) < 1e-9


def test_forward_model_with_a_stage_motion_equals_the_renderer():
    """predict_px(motion=...) (the joint-model study's forward model) against the renderer's exact ellipse centres at
    three stage positions with true error motions (campaign.truth_multi_campaign, noise 1e-9 px), and against
    geometry.forward_df (centre projections) without the minor axes."""
    import dataclasses

    from campaign import truth_multi_campaign

    pos, tr = truth_multi_campaign(5, n_positions=3, n_views=12, noise_px=1e-9)
    geom = ct_discrepancy.static_to_detector_frame(tr["w"], tr["ref"].centres_of_m)
    for (_srd, obs), m in zip(pos, tr["motions"]):
        p = ct_discrepancy.predict_px(tr["w"], obs, tr["ref"].centres_of_m, DET, motion=m)
        assert np.max(np.abs(p - obs.uv_px)) < 1e-7
        bare = dataclasses.replace(obs, minor_axis_px=None)
        p0 = ct_discrepancy.predict_px(tr["w"], bare, tr["ref"].centres_of_m, DET, motion=m)
        alphas = np.unique(obs.alpha_rad)
        uv = forward_df(geom, m, alphas, DET)[np.searchsorted(alphas, obs.alpha_rad), obs.sphere_index]
        assert np.max(np.abs(p0 - uv)) < 1e-9


def test_hidden_physics_truth_by_hand():
    ref = helix49()
    w = np.array([0.364, 1e-3, -1e-3, 1.05, 0.003, -0.004, 0.002, 2e-4, -3e-4, 0.3641, 0.002, 0.3, -0.001])
    base = frame_truth(w, np.zeros(6), 0.4, ref, DET, RenderSettings(ellipse_centre_bias=False), time_s=2.0)
    # stage drift: every centre projection moves by M d (M = D / (C_z - S_z)), d = rate * t
    rate = (3e-6, -2e-6, 0.0)
    moved = frame_truth(w, np.zeros(6), 0.4, ref, DET,
                        RenderSettings(ellipse_centre_bias=False, effects=(fx.StageDrift(rate),)), time_s=2.0)
    s, c = base.source_df_m, base.centres_df_m
    expect = project_df(s, c + 2.0 * np.asarray(rate), DET)
    assert np.max(np.abs(moved.centre_px - expect)) < 1e-9
    m = -s[2] / (c[:, 2] - s[2])
    assert np.allclose(moved.centre_px[:, 0] - base.centre_px[:, 0], m * 6e-6 / DET.pixel_pitch_m, rtol=1e-6)
    # detector bow: recorded = landing (D + h) / D, inverse to 1e-12 m; 0.72 mm sag at the corner -> ~0.5 px
    bow = fx.DetectorBow(sag_x_m=0.36e-3, sag_y_m=0.36e-3)
    xy = np.array([[0.2048, 0.2048], [0.05, -0.1], [0.0, 0.0]])
    src = np.array([0.0, 0.0, -1.05])
    rec = bow.recorded_from_landing(xy, src)
    assert np.max(np.abs(bow.landing_from_recorded(rec, src) - xy)) < 1e-12
    corner_shift_px = np.linalg.norm(rec[0] - xy[0]) / DET.pixel_pitch_m
    assert 0.45 < corner_shift_px < 0.55
    # encoder harmonic: true angle = alpha + A sin(2 alpha + phi)
    tr = frame_truth(w, np.zeros(6), 0.4, ref, DET, RenderSettings(effects=(fx.EncoderHarmonic(2, 1e-4, 0.3),)))
    assert abs(tr.alpha_true_rad - (0.4 + 1e-4 * np.sin(0.8 + 0.3))) < 1e-15


def test_noise_floor_ignores_smooth_structure():
    rng = np.random.default_rng(5)
    n_v, n_s = 360, 20
    view = np.repeat(np.arange(n_v), n_s)
    sph = np.tile(np.arange(n_s), n_v)
    q = view.size
    sigma_stated, factor, tau = 0.02, 1.4, 0.012
    smooth = 0.2 * np.sin(2 * np.pi * view / n_v + sph) + 0.1 * (view / n_v) ** 2      # >> the noise
    r = []
    for _ in range(2):
        r.append(smooth + rng.normal(0, factor * sigma_stated, q) + rng.normal(0, tau, n_v)[view])
    order = np.lexsort((view, sph))
    ok = (sph[order][1:] == sph[order][:-1])
    pairs = np.stack([order[:-1][ok], order[1:][ok]], 1)
    ds = Dataset(residual=np.concatenate(r), jac=np.zeros((2 * q, 0)), nominal_names=(),
                 sigma=np.full(2 * q, sigma_stated), component=np.repeat([0, 1], q),
                 group=np.concatenate([view, view]), neighbours=np.concatenate([pairs, pairs + q]),
                 fold=np.zeros(2 * q, int))
    fl = noise_floor(ds)
    # relative sd of a MAD scale over ~7000 pairs ~ 1.5 %; the smooth part (10x the noise) changes by < 0.004 px
    # between neighbouring views, adding < 1 % to the variance
    assert np.all(np.abs(fl.factor / factor - 1) < 0.08), fl.factor
    assert np.all(np.abs(fl.tau / tau - 1) < 0.35), fl.tau


@pytest.mark.parametrize("seed", range(6))
def test_clean_recordings_are_adequate(seed):
    out, tr, st = analyse_truth_campaign(9100 + seed, "clean")
    assert out["adequate"], (out["verdict"], out["findings"], out["unexplained"])
    assert out["verdict"].startswith("No significant discrepancy")
    lim = out["detection_limits"]["focal_spot_drift"]["limit"]
    assert lim is not None and 0 < lim < 30            # a 30 um drift would have been seen here


@pytest.mark.parametrize("effect", EFFECTS)
def test_concealed_effect_is_named_and_modelled(effect):
    out, tr, st = analyse_truth_campaign(4200 + EFFECTS.index(effect), effect)
    assert not out["adequate"], out["verdict"]
    top = out["findings"][0]
    names = {top["term"], *top["degenerate_with"]}
    assert tr["term"] in names, (effect, top["term"], top["degenerate_with"])
    if tr["term"] == top["term"]:
        # within 15 %, or within 3.5 of its own standard uncertainty when the effect is near the detection limit
        err = abs(top["magnitude"] - tr["magnitude"])
        assert err < max(0.15 * tr["magnitude"], 3.5 * top["magnitude_u"]), (top["magnitude"], top["magnitude_u"],
                                                                             tr["magnitude"])
    else:
        assert effect in DEGENERATE and set(top["degenerate_with"]) | {top["term"]} >= {effect}
        assert top["separate_by"]
    # the held-out residual falls, and ends near the noise floor
    nf = out["noise_floor"]["independent_sd"]
    floor = np.hypot(nf["u"], nf["v"]) / np.sqrt(2) * np.sqrt(1 + (out["noise_floor"]["shared_per_projection_sd"]["u"]
                                                                    / max(nf["u"], 1e-12)) ** 2)
    assert out["fit_after"]["held_out_rms"] < out["fit_before"]["held_out_rms"]
    assert out["fit_after"]["held_out_rms"] < 1.15 * floor, (out["fit_after"], floor)


@pytest.mark.parametrize("effect", sorted(DEGENERATE))
def test_reveal_acquisition_names_the_degenerate_groups_members(effect):
    # On the standard acquisition these are named only within their groups (stage / focal-spot / detector drift
    # across the beam; expansion / axial drifts). The `reveal` acquisition (magnification 4.4-5.8, the object
    # raised 20 mm off the principal ray, two turns) separates them: in validation 60-64 of 64 top-1 per effect
    # (ct_discrepancy.md). Six fresh seeds: at most one may still be reported within its group, none named wrong.
    top1, sizes = 0, []
    for seed in range(4300, 4306):
        out, tr, st = analyse_truth_campaign(seed, effect, acquisition="reveal")
        assert not out["adequate"], (seed, out["verdict"])
        top = out["findings"][0]
        assert tr["term"] in {top["term"], *top["degenerate_with"]}, (seed, top["term"], top["degenerate_with"])
        if top["term"] == tr["term"]:
            top1 += 1
            sizes.append((top["magnitude"], top["magnitude_u"], tr["magnitude"]))
    assert top1 >= 5, (effect, top1)
    for est, u, true in sizes:
        assert abs(est - true) < 0.15 * true, (effect, est, u, true)


def test_too_small_effect_is_not_given_a_false_name():
    # a 1.5 um focal-spot drift is below what 72 projections at this noise reveal: the limit says so
    out, tr, st = analyse_truth_campaign(77, "focal_spot_drift", scale=0.05)
    named = [f["term"] for f in out["findings"]]
    assert all(n == "focal_spot_drift" for n in named), named
    if not named:
        assert out["detection_limits"]["focal_spot_drift"]["limit"] > tr["magnitude"]


def test_no_time_stamps_means_drift_cannot_be_seen():
    obs, tr = truth_campaign(12, "clean", n_views=36)
    same = obs.__class__(obs.uv_px, obs.sphere_index, obs.alpha_rad, obs.view_index,
                         np.zeros(obs.n_obs, np.int64), obs.sigma_px, obs.minor_axis_px)
    st = solve_static(same, tr["ref"].centres_of_m, DET, tr["srd"], tr["sdd"])
    out = ct_discrepancy.run(same, st, DET)
    assert out["detection_limits"]["focal_spot_drift"]["limit"] is None
    assert "time stamps" in out["detection_limits"]["focal_spot_drift"]["cannot_see"]


def test_rendered_focal_spot_drift_is_found():
    out, tr = analyse_campaign(31, "focal_spot_drift", n_views=36)
    top = out["findings"][0]
    assert top["term"] == "focal_spot_drift", out["verdict"]
    assert abs(top["magnitude"] / tr["magnitude"] - 1) < 0.15, top["magnitude"]
    assert out["fit_after"]["held_out_rms"] < 0.5 * out["fit_before"]["held_out_rms"]


def test_whitener_inverts_the_floor_covariance():
    rng = np.random.default_rng(2)
    n_v, q = 5, 7
    view = np.repeat(np.arange(n_v), q)
    comp = np.repeat([0, 1], n_v * q)
    sigma = rng.uniform(0.5, 2.0, 2 * n_v * q)
    ds = Dataset(residual=np.zeros(2 * n_v * q), jac=np.zeros((2 * n_v * q, 0)), nominal_names=(), sigma=sigma,
                 component=comp, group=np.concatenate([view, view]), neighbours=np.zeros((0, 2), int),
                 fold=np.zeros(2 * n_v * q, int))
    fl = Floor(factor=np.array([1.3, 0.8]), tau=np.array([0.7, 0.4]), sigma_median=1.0, n_pairs=0)
    d = fl.factor[comp] * sigma
    same = (ds.group[:, None] == ds.group[None, :]) & (comp[:, None] == comp[None, :])
    cov = np.diag(d ** 2) + same * (fl.tau[comp][:, None] ** 2)
    w = Whitener(ds, fl)(np.eye(cov.shape[0]))
    assert np.allclose(w @ cov @ w.T, np.eye(cov.shape[0]), atol=1e-12)


def test_every_stage_position_is_judged_and_trends_are_fitted():
    """Three stage positions (different instruments/SRD per seed, feature level): a focal-spot drift growing from
    position to position (15, 30, 45 um over each scan) is named at each position with its size, and the trend
    against SRD is reported; a clean campaign at every position names nothing."""
    from ct_calib_nodes.core.ct_discrepancy import run_positions

    pos, pos_clean, mags = [], [], []
    for k, scale in enumerate((0.5, 1.0, 1.5)):
        obs, tr = truth_campaign(300 + k, "focal_spot_drift", scale, n_views=48)
        pos.append((tr["srd"], obs))
        mags.append(tr["magnitude"])
        obs_c, tr_c = truth_campaign(400 + k, "clean", 1.0, n_views=48)
        pos_clean.append((tr_c["srd"], obs_c))
    ref = helix49()
    out = run_positions(pos, ref.centres_of_m, DET, 1.04821)
    assert [r["position"] for r in out["positions"]] == [0, 1, 2]
    for r, true in zip(out["positions"], mags):
        f = r["findings"][0]
        assert "focal_spot_drift" in [f["term"], *f["degenerate_with"]], r["verdict"]
        if f["term"] == "focal_spot_drift":
            assert abs(f["magnitude"] - true) < max(4 * f["magnitude_u"], 0.15 * true), (f, true)
    clean = run_positions(pos_clean, ref.centres_of_m, DET, 1.04821)
    assert all(r["adequate"] for r in clean["positions"]) and clean["trends"] == []
    few = run_positions([(pos[0][0], pos[0][1].select(pos[0][1].view_index < 4))], ref.centres_of_m, DET, 1.04821)
    assert few["positions"] == [] and "fewer than 8" in few["not_judged"][0]["why"]


def test_campaign_long_focal_spot_drift_is_named_with_its_size():
    """Three stage positions on one instrument (campaign.truth_multi_campaign: true error motions, one hour between
    scans, 24 projections each): the focal spot drifting 400 um across the beam over the whole campaign (stated
    limit about 120 um) moves only ~1.3 um within a scan (a single position sees at most a um-sized drift of the
    drift group, never the campaign's 400 um); the campaign-long test on the positions' calibrated focal spot
    names it (with its stated group: a detector drift) and its size; the same campaign without the drift names
    nothing and states a detection limit. The false-alarm rate over 170 clean campaigns is in
    tests/benchmarks/validate_ct_campaign_drift.py (doc/ct_discrepancy.md)."""
    from ct_calib_nodes.core.ct_discrepancy import campaign_drift, run_positions

    from campaign import truth_multi_campaign

    for drift in (0.0, 400.0):
        pos, tr = truth_multi_campaign(21, n_positions=3, n_views=24, gap_s=3600.0, focal_drift_um=drift,
                                       noise_px=0.01)
        out = run_positions(pos, tr["ref"].centres_of_m, DET, tr["sdd"])
        camp = out["campaign"]
        assert camp["performed"] and camp["n_positions"] == 3, camp
        assert abs(camp["time_srd_correlation"]) > 0.95         # positions visited in SRD order: said in separate_by
        lim = camp["detection_limits"]["focal_spot_drift"]["limit"]
        assert 0 < lim < 400, lim
        if drift == 0:
            assert camp["adequate"] and not camp["findings"] and out["adequate"], camp
            continue
        f = camp["findings"][0]
        assert f["term"] == "focal_spot_drift" and f["degenerate_with"] == ["detector_drift"], camp["findings"]
        true = tr["focal_rate_m_per_s"][:2] * camp["span_s"] * 1e6
        est = np.array([p["value"] for p in f["parameters"]]) * 1e6
        u = np.array([p["u"] for p in f["parameters"]]) * 1e6
        assert np.all(np.abs(est - true) < 4 * u), (est, true, u)
        assert abs(f["per_scan_um"] - tr["per_scan_um"]) < 0.3 * tr["per_scan_um"]
        assert not camp["unexplained"] and not out["adequate"] and out["campaign"]["adequate"] is False
    # too few positions: said, not guessed
    few = campaign_drift(out["positions"][:2])
    assert not few["performed"] and "needs 3" in few["why"]


def _three_smooth_terms(seed, coef):
    """600 residuals of unit noise along a smooth axis; candidates Y, Z (orthogonal-ish smooth shapes) and
    X = Y + Z + 0.5 W (a third shape): the data carry coef[0] Y + coef[1] Z."""
    from ct_calib_nodes.core.discrepancy import Candidate
    rng = np.random.default_rng(seed)
    n = 600
    t = np.linspace(0, 1, n)
    y, z, w = np.sin(2 * np.pi * t), np.cos(3 * np.pi * t), np.cos(5 * np.pi * t)
    ds = Dataset(residual=coef[0] * y + coef[1] * z + rng.normal(0, 1, n), jac=np.ones((n, 1)),
                 nominal_names=("offset",), sigma=np.ones(n), component=np.zeros(n, int), group=np.arange(n),
                 neighbours=np.column_stack([np.arange(n - 1), np.arange(1, n)]), fold=(np.arange(n) * 5) // n,
                 shared_shift=False)
    cands = [Candidate(id=i, name=i, mechanism="", param_names=("a",), param_units=("1",), basis=b[:, None],
                       magnitude_unit="1", display_scale=np.ones(1), reveal_by="")
             for i, b in (("X", y + z + 0.5 * w), ("Y", y), ("Z", z))]
    return ds, cands


@pytest.mark.parametrize("seed", range(8))
def test_term_set_refinement_replaces_a_greedy_stand_in(seed):
    # Y and Z at 0.6 (each ~10 sd of its estimate): the forward selection takes X, which stands in for both,
    # and then neither passes alone; the best subset by joint BIC is {Y, Z}, each sized within 4 u
    from ct_calib_nodes.core.discrepancy import analyse
    ds, cands = _three_smooth_terms(seed, (0.6, 0.6))
    greedy = analyse(ds, cands, max_terms=2)
    assert "X" in [f["term"] for f in greedy["findings"]]
    out = analyse(ds, cands, max_terms=2, refine=True)
    assert sorted(f["term"] for f in out["findings"]) == ["Y", "Z"]
    for f in out["findings"]:
        u = float(np.sqrt(f["theta_cov"][0, 0]))
        assert 0.04 < u < 0.09 and abs(f["theta"][0] - 0.6) < 4 * u, (f["term"], f["theta"], u)
    # a single true term stays alone
    ds1, _ = _three_smooth_terms(seed, (0.6, 0.0))
    one = analyse(ds1, cands, max_terms=2, refine=True)
    assert [f["term"] for f in one["findings"]] == ["Y"]
