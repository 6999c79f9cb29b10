"""ct_discrepancy_node on the live graph (issue 11): after the geometry solver's solve it judges the model,
publishes metro_msgs/DiscrepancyReport latched, stores it in the history as kind 'discrepancy', and the
geometry solver re-publishes an inadequate geometry with status POOR_FIT (what plant software reads).

Two cells in two namespaces, both told nothing: a clean campaign, and one whose detector creeps 0.12 px
(48 um) across the beam during the scan."""
import json

import numpy as np
import pytest


from metro_msgs.msg import CtGeometry, DiscrepancyReport, SolveStatus, SphereObservationArray
from ct_calib_nodes.core.geometry import forward_srf
from ct_calib_nodes.core.scenario import default_static_truth
from ct_calib_nodes.io import ct_files
from ct_calib_nodes.nodes.runner import QOS_LATCHED, QOS_RELIABLE_STREAM
from ct_obs_msg import observation_array

pytestmark = pytest.mark.ros

N_VIEWS, NOISE_PX, STATED_PX, DRIFT_PX = 36, 0.02, 0.05, 0.12


def test_discrepancy_node_judges_each_solve_and_marks_the_geometry(start_node, ros_node, tmp_path):
    from ct_calib_nodes.io.history import History

    instrument = ct_files.load_instrument(ct_files.default_instrument_path())
    ref = ct_files.load_reference_object(ct_files.default_reference_object_path())
    truth = default_static_truth()
    alphas = 2 * np.pi * np.arange(N_VIEWS) / N_VIEWS
    uv = forward_srf(truth, ref.centres_of_m, alphas, instrument.detector)
    db = tmp_path / "history.sqlite"
    cells = {"/clean": 0.0, "/drift": DRIFT_PX}
    nodes, reports, geoms, pubs = {}, {}, {}, {}
    for ns in cells:
        common = ["--ros-args", "-r", f"__ns:={ns}", "-p", f"history_db:={db}"]
        nodes[ns] = (start_node("ct_calib_nodes", "ct_geometry_solver", *common, "-p", "idle_solve_s:=1.0",
                                name=f"geom{ns[1:]}"),
                     start_node("ct_calib_nodes", "ct_discrepancy_node", *common, name=f"disc{ns[1:]}"))
        reports[ns], geoms[ns] = [], []
        ros_node.create_subscription(DiscrepancyReport, f"{ns}/ct/discrepancy", reports[ns].append, QOS_LATCHED)
        ros_node.create_subscription(CtGeometry, f"{ns}/ct/geometry", geoms[ns].append, QOS_LATCHED)
        pubs[ns] = ros_node.create_publisher(SphereObservationArray, f"{ns}/ct/observations", QOS_RELIABLE_STREAM)
    assert ros_node.spin_until(lambda: all(p.get_subscription_count() >= 2 for p in pubs.values()), timeout=60), \
        "\n".join(n.log() for pair in nodes.values() for n in pair)
    rng = np.random.default_rng(11)
    for ns, drift in cells.items():
        for j, a in enumerate(alphas):
            tau = j / (N_VIEWS - 1) - 0.5
            obs = uv[j] + rng.normal(0, NOISE_PX, uv[j].shape)
            obs[:, 0] += drift * tau                       # the panel creeps along its columns
            pubs[ns].publish(observation_array((300 + j) * 10**9, a, 0.364, ref.ids, obs, STATED_PX))

    def done():
        return all(reports[ns] for ns in cells) and any(g.static_estimate.status.code == SolveStatus.POOR_FIT
                                                        for g in geoms["/drift"])
    assert ros_node.spin_until(done, timeout=90), "\n".join(n.log() for pair in nodes.values() for n in pair)

    clean, drift = reports["/clean"][-1], reports["/drift"][-1]
    # clean: adequate, SUCCESS, the floor from the data (not the stated 0.05 px), limits stated
    assert clean.adequate and clean.status.code == SolveStatus.SUCCESS, clean.verdict
    assert not clean.findings and clean.verdict.startswith("No significant discrepancy")
    assert 0.7 * NOISE_PX < clean.noise_floor_u_px < 1.3 * NOISE_PX
    lim = dict(zip(clean.limit_terms, clean.limit_values))
    assert len(lim) >= 14 and np.isfinite(lim["detector_bow"]) and lim["detector_bow"] > 0
    assert clean.header.stamp == geoms["/clean"][-1].header.stamp
    assert geoms["/clean"][-1].static_estimate.status.code == SolveStatus.SUCCESS
    # drift: inadequate, the drift (or its stated degenerate group) named with a magnitude near the truth
    assert not drift.adequate and drift.status.code == SolveStatus.POOR_FIT, drift.verdict
    top = drift.findings[0]
    group = {top.term, *top.degenerate_with}
    assert "detector_drift" in group, (top.term, list(top.degenerate_with))
    if top.term == "detector_drift":
        true_um = DRIFT_PX * instrument.detector.pixel_pitch_m * 1e6
        assert abs(top.magnitude - true_um) < max(4 * top.u_magnitude, 0.15 * true_um), (top.magnitude, true_um)
    assert drift.held_out_rms_after_px < drift.held_out_rms_before_px
    body = json.loads(drift.report_json)
    assert body["verdict"] == drift.verdict and body["findings"][0]["term"] == top.term
    # the solver status plant software reads now says so
    g = geoms["/drift"][-1]
    assert g.static_estimate.status.code == SolveStatus.POOR_FIT and "inadequate" in g.static_estimate.status.message
    assert g.header.stamp == drift.header.stamp
    # history: one 'discrepancy' record per cell, the inadequate one as poor_fit
    for pair in nodes.values():
        for n in pair:
            assert n.proc.poll() is None, n.log()
    recs, geo = {}, []
    for _ in range(40):                 # the solver stores its superseding record after the verdict: a moment
        with History(db) as h:
            recs = {r.cell: r for r in h.list(kind="discrepancy", with_details=True)}
            geo = h.list(cell="/drift", kind="ct_geometry", newest_first=True, with_details=True)
        if len(recs) == 2 and geo and geo[0].status == "poor_fit":
            break
        ros_node.spin_until(lambda: False, timeout=0.25)
    assert recs["/clean"].status == "success" and recs["/drift"].status == "poor_fit"
    assert recs["/drift"].result["findings"][0]["term"] == top.term
    # the geometry's own history record carries the verdict: a superseding poor_fit record, original kept
    with History(db) as h:
        assert [r.status for r in geo[:2]] == ["poor_fit", "success"], [(r.id, r.status) for r in geo]
        assert geo[0].result["supersedes"]["uid"] == geo[1].uid and h.superseded(geo[1].uid)
        assert h.latest_valid("/drift", "ct_geometry") is None
        assert h.latest_valid("/clean", "ct_geometry") is not None
    # a restarted (killed) solver re-publishes POOR_FIT, not the original SUCCESS
    geom_drift = nodes["/drift"][0]
    geom_drift.proc.kill()                  # a crash, not a clean stop
    geom_drift.proc.wait(timeout=15)
    after = []
    ros_node.create_subscription(CtGeometry, "/drift/ct/geometry", after.append, QOS_LATCHED)
    geom2 = start_node("ct_calib_nodes", "ct_geometry_solver", "--ros-args", "-r", "__ns:=/drift",
                       "-p", f"history_db:={db}", "-p", "idle_solve_s:=1.0", name="geomdrift2")
    assert ros_node.spin_until(lambda: any(m.header.stamp == g.header.stamp for m in after), timeout=60), geom2.log()
    ros_node.spin_until(lambda: False, timeout=3.0)        # nothing turns it back to SUCCESS
    mine = [m for m in after if m.header.stamp == g.header.stamp]
    assert mine and all(m.static_estimate.status.code == SolveStatus.POOR_FIT for m in mine), \
        ([m.static_estimate.status.code for m in mine], geom2.log())
    assert geom2.proc.poll() is None, geom2.log()
