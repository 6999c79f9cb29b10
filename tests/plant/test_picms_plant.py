"""The Pixel Probe cell as a plant citizen: the sample recording in bags/samples calibrates offline (the
result against the simulator's truth within the stated uncertainties), the calibration goes into the
history with its inputs hashed, a recording made under a namespace replays, the history CLI trends and
compares PiCMS calibrations, and the live calibration node re-publishes the latest valid calibration
latched at start (restart), never replaces it by a failed run, and reports on /diagnostics."""
import json
import pathlib
import shutil

import numpy as np
import pytest
import yaml

from ct_calib_nodes.io.history import History, content_hash, sha256_file
from picms_nodes import offline

ROOT = pathlib.Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "bags/samples/picms_appendix_a_window"
TRUTH = ROOT / "bags/samples/picms_appendix_a_window.truth.yaml"


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """The sample calibrated once by the command line (history in a module database)."""
    d = tmp_path_factory.mktemp("picms_sample")
    db, out = d / "history.sqlite", d / "picms_calibration.yaml"
    res, summary = offline.run(SAMPLE, None, out, log=lambda s: None, history=str(db))
    return res, summary, db, out


def test_sample_calibrates_against_truth_and_is_in_the_history(calibrated):
    res, summary, db, out = calibrated
    assert res is not None, summary
    assert summary["cell_file"] == str(SAMPLE / "picms_cell.yaml") and summary["namespace"] == "/"
    size = sum(f.stat().st_size for f in SAMPLE.rglob("*") if f.is_file())
    assert size < 8e6, size
    truth = yaml.safe_load(TRUTH.read_text())
    # x_j*: the image of X* in the recorded (windowed) sensor, error within 4 stated u per component
    for cam, px in truth["probe_point_pixels"].items():
        z = (np.asarray(res.pixels[cam]) - px) / np.asarray(res.u_pixels[cam])
        assert np.all(np.abs(z) < 4), (cam, z, res.pixels[cam], px)
    # camera centres within 4 stated u (the stage frame's origin is X*: p_stage_centre is relative to it)
    for cam, c in truth["cameras"].items():
        z = (res.cameras[cam].p_stage_centre - np.asarray(c["p_stage_centre"])) / res.cameras[cam].u_p_stage_centre
        assert np.all(np.abs(z) < 4), (cam, z)
    # X* in the tracker frame: Mahalanobis distance with the stated covariance (3 dof; 99.9 %: 16.3)
    e = res.p_tracker - np.asarray(truth["p_tracker_x_star"])
    assert e @ np.linalg.solve(res.cov_p_tracker, e) < 16.3, e
    assert yaml.safe_load(out.read_text())["probe_point"]["pixels"]
    with History(db) as h:
        (rec,) = h.list(kind="picms_calibration", with_details=True)
    assert rec.status == "success" and rec.source == "offline" and rec.cell == "/"
    assert rec.id == summary["history"]["id"]
    inputs = {i.role: i for i in rec.inputs}
    assert inputs["recording"].sha256 == content_hash(SAMPLE)
    assert inputs["picms_cell_yaml"].sha256 == sha256_file(SAMPLE / "picms_cell.yaml")
    q = {x.name: x for x in rec.quantities}
    assert q["x_star_col_camera_1"].value == pytest.approx(res.pixels["camera_1"][0])
    assert q["p_tracker_x"].u == pytest.approx(np.sqrt(res.cov_p_tracker[0, 0]))
    assert rec.campaign_id.startswith("/@") and rec.data_end_ns > rec.data_start_ns
    assert rec.result["ros_msg"]["type"] == "metro_msgs/msg/PicmsCalibration"


def _renamed_copy(src: pathlib.Path, dst: pathlib.Path, namespace: str):
    """The sample's messages (exact bytes) under a namespace, as a recorder in that namespace writes them."""
    from mcap.reader import make_reader

    from ct_calib_nodes.io.mcap_io import Rosbag2McapWriter

    with Rosbag2McapWriter(dst, compression="zstd") as w:
        for f in sorted(src.glob("*.mcap")):
            with open(f, "rb") as fh:
                for schema, ch, m in make_reader(fh).iter_messages(log_time_order=False):
                    t = namespace + ch.topic
                    if t not in w._topics:
                        w.add_topic(t, schema.name)
                    w.write_raw(t, m.data, m.log_time)
    shutil.copy(src / "picms_cell.yaml", dst / "picms_cell.yaml")


