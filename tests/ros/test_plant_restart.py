"""Calibration history in the live nodes: a restarted geometry solver re-publishes the latest valid
calibration of its cell latched; a solve that is not SUCCESS neither replaces it on the topic nor in
the history's latest valid entry; diagnostics say so."""
import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray

from metro_msgs.msg import CtGeometry, SolveStatus, SphereObservationArray
from metro_msgs.srv import TriggerSolve
from ct_calib_nodes.core.geometry import forward_srf
from ct_calib_nodes.core.scenario import default_static_truth
from ct_calib_nodes.io import ct_files
from ct_calib_nodes.io.history import History
from ct_calib_nodes.nodes.runner import QOS_LATCHED, QOS_RELIABLE_STREAM

from ct_obs_msg import observation_array  # noqa: E402

pytestmark = pytest.mark.ros


def _latched(ros_node, topic="/ct/geometry", timeout=30):
    got = []
    sub = ros_node.create_subscription(CtGeometry, topic, got.append, QOS_LATCHED)
    ros_node.spin_until(lambda: got, timeout=timeout)
    ros_node.destroy_subscription(sub)
    return got


def _call(ros_node, node, **kw):
    cli = ros_node.create_client(TriggerSolve, "/ct_geometry_solver/solve")
    assert ros_node.spin_until(cli.service_is_ready, timeout=30), node.log()
    fut = cli.call_async(TriggerSolve.Request(what="static", stage_position=-1, **kw))
    assert ros_node.spin_until(fut.done, timeout=90), node.log()
    ros_node.destroy_client(cli)
    return fut.result()


def _feed(ros_node, frames):
    pub = ros_node.create_publisher(SphereObservationArray, "/ct/observations", QOS_RELIABLE_STREAM)
    assert ros_node.spin_until(lambda: pub.get_subscription_count() > 0, timeout=30)
    for m in frames:
        pub.publish(m)
    ros_node.spin_until(lambda: False, timeout=1.5)
    ros_node.destroy_publisher(pub)


def test_restart_republishes_latest_valid_and_failures_never_replace_it(start_node, ros_node, tmp_path):
    instrument = ct_files.load_instrument(ct_files.default_instrument_path())
    ref = ct_files.load_reference_object(ct_files.default_reference_object_path())
    db = tmp_path / "cell.sqlite"
    args = ("--ros-args", "-p", "idle_solve_s:=0.0", "-p", f"history_db:={db}")
    truth = default_static_truth()
    alphas = 2 * np.pi * np.arange(24) / 24
    uv = forward_srf(truth, ref.centres_of_m, alphas, instrument.detector)
    rng = np.random.default_rng(11)

    # 1. a valid calibration, stored
    node = start_node("ct_calib_nodes", "ct_geometry_solver", *args, name="solver1")
    _feed(ros_node, [observation_array((200 + j) * 10**9, float(a), 0.364, ref.ids,
                                       uv[j] + rng.normal(0, 0.05, uv[j].shape))
                     for j, a in enumerate(alphas)])
    r = _call(ros_node, node)
    assert r.accepted and r.result.status.code == SolveStatus.SUCCESS, r.message
    g1 = _latched(ros_node)[-1]
    assert list(g1.static_estimate.values) == list(r.result.values)
    # the stamp is the end of the data (last frame: t = 223 s), and the service returns what the topic carries
    assert (g1.header.stamp.sec, r.result.header.stamp.sec) == (223, 223)
    rc = node.stop()
    assert rc == 0, node.log()[-3000:]

    # 2. restart: the late subscriber gets the same calibration with no new data
    node = start_node("ct_calib_nodes", "ct_geometry_solver", *args, name="solver2")
    got = _latched(ros_node)
    assert got, node.log()
    assert list(got[-1].static_estimate.values) == list(g1.static_estimate.values)
    assert got[-1].header.stamp == g1.header.stamp and got[-1].static_estimate.covariance == g1.static_estimate.covariance
    assert ros_node.spin_until(lambda: "re-published the latest valid calibration of cell /" in node.log(),
                               timeout=10), node.log()

    # 3. a campaign whose solve is not usable (sphere identities scrambled): not published, not latest valid
    bad = []
    for j, a in enumerate(alphas):
        perm = rng.permutation(len(ref.ids))
        bad.append(observation_array((300 + j) * 10**9, float(a), 0.364, ref.ids[perm], uv[j]))
    _feed(ros_node, bad)
    r = _call(ros_node, node)
    assert r.accepted and r.result.status.code != SolveStatus.SUCCESS, r.result.status.message
    got = _latched(ros_node)
    assert [list(m.static_estimate.values) for m in got] == [list(g1.static_estimate.values)]
    diags = []
    ros_node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    assert ros_node.spin_until(lambda: any(s.name == "/ct_geometry_solver" for d in diags for s in d.status),
                               timeout=10)
    st = [s for d in diags for s in d.status if s.name == "/ct_geometry_solver"][-1]
    assert st.level == b"\x01" and "previous valid calibration stays published" in st.message, st
    rc = node.stop()
    assert rc == 0, node.log()[-3000:]

    with History(db) as h:
        recs = h.list(cell="/", kind="ct_geometry", with_details=True)
        assert [r.status == "success" for r in recs] == [True, False]
        assert h.latest_valid("/", "ct_geometry").uid == recs[0].uid
        assert {i.role for i in recs[0].inputs} == {"instrument_yaml", "reference_object_yaml", "topic"}
        assert all(i.sha256 for i in recs[0].inputs if i.role.endswith("_yaml"))
        assert recs[0].data_start_ns == 200 * 10**9 and recs[0].data_end_ns == 223 * 10**9

    # 4. restart again: still the valid one
    node = start_node("ct_calib_nodes", "ct_geometry_solver", *args, name="solver3")
    got = _latched(ros_node)
    assert list(got[-1].static_estimate.values) == list(g1.static_estimate.values), node.log()


def test_interleaved_campaign_refused_not_merged(start_node, ros_node):
    """A second campaign at the same stage position (the frames of another cell on the same topics) is
    refused and counted; the solve uses the first campaign's frames only."""
    instrument = ct_files.load_instrument(ct_files.default_instrument_path())
    ref = ct_files.load_reference_object(ct_files.default_reference_object_path())
    node = start_node("ct_calib_nodes", "ct_geometry_solver", "--ros-args", "-p", "idle_solve_s:=0.0")
    alphas = 2 * np.pi * np.arange(12) / 12
    uv = forward_srf(default_static_truth(), ref.centres_of_m, alphas, instrument.detector)
    rng = np.random.default_rng(4)
    frames = [observation_array((100 + j) * 10**9, float(a), 0.364, ref.ids,
                                uv[j] + rng.normal(0, 0.05, uv[j].shape))
              for j, a in enumerate(alphas)]
    other = [observation_array((500 + j) * 10**9, float(a), 0.364, ref.ids, uv[j] + 3.0) for j, a in enumerate(alphas)]
    _feed(ros_node, frames + other)
    r = _call(ros_node, node)
    assert r.accepted and r.result.status.code == SolveStatus.SUCCESS, r.result.status.message
    assert r.result.status.observations == 2 * 12 * 49          # the first campaign only
    assert ros_node.spin_until(lambda: "refused observations #12" in node.log() or
                               node.log().count("refused observations") >= 5, timeout=10), node.log()[-2000:]
    assert "second frame at rotary angle" in node.log()
