"""Malformed messages on every subscribed topic of every CT node, over real DDS.

The detector, the geometry solver and the error-motion node run as processes; this test
publishes malformed images, stage readings, observations and geometries (wrong lengths and
encodings, NaN, negative and huge values, empty arrays, unknown joint names and sphere ids),
each several times, then a short good campaign. Every node must stay up, count each bad message
(the totals it logs on the way out equal what was sent), log each kind once plus summaries
(not one line per message), and still serve the good messages: the detector publishes
observations, the solver solves the static geometry from them, the error-motion node takes it.
"""

import copy
import math
import re

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from metro_msgs.msg import CtGeometry, SphereObservation, SphereObservationArray
from rclpy.duration import Duration
from sensor_msgs.msg import Image, JointState

from ct_calib_nodes.nodes.runner import QOS_LATCHED, QOS_RELIABLE_STREAM
from reliab_recordings import IMAGE, STAGE, ct_recording

pytestmark = pytest.mark.ros
REPEAT = 3


def _stamp(t):
    return Time(sec=t // 10**9, nanosec=t % 10**9)


def _bad_images(img):
    def m(**kw):
        x = copy.deepcopy(img)
        for k, v in kw.items():
            setattr(x, k, v)
        return x
    return {"encoding": m(encoding="bgr8"), "short_data": m(data=bytes(img.data)[:1000]),
            "rows_1e9": m(height=10**9), "zero_width": m(width=0), "small_step": m(step=10),
            "wrong_size": m(height=64, width=64, step=128, data=bytes(64 * 128)), "empty": m(data=b"", height=0)}


def _bad_stages(js):
    def m(name=None, position=None):
        x = copy.deepcopy(js)
        if name is not None:
            x.name = name
        if position is not None:
            x.position = position
        return x
    a, s = js.position
    return {"nan": m(position=[math.nan, s]), "inf": m(position=[a, math.inf]), "negative": m(position=[a, -0.3]),
            "huge": m(position=[a, 1e12]), "unknown_joints": m(name=["theta", "zoom"]),
            "empty": m(name=[], position=[]), "length_mismatch": m(position=[a])}


def _bad_observations(t):
    def arr(*obs, alpha=0.1, srd=0.364):
        msg = SphereObservationArray(rotary_angle_rad=alpha, srd_reported_m=srd, image_cols=128, image_rows=128)
        msg.header.stamp = _stamp(t)
        msg.observations = list(obs)
        return msg

    def ob(i=1, c=10.0, r=10.0):
        return SphereObservation(sphere_id=i, flag=0, col_px=c, row_px=r, sigma_px=0.05, semi_minor_px=3.0,
                                 semi_major_px=3.0)
    return {"nan_centre": arr(ob(c=math.nan)), "unknown_id": arr(ob(i=999)), "duplicate_id": arr(ob(1), ob(1)),
            "nan_angle": arr(ob(), alpha=math.nan), "negative_srd": arr(ob(), srd=-1.0),
            "inf_srd": arr(ob(), srd=math.inf)}


def _bad_geometries():
    def g(names, values):
        msg = CtGeometry()
        msg.static_estimate.model = "fuzz"
        msg.static_estimate.names = names
        msg.static_estimate.values = values
        return msg
    from ct_calib_nodes.core.geometry import STATIC_PARAM_NAMES
    names = list(STATIC_PARAM_NAMES)
    return {"wrong_names": g(["a"] * 13, [0.1] * 13), "short": g(names, [0.1] * 5), "nan": g(names, [math.nan] * 13),
            "empty": g([], [])}


def test_nodes_survive_malformed_messages(tmp_path, start_node, ros_node):
    good = []
    ct_recording(tmp_path / "cell", n_positions=1, n_proj=4, messages=good)
    files = ["-p", f"instrument_file:={tmp_path / 'cell' / 'ct_instrument.yaml'}",
             "-p", f"reference_object_file:={tmp_path / 'cell' / 'reference_object.yaml'}"]
    det = start_node("ct_calib_nodes", "ct_sphere_detector", "--ros-args", *files, "-p", "init_frames:=3")
    sol = start_node("ct_calib_nodes", "ct_geometry_solver", "--ros-args", *files, "-p", "idle_solve_s:=2.0")
    emo = start_node("ct_calib_nodes", "ct_error_motion", "--ros-args", *files)
    pub_i = ros_node.create_publisher(Image, IMAGE, QOS_RELIABLE_STREAM)
    pub_j = ros_node.create_publisher(JointState, STAGE, QOS_RELIABLE_STREAM)
    pub_o = ros_node.create_publisher(SphereObservationArray, "/ct/observations", QOS_RELIABLE_STREAM)
    pub_g = ros_node.create_publisher(CtGeometry, "/ct/geometry", QOS_LATCHED)
    geometries = []
    ros_node.create_subscription(CtGeometry, "/ct/geometry", geometries.append, QOS_LATCHED)
    assert ros_node.spin_until(lambda: pub_i.get_subscription_count() and pub_j.get_subscription_count()
                               and pub_o.get_subscription_count() >= 2 and pub_g.get_subscription_count() >= 1,
                               timeout=40), det.log() + sol.log() + emo.log()

    img0 = next(m for tp, _t, m, _lt in good if tp == IMAGE)
    js0 = next(m for tp, _t, m, _lt in good if tp == STAGE)
    t = 1_800_000_000_000_000_000
    sent = {"detector": 0, "observations": 0, "geometry": 0}
    for _ in range(REPEAT):
        for bad in _bad_images(img0).values():            # each paired with a good stage reading
            t += 1000
            bad.header.stamp, js = _stamp(t), copy.deepcopy(js0)
            js.header.stamp = _stamp(t)
            pub_i.publish(bad)
            pub_j.publish(js)
            sent["detector"] += 1
        for bad in _bad_stages(js0).values():             # each paired with a good image
            t += 1000
            bad.header.stamp, im = _stamp(t), copy.deepcopy(img0)
            im.header.stamp = _stamp(t)
            pub_j.publish(bad)
            pub_i.publish(im)
            sent["detector"] += 1
        for bad in _bad_observations(t).values():
            pub_o.publish(bad)
            sent["observations"] += 1
        for bad in _bad_geometries().values():         # latched, depth 1: one at a time
            pub_g.publish(bad)
            sent["geometry"] += 1
            # a keep-last-1 writer replaces a sample not yet acknowledged (one was lost this way in a
            # CI run): wait for the readers' acknowledgement, then give the node time to take it
            pub_g.wait_for_all_acked(Duration(seconds=5))
            ros_node.spin_until(lambda: False, timeout=0.3)
        ros_node.spin_until(lambda: False, timeout=0.3)
    ros_node.spin_until(lambda: False, timeout=1.5)
    for tp, _tn, msg, _lt in good:                       # then the good campaign (4 frames, 1 position)
        (pub_i if tp == IMAGE else pub_j).publish(msg)
    solved = ros_node.spin_until(lambda: any(g.static_estimate.model != "fuzz" for g in geometries), timeout=60)
    ros_node.spin_until(lambda: "static geometry received" in emo.log(), timeout=10)
    alive = {n: p.proc.poll() is None for n, p in (("detector", det), ("solver", sol), ("error_motion", emo))}
    assert all(alive.values()), (alive, det.log()[-3000:], sol.log()[-3000:], emo.log()[-3000:])
    for p in (det, sol, emo):
        assert p.stop() == 0, p.log()[-3000:]
    logs = {"detector": det.log(), "solver": sol.log(), "error_motion": emo.log()}
    assert solved, logs["solver"][-3000:]
    assert "static geometry received" in logs["error_motion"]
    for name, text in logs.items():
        assert "Traceback" not in text, (name, text[-3000:])

    def totals(text):
        m = re.findall(r"bad input totals: (\d+) message\(s\) skipped", text)
        return int(m[-1]) if m else None
    # every bad message counted; the solvers both saw the bad observations; the error-motion node the geometries
    assert totals(logs["detector"]) == sent["detector"], logs["detector"][-3000:]
    assert totals(logs["solver"]) == sent["observations"], logs["solver"][-3000:]
    assert totals(logs["error_motion"]) == sent["observations"] + sent["geometry"], logs["error_motion"][-3000:]
    # rate-limited: one line per kind (plus summaries), far fewer lines than bad messages
    for name, n_bad in (("detector", sent["detector"]), ("solver", sent["observations"]),
                        ("error_motion", sent["observations"] + sent["geometry"])):
        first = logs[name].count("bad input on ")
        assert 2 <= first <= n_bad // REPEAT, (name, first, n_bad)
    # the good frames were paired and detected after all that
    assert re.search(r"'published': [1-9]", logs["detector"]), logs["detector"][-2000:]
