"""CT nodes started as their console scripts (as `ros2 run` would): they answer, publish, and
survive bad messages (logged, counted, skipped)."""
import numpy as np
import pytest
from builtin_interfaces.msg import Time
from sensor_msgs.msg import Image, JointState

from metro_msgs.msg import CtGeometry, SolveStatus, SphereObservation, SphereObservationArray
from metro_msgs.srv import TriggerSolve
from ct_calib_nodes.core.render import RenderSettings, render_projection
from ct_calib_nodes.core.scenario import default_static_truth
from ct_calib_nodes.io import ct_files
from ct_calib_nodes.io.convert import image_from_array
from ct_calib_nodes.nodes.runner import QOS_LATCHED, QOS_RELIABLE_STREAM
from ct_obs_msg import observation_array

pytestmark = pytest.mark.ros


@pytest.fixture(scope="module")
def cell():
    return (ct_files.load_instrument(ct_files.default_instrument_path()),
            ct_files.load_reference_object(ct_files.default_reference_object_path()))


def _stage(sec, alpha=0.0, srd=0.364, names=("rotary", "magnification")):
    js = JointState(name=list(names), position=[alpha, srd])
    js.header.stamp = Time(sec=sec)
    return js


def test_sphere_detector_skips_bad_frames_and_keeps_running(start_node, ros_node, cell):
    instrument, ref = cell
    node = start_node("ct_calib_nodes", "ct_sphere_detector", "--ros-args", "-p", "init_frames:=1")
    got = []
    ros_node.create_subscription(SphereObservationArray, "/ct/observations", got.append, QOS_RELIABLE_STREAM)
    pub_i = ros_node.create_publisher(Image, "/ct/detector/image", QOS_RELIABLE_STREAM)
    pub_j = ros_node.create_publisher(JointState, "/ct/stage/joint_states", QOS_RELIABLE_STREAM)
    assert ros_node.spin_until(lambda: pub_i.get_subscription_count() and pub_j.get_subscription_count()
                               and ros_node.count_publishers("/ct/observations"), timeout=30), node.log()

    det = instrument.detector
    good = render_projection(default_static_truth(), np.zeros(6), 0.3, ref, det, RenderSettings(),
                             np.random.default_rng(3)).image
    bad = []
    m = image_from_array(good, Time(sec=1), "ct_detector")
    m.encoding = "rgb8"                                       # unsupported encoding
    bad.append((m, _stage(1)))
    bad.append((image_from_array(np.zeros((512, 512), np.uint16) + 40000, Time(sec=2), "ct_detector"),
                _stage(2)))                                   # size differs from ct_instrument.yaml
    nan = np.ones((det.rows, det.cols), np.float32)
    nan[10, 10] = np.nan
    bad.append((image_from_array(nan, Time(sec=3), "ct_detector"), _stage(3)))   # NaN in 32FC1
    bad.append((image_from_array(good, Time(sec=4), "ct_detector"),
                _stage(4, names=("x", "y"))))                 # wrong joint names
    bad.append((image_from_array(np.zeros((det.rows, det.cols), np.uint16), Time(sec=5), "ct_detector"),
                _stage(5)))                                   # all dark
    bad.append((image_from_array(good, Time(sec=7), "ct_detector"),
                _stage(7, srd=1.084)))                        # object beyond the detector (SRD > SDD)
    for img, js in bad:
        pub_j.publish(js)
        pub_i.publish(img)
    # The good frame comes last in stamp order too: the detector takes images to arrive in stamp
    # order, and an image stamped after a stage reading that has not been paired yet drops it as
    # overtaken (its image was lost). With the good frame stamped 6 after the bad one stamped 7,
    # the small stage reading 6 could overtake the 2 MB image 7 in DDS and then be dropped by it
    # (stop-18 CI, 1 run in many).
    pub_i.publish(image_from_array(good, Time(sec=8), "ct_detector"))
    pub_j.publish(_stage(8, alpha=0.3))
    assert ros_node.spin_until(lambda: got, timeout=60), node.log()
    ros_node.spin_until(lambda: False, timeout=1.0)
    assert [o.header.stamp.sec for o in got] == [8]           # only the good frame came out
    obs = got[0]
    ok = [o for o in obs.observations if o.flag == SphereObservation.ACCEPTED]
    assert len(ok) >= 40 and len({o.sphere_id for o in ok}) == len(ok)
    assert all(o.sphere_id in set(ref.ids.tolist()) for o in ok)
    assert obs.rotary_angle_rad == 0.3 and obs.srd_reported_m == 0.364
    assert node.proc.poll() is None                           # still running
    log = node.log()
    assert "unsupported image encoding 'rgb8'" in log
    assert "ct_instrument.yaml says 1024x1024" in log
    assert "lack 'rotary' and 'magnification'" in log
    assert "bad_stage_reading" in log and "1.084 m" in log
    assert log.count("skipped") >= 6


