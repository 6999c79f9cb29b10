"""Two CT cells (different simulated instruments) under their own namespaces on one ROS domain, each
node in its own process: each solves its own geometry from its own frames (no cross-talk), both write
the same calibration history, and cell A's recorder records only its cell; the recording made under
the namespace replays offline to the same geometry."""
import json
import pathlib
import subprocess

import numpy as np
import pytest
import yaml

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from metro_msgs.msg import CtGeometry, SolveStatus
from ct_calib_nodes.io.history import History
from ct_calib_nodes.io.mcap_io import iter_recording
from ct_calib_nodes.io.namespaces import find_namespace, recording_topics
from ct_calib_nodes.io.truth_files import read_truth
from ct_calib_nodes.nodes.runner import QOS_LATCHED

pytestmark = pytest.mark.ros
N_PROJ = 12
CELLS = {  # different instruments: detector format, pixel pitch, source-detector distance, first SRD
    "cell_a": dict(cols=512, rows=512, pitch=0.0008, sdd=1.04821, srd=0.364, seed=1),
    "cell_b": dict(cols=400, rows=400, pitch=0.0010, sdd=1.20000, srd=0.400, seed=2),
}


def _instrument(path, c):
    path.write_text(yaml.safe_dump({"units": "SI", "source_to_detector": c["sdd"],
                                    "detector": {"cols": c["cols"], "rows": c["rows"], "pixel_pitch": c["pitch"],
                                                 "flat_field_counts": 50000}}))
    return path


def test_two_cells_one_domain_no_cross_talk(start_node, ros_node, tmp_path):
    db = tmp_path / "plant_history.sqlite"
    geoms = {name: [] for name in CELLS}
    diags = {}
    ros_node.create_subscription(DiagnosticArray, "/diagnostics",
                                 lambda m: diags.update({st.name: st for st in m.status}), 50)
    for name in CELLS:
        ros_node.create_subscription(CtGeometry, f"/{name}/ct/geometry", geoms[name].append, QOS_LATCHED)
    nodes = {}
    for name, c in CELLS.items():
        inst = _instrument(tmp_path / f"{name}_instrument.yaml", c)
        ns = ["--ros-args", "-r", f"__ns:=/{name}", "-p", f"instrument_file:={inst}"]
        nodes[name, "det"] = start_node("ct_calib_nodes", "ct_sphere_detector", *ns, name=f"{name}_det")
        nodes[name, "geo"] = start_node("ct_calib_nodes", "ct_geometry_solver", *ns, "-p", f"history_db:={db}",
                                        "-p", "idle_solve_s:=2.0", name=f"{name}_geo")
    rec = tmp_path / "cell_a_bag"
    nodes["rec"] = start_node("ct_calib_nodes", "mcap_recorder", "--ros-args", "-r", "__ns:=/cell_a",
                              "-p", f"output:={rec}", name="cell_a_rec")
    for name, c in CELLS.items():
        subs = "2" if name == "cell_a" else "1"       # cell A: detector + recorder
        nodes[name, "sim"] = start_node(
            "ct_calib_nodes", "ct_projection_sim", "--ros-args", "-r", f"__ns:=/{name}",
            "-p", f"instrument_file:={tmp_path / f'{name}_instrument.yaml'}", "-p", "n_positions:=1",
            "-p", f"projections_per_position:={N_PROJ}", "-p", "rate_hz:=0.0", "-p", f"srd_first_m:={c['srd']}",
            "-p", f"seed:={c['seed']}", "-p", f"wait_for_subscribers:={subs}",
            # stays up after its last frame, as a real driver would, so that its diagnostics are
            # seen even when it finishes before its first diagnostics period (it did under load)
            "-p", "exit_when_done:=false",
            "-p", f"truth_output:={tmp_path / f'{name}_truth.yaml'}", name=f"{name}_sim")
    ok = ros_node.spin_until(lambda: all(geoms.values()), timeout=240)
    assert ok, "\n".join(f"--- {k}\n{p.log()[-1500:]}" for k, p in nodes.items() if not isinstance(p, str))
    for name, c in CELLS.items():
        g = geoms[name][-1]
        est = g.static_estimate
        assert est.status.code == SolveStatus.SUCCESS, (name, est.status.message)
        assert (g.image_cols, g.image_rows, g.pixel_pitch_m, g.sdd_reported_m) == (c["cols"], c["rows"], c["pitch"],
                                                                                  c["sdd"])
        truth = read_truth(tmp_path / f"{name}_truth.yaml")
        u = np.sqrt(np.diag(np.reshape(est.covariance, (13, 13))))
        err = np.asarray(est.values[:13]) - truth.static_w
        assert np.all(np.abs(err) < 5 * u), (name, err / u)
        # at most every sphere of every frame of this cell (the solver's frame count is checked in the history)
        assert 0 < est.status.observations <= 2 * 49 * N_PROJ, name
        assert "skipped" not in nodes[name, "det"].log(), nodes[name, "det"].log()[-2000:]
    # diagnostics: every node of both cells reports on /diagnostics under its full name
    names = {f"/{c}/{n}" for c in CELLS for n in ("ct_sphere_detector", "ct_geometry_solver", "ct_projection_sim")}
    assert ros_node.spin_until(lambda: names <= set(diags) and all(
        diags[f"/{c}/ct_geometry_solver"].message == "calibration valid" for c in CELLS), timeout=20), \
        (f"missing: {sorted(names - set(diags))}; "
         + "; ".join(f"{k}: {v.message}" for k, v in diags.items() if k.endswith("ct_geometry_solver")))
    for c in CELLS:
        det = diags[f"/{c}/ct_sphere_detector"]
        assert det.level == DiagnosticStatus.OK and det.hardware_id == f"/{c}", (det.level, det.message)
        assert {kv.key: kv.value for kv in det.values}["frames"] == str(N_PROJ)
    za, zb = (geoms[n][-1].static_estimate.values[3] for n in CELLS)
    assert abs((zb - za) - (1.20 - 1.04821)) < 0.01          # each found its own detector distance
    nodes["rec"].stop()
    with History(db) as h:
        assert {r.cell for r in h.list(kind="ct_geometry")} == {"/cell_a", "/cell_b"}
        for name in CELLS:
            r = h.latest_valid(f"/{name}", "ct_geometry")
            assert r.result["frames"] == N_PROJ and r.result["ros_msg"]
    # the cell's recorder recorded its cell only, and its recording replays offline in that namespace
    topics = recording_topics(rec)
    assert all(t.startswith("/cell_a/") for t in topics), topics
    assert topics["/cell_a/ct/detector/image"] == N_PROJ
    assert find_namespace(rec) == "/cell_a"
    out = tmp_path / "offline"
    exe = pathlib.Path(__file__).resolve().parents[2] / "ros_ws/install/ct_calib_nodes/lib/ct_calib_nodes/ct_offline_solve"
    r = subprocess.run([str(exe), str(rec), "--instrument", str(tmp_path / "cell_a_instrument.yaml"),
                        "--out", str(out), "--history", str(db)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "CT cell namespace /cell_a" in r.stdout
    static = json.loads((out / "results.json").read_text())["static"]
    assert np.allclose(static["x"][:13], geoms["cell_a"][-1].static_estimate.values[:13], rtol=0, atol=1e-12)
    res_topics = {m.topic for m in iter_recording(out / "results.mcap")}
    assert "/cell_a/ct/geometry" in res_topics
    with History(db) as h:
        offline = h.list(cell="/cell_a", kind="ct_geometry", source="offline", with_details=True)
        assert len(offline) == 1 and any(i.role == "recording" and i.sha256 for i in offline[0].inputs)
