"""The simulated PiCMS cell end to end over DDS (separate node processes: stage, cameras,
tracker, MCAP recorder, calibration node driving the stage), then the offline calibration of
the recording. Both must recover the simulator's truth (rebuilt from the seed, never seen by
the solvers); the recording must hold every PiCMS topic."""
import json
import pathlib
import subprocess

import numpy as np
import pytest
import yaml

from ct_calib_nodes.io.mcap_io import ReadReport, iter_recording

pytestmark = [pytest.mark.ros, pytest.mark.slow]
ROOT = pathlib.Path(__file__).resolve().parents[2]
BIN = ROOT / "ros_ws" / "install" / "picms_nodes" / "lib" / "picms_nodes"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("picms_graph")
    res = subprocess.run([str(BIN / "picms_demo"), "--out", str(tmp / "out"), "--bags", str(tmp / "bags"),
                          "--dwell", "1.0", "--seed", "8", "--timeout", "300"],
                         capture_output=True, text=True, timeout=420)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-4000:]
    return json.loads(res.stdout), tmp


def test_live_and_offline_recover_truth(run):
    summary, tmp = run
    for key in ("live_vs_truth", "offline_vs_truth"):
        r = summary[key]
        # the stated uncertainties are ~1.3 um (X*) and ~3-5 um / ~3-5 arcsec (cameras), see
        # tests/picms; these bounds are ~5 sigma
        assert r["x_star_err_um"] < 7.0, (key, r)
        for cam, c in r["cameras"].items():
            assert c["rot_err_arcsec"] < 25.0 and c["centre_err_um"] < 25.0, (key, cam, c)
            assert c["reprojection_rms_px"] < 0.05
    d = yaml.safe_load(pathlib.Path(summary["calibration_file"]).read_text())
    assert set(d["probe_point"]["pixels"]) == {"camera_1", "camera_2", "camera_3"}


def test_recording_holds_every_topic(run):
    summary, _ = run
    rep = ReadReport()
    topics = {}
    disc = []
    for m in iter_recording(summary["recording"], report=rep):
        topics[m.topic] = topics.get(m.topic, 0) + 1
        if m.topic == "/picms/discrepancy":
            disc.append(m.msg)
    assert rep.complete, rep.errors
    want = {"/picms/stage/joint_states", "/picms/stage/command", "/picms/tracker/probe_pose", "/picms/calibration",
            "/picms/discrepancy"}
    want |= {f"/picms/camera_{k}/{t}" for k in (1, 2, 3) for t in ("image_raw", "camera_info")}
    want |= {f"/picms/tracker/smr/{n}" for n in ("smr_1", "smr_2", "smr_3", "smr_4", "smr_5", "smr_star")}
    assert want <= set(topics), want - set(topics)
    assert topics["/picms/stage/command"] == 8        # reference, +-x, +-y, +-z, back to the reference
    # the live calibration was judged: the Appendix-A session's 7 stations are too few for a verdict, and
    # the report says so (INSUFFICIENT_DATA) instead of passing or failing the model
    assert len(disc) == 1 and disc[0].status.code == 3 and "too few" in disc[0].status.message, disc