def test_geometry_solver_answers_publishes_and_skips_bad(start_node, ros_node, cell):
    from ct_calib_nodes.core.geometry import forward_srf

    instrument, ref = cell
    node = start_node("ct_calib_nodes", "ct_geometry_solver", "--ros-args", "-p", "idle_solve_s:=0.0")
    cli = ros_node.create_client(TriggerSolve, "/ct_geometry_solver/solve")
    assert ros_node.spin_until(lambda: cli.service_is_ready(), timeout=30), node.log()

    def call(**kw):
        # A service can be "ready" (request channel matched) before its response channel is: Fast DDS
        # then drops the first response under load. The requests here are idempotent, so re-send.
        for _attempt in range(4):
            fut = cli.call_async(TriggerSolve.Request(what="static", stage_position=-1, **kw))
            if ros_node.spin_until(fut.done, timeout=15):
                return fut.result()
            cli.remove_pending_request(fut)
        raise AssertionError("no response from the geometry solver's service in 4 x 15 s\n" + node.log())

    r = call()
    assert not r.accepted and "frame" in r.message             # nothing to solve yet: says so

    geoms = []
    ros_node.create_subscription(CtGeometry, "/ct/geometry", geoms.append, QOS_LATCHED)
    pub = ros_node.create_publisher(SphereObservationArray, "/ct/observations", QOS_RELIABLE_STREAM)
    assert ros_node.spin_until(lambda: pub.get_subscription_count() > 0, timeout=30)
    truth = default_static_truth()
    alphas = 2 * np.pi * np.arange(24) / 24
    uv = forward_srf(truth, ref.centres_of_m, alphas, instrument.detector)
    rng = np.random.default_rng(5)
    bad = observation_array(100 * 10**9, 0.0, 0.364, ref.ids, uv[0])
    bad.observations[3].col_px = float("nan")
    pub.publish(bad)                                                                 # bad: NaN centre
    pub.publish(observation_array(101 * 10**9, float("nan"), 0.364, ref.ids, uv[0]))          # bad: NaN angle
    for j, a in enumerate(alphas):
        noisy = uv[j] + rng.normal(0, 0.05, uv[j].shape)
        pub.publish(observation_array((200 + j) * 10**9, float(a), 0.364, ref.ids, noisy))
    ros_node.spin_until(lambda: False, timeout=1.5)
    r = call()
    assert r.accepted, r.message
    est = r.result
    assert est.status.code == SolveStatus.SUCCESS, est.status.message
    assert est.names[0] == "z_R" and est.units[0] == "m"
    cov = np.reshape(est.covariance, (13, 13))
    err = np.asarray(est.values) - truth
    # 24 views x 49 spheres at 0.05 px: the errors are explained by the reported covariance
    assert np.all(np.abs(err) < 5 * np.sqrt(np.diag(cov))), (err, np.sqrt(np.diag(cov)))
    assert est.status.observations == 2 * 24 * 49
    assert ros_node.spin_until(lambda: geoms, timeout=20)
    assert np.allclose(geoms[-1].static_estimate.values, est.values)
    assert node.proc.poll() is None
    assert node.log().count("bad input on /ct/observations, skipped") == 2     # one line per kind (rate-limited)
