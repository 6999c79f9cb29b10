"""The simulated CT cell end to end over DDS (separate node processes), on a small campaign:
the error map must be recovered within the issue's tolerances and within its own uncertainty."""
import json
import pathlib
import subprocess

import numpy as np
import pytest

from ct_calib_nodes.io.mcap_io import ReadReport, iter_recording

pytestmark = pytest.mark.ros
ROOT = pathlib.Path(__file__).resolve().parents[2]

# Issue #5 tolerances (multi-projection mode): positioning 10 um, straightness 3 um, pitch and
# roll 3 arcsec, yaw 5 arcsec.
TOL = {"positioning_m": 10.0, "straightness_x_m": 3.0, "straightness_y_m": 3.0,
       "pitch_rad": 3.0, "roll_rad": 3.0, "yaw_rad": 5.0}


def test_ct_campaign_end_to_end(tmp_path):
    exe = ROOT / "ros_ws" / "install" / "ct_calib_nodes" / "lib" / "ct_calib_nodes" / "ct_demo"
    res = subprocess.run([str(exe), "--positions", "3", "--projections", "12", "--rate", "10",
                          "--out", str(tmp_path / "out"), "--bags", str(tmp_path / "bags"), "--timeout", "300"],
                         capture_output=True, text=True, timeout=400)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-4000:]
    run = next((tmp_path / "out").iterdir())
    rows = json.loads((run / "recovered_vs_truth.json").read_text())["error_map"]
    multi = {r["component"]: r for r in rows if r["mode"] == "multi"}
    for comp, tol in TOL.items():
        r = multi[comp]
        assert r["max_abs_error"] < tol, (comp, r)
        # and the error is explained by the reported uncertainty (k = 4.5 over 3 x 2 positions)
        assert r["max_abs_error"] < 4.5 * max(r["median_u"], 1e-3) + 0.05 * tol, (comp, r)
    assert (run / "report" / "index.html").is_file()
    assert (run / "geometry_export" / "geometry.json").is_file()
    # the recording holds every raw and result topic, readable by an independent reader
    bag = next((tmp_path / "bags").iterdir())
    rep = ReadReport()
    topics = {}
    for m in iter_recording(bag, report=rep):
        topics[m.topic] = topics.get(m.topic, 0) + 1
    assert rep.complete, rep.errors
    assert topics["/ct/detector/image"] == 36 and topics["/ct/stage/joint_states"] == 36
    assert topics["/ct/observations"] == 36
    assert topics.get("/ct/geometry", 0) >= 1 and topics.get("/ct/error_map", 0) >= 1
