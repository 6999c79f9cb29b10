"""The integration guide's example subscriber (ros_ws/src/ct_calib_nodes/examples/plant_subscriber.py),
run in its own process against the live solver nodes of a namespaced cell: it receives the geometry and
the error map with the latched QoS, finds them valid, and prints them."""
import json
import pathlib
import subprocess
import sys
import time

import numpy as np
import pytest


from metro_msgs.msg import CtGeometry, ErrorMap, SphereObservationArray
from ct_calib_nodes.core.geometry import forward_df, static_to_detector_frame
from ct_calib_nodes.core.scenario import default_campaign
from ct_calib_nodes.io import ct_files
from ct_calib_nodes.nodes.runner import QOS_LATCHED, QOS_RELIABLE_STREAM
from ct_obs_msg import observation_array

pytestmark = pytest.mark.ros
EXAMPLE = pathlib.Path(__file__).resolve().parents[2] / "ros_ws/src/ct_calib_nodes/examples/plant_subscriber.py"


def test_example_subscriber_against_live_nodes(start_node, ros_node):
    inst = ct_files.load_instrument(ct_files.default_instrument_path())
    ref = ct_files.load_reference_object(ct_files.default_reference_object_path())
    ns = ["--ros-args", "-r", "__ns:=/cell_x"]
    geo = start_node("ct_calib_nodes", "ct_geometry_solver", *ns, "-p", "idle_solve_s:=1.0", name="geo")
    mot = start_node("ct_calib_nodes", "ct_error_motion", *ns, "-p", "idle_solve_s:=2.0", name="mot")
    truth = default_campaign(3, 0.072, 0.364, inst.sdd_reported_m)
    g = static_to_detector_frame(truth.static_w, ref.centres_of_m)
    alphas = 2 * np.pi * np.arange(18) / 18
    rng = np.random.default_rng(3)
    pub = ros_node.create_publisher(SphereObservationArray, "/cell_x/ct/observations", QOS_RELIABLE_STREAM)
    assert ros_node.spin_until(lambda: pub.get_subscription_count() >= 2, timeout=30), geo.log() + mot.log()
    t = time.time_ns()
    for k in range(3):
        uv = forward_df(g, truth.motions[k], alphas, inst.detector)
        for j, a in enumerate(alphas):
            pub.publish(observation_array(t, a, truth.srd_reported_m[k], ref.ids, uv[j] + rng.normal(0, 0.05, uv[j].shape)))
            t += 50_000_000
    maps = []
    ros_node.create_subscription(ErrorMap, "/cell_x/ct/error_map", maps.append, QOS_LATCHED)
    assert ros_node.spin_until(lambda: any(m.final for m in maps), timeout=120), \
        geo.log()[-2000:] + mot.log()[-2000:]
    # a Pixel Probe measurement result, latched as picms_measurement publishes it (a stand-in publisher:
    # running the cell here would cost ~80 s; the node's own publication is tested in
    # tests/ros/test_picms_measurement_node.py)
    from std_msgs.msg import String
    meas = {"part": "chrome_targets", "mode": "stage", "summary": {"n_points": 6, "n_ok": 6},
            "features": [{"id": "c7", "type": "circle", "size": 0.00700014, "u_size": 9e-8, "form_rms": 2.1e-7,
                          "n_points": 6}], "dot_grids": []}
    mpub = ros_node.create_publisher(String, "/cell_x/picms/measurement/result", QOS_LATCHED)
    mpub.publish(String(data=json.dumps(meas)))
    r = subprocess.run([sys.executable, str(EXAMPLE), "--timeout", "60", "--measurement", "--ros-args", "-r", "__ns:=/cell_x"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    out = r.stdout
    assert "calibration valid" in out and "z_R" in out and out.count("SRD ") == 3, out
    assert "6/6 points" in out and "c7" in out and "size 7.000140 mm  (u = 0.090 um)" in out, out
    final = [m for m in maps if m.final][-1]
    assert final.campaign_id.startswith("/cell_x@") and f"campaign {final.campaign_id}, final," in out, out
    assert all(not m.final for m in maps[:maps.index(final)])      # growing maps (if seen) are not final
    geos = []
    ros_node.create_subscription(CtGeometry, "/cell_x/ct/geometry", geos.append, QOS_LATCHED)
    assert ros_node.spin_until(lambda: geos, timeout=10)
    assert final.geometry_stamp == geos[-1].header.stamp and geos[-1].campaign_id == final.campaign_id
    # what it printed is the truth within the stated uncertainty (positioning at the last position)
    last = [ln for ln in out.splitlines() if ln.strip().startswith("SRD")][-1]
    pos_um, u_um = float(last.split("positioning")[1].split()[0]), float(last.split("+-")[1].split()[0])
    assert u_um > 0
    want = maps[-1].positioning_m[-1] * 1e6
    assert abs(pos_um - want) < 1e-3