def test_namespaced_recording_replays_and_history_cli_trends(calibrated, tmp_path, capsys):
    res, _summary, db, _out = calibrated
    bag = tmp_path / "cell_b_bag"
    _renamed_copy(SAMPLE, bag, "/cell_b")
    with pytest.raises(ValueError, match=r"no /cell_c/picms/stage/joint_states.*\['/cell_b'\]"):
        offline.run(bag, None, None, log=lambda s: None, namespace="/cell_c")
    # found by itself; the same data give the same calibration, stored under the cell /cell_b
    res_b, summary = offline.run(bag, None, tmp_path / "cal_b.yaml", log=lambda s: None, history=str(db))
    assert res_b is not None and summary["namespace"] == "/cell_b", summary
    for cam in res.pixels:
        assert np.allclose(res_b.pixels[cam], res.pixels[cam], atol=1e-9)
    with History(db) as h:
        ids = [r.id for r in h.list(kind="picms_calibration")]
        assert [r.cell for r in h.list(kind="picms_calibration")] == ["/", "/cell_b"]
    # a later calibration of /cell_b with X* moved by 10 u in the constellation frame (synthetic): flagged
    from dataclasses import replace as dc_replace

    from ct_calib_nodes.io.history import Quantity, SolveRecord
    with History(db) as h:
        last = h.get(ids[1])
        moved = [dc_replace(q) if q.name != "p_constellation_x" else Quantity(q.name, q.value + 10 * q.u, q.u, q.unit)
                 for q in last.quantities]
        h.record(SolveRecord(cell="/cell_b", kind="picms_calibration", status="success", result={}, source="offline",
                             quantities=moved))
    from ct_calib_nodes import history_cli
    capsys.readouterr()
    assert history_cli.main(["--db", str(db), "compare", str(ids[0]), str(ids[1])]) == 0
    out = capsys.readouterr().out
    assert "x_star_col_camera_1" in out and "0 of" in out            # identical data: nothing changed
    assert history_cli.main(["--db", str(db), "trend", "--cell", "/cell_b", "--kind", "picms_calibration",
                             "--plot", str(tmp_path / "plots")]) == 0
    out = capsys.readouterr().out
    assert "centre_x_camera_2" in out and "1 change(s)" in out, out
    assert [ln for ln in out.splitlines() if "CHANGED" in ln][0].split()[1] == "p_constellation_x", out
    assert (tmp_path / "plots" / "trend_picms_calibration.png").stat().st_size > 1000
    assert history_cli.main(["--db", str(db), "export", "--format", "json", "--kind", "picms_calibration",
                             "--out", str(tmp_path / "h.json")]) == 0
    d = json.loads((tmp_path / "h.json").read_text())
    assert len(d["solves"]) == 3 and all(s["kind"] == "picms_calibration" for s in d["solves"])


@pytest.mark.ros
def test_node_republishes_latest_valid_at_start_and_failures_never_replace_it(calibrated, start_node, ros_node):
    from diagnostic_msgs.msg import DiagnosticArray
    from metro_msgs.msg import PicmsCalibration, SolveStatus
    from metro_msgs.srv import RunPicmsCalibration

    from ct_calib_nodes.nodes.runner import QOS_LATCHED

    res, _summary, db, _out = calibrated
    args = ("--ros-args", "-p", f"history_db:={db}", "-p", "info_timeout_s:=2.0")

    def latched():
        got = []
        sub = ros_node.create_subscription(PicmsCalibration, "/picms/calibration", got.append, QOS_LATCHED)
        ros_node.spin_until(lambda: got, timeout=20)
        ros_node.destroy_subscription(sub)
        return got

    # 1. start: the latest valid calibration of the cell (the offline one) is on the topic at once
    cal = start_node("picms_nodes", "picms_calibration", *args, name="cal1")
    stage = start_node("picms_nodes", "picms_stage_sim", name="stage")
    got = latched()
    assert got, cal.log()
    m = got[-1]
    assert m.status.code == SolveStatus.SUCCESS
    assert np.allclose(m.pixels, [v for c in sorted(res.pixels) for v in res.pixels[c]], atol=1e-12)
    # 2. a run that fails (the stage runs, but no camera publishes CameraInfo): returned, not published
    from sensor_msgs.msg import JointState

    js = []
    js_sub = ros_node.create_subscription(JointState, "/picms/stage/joint_states", js.append, 10)
    assert ros_node.spin_until(lambda: js, timeout=20), stage.log()      # the stage is up and discovered
    ros_node.destroy_subscription(js_sub)
    cli = ros_node.create_client(RunPicmsCalibration, "/picms/run_calibration")
    assert ros_node.spin_until(cli.service_is_ready, timeout=20), cal.log()
    fut = cli.call_async(RunPicmsCalibration.Request(write_file=False))
    assert ros_node.spin_until(fut.done, timeout=30), cal.log()
    r = fut.result()
    assert not r.success and "CameraInfo missing" in r.message, r.message
    got = latched()
    assert [g.status.code for g in got] == [SolveStatus.SUCCESS] and list(got[-1].pixels) == list(m.pixels)
    diags = []
    ros_node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)

    def status(name):
        st = [s for d in diags for s in d.status if s.name == name]
        return st[-1] if st else None

    def values(name):
        return {kv.key: kv.value for kv in status(name).values}
    # the node's count of stage readings is waited for (under load it can hear the stage seconds after this
    # test did), not assumed from the first report
    assert ros_node.spin_until(lambda: status("/picms_calibration") and status("/picms_stage_sim")
                               and int(values("/picms_calibration")["stage readings"]) > 0, timeout=20), cal.log()
    st = status("/picms_calibration")
    v = values("/picms_calibration")
    assert st.level == b"\x01" and "previous valid calibration stays published" in st.message, st
    assert int(v["stage readings"]) > 0 and v["cameras with CameraInfo"] == "0 of 3", v
    sv = values("/picms_stage_sim")
    assert status("/picms_stage_sim").level == b"\x00" and int(sv["stage readings published"]) > 0, sv
    assert cal.stop() == 0
    stage.stop()
    with History(db) as h:
        recs = h.list(cell="/", kind="picms_calibration")
        assert [(r.source, r.status) for r in recs] == [("offline", "success"), ("live", "failed")]
    # 3. restart: still the valid one
    cal = start_node("picms_nodes", "picms_calibration", *args, name="cal2")
    got = latched()
    assert got and list(got[-1].pixels) == list(m.pixels), cal.log()
    assert ros_node.spin_until(lambda: "re-published the latest valid Pixel Probe calibration of cell /" in cal.log(),
                               timeout=10), cal.log()


def test_stored_message_of_another_definition_is_not_decoded():
    """A message stored in the history under an older definition of its type (other fields) is not
    decoded with the current one (the node then waits for a new calibration instead of re-publishing
    garbage)."""
    from ct_calib_nodes.io.ct_history import ros_msg_blob, ros_msg_bytes

    blob = ros_msg_blob("metro_msgs/msg/ErrorMap", b"\x00\x01\x00\x00")
    assert blob["type_hash"].startswith("RIHS01_")
    assert ros_msg_bytes({"ros_msg": blob}, "metro_msgs/msg/ErrorMap") == b"\x00\x01\x00\x00"
    assert ros_msg_bytes({"ros_msg": dict(blob, type_hash="RIHS01_" + "0" * 64)}, "metro_msgs/msg/ErrorMap") is None
    assert ros_msg_bytes({"ros_msg": blob}, "metro_msgs/msg/CtGeometry") is None


def test_restart_message_skips_a_superseded_calibration(calibrated, tmp_path):
    """What the calibration node re-publishes at start (PicmsPlant -> HistoryHook.latest_msg) is the
    newest valid calibration that no later verdict withdrew: the same record as History.latest_valid."""
    import logging

    from builtin_interfaces.msg import Time
    from metro_msgs.msg import PicmsCalibration

    from ct_calib_nodes.nodes.plant import HistoryHook
    from picms_nodes.io.calibration_msg import calibration_msg
    from picms_nodes.io.picms_history import KIND, MSG_TYPE, calibration_record

    class Node:
        def get_namespace(self):
            return "/"

        def get_logger(self):
            return logging.getLogger("picms_test")

    hook = HistoryHook(Node(), str(tmp_path / "h.sqlite"))
    res = calibrated[0]
    recs = [hook.store(calibration_record(res, cell="/", source="live", joint_stamps_ns=[10**9 * s]),
                       calibration_msg(res, Time(sec=s), ""), MSG_TYPE) for s in (1, 2)]
    rec, msg = hook.latest_msg(KIND, PicmsCalibration, MSG_TYPE)
    assert rec.uid == recs[1].uid and msg.header.stamp.sec == 2
    hook.history.supersede(recs[1], "poor_fit", "withdrawn by a later verdict")
    rec, msg = hook.latest_msg(KIND, PicmsCalibration, MSG_TYPE)
    assert rec.uid == recs[0].uid == hook.history.latest_valid("/", KIND).uid and msg.header.stamp.sec == 1
    hook.close()
