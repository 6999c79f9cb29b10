"""The simulated CT cell end to end (the README's main command).

Starts, each in its own process over DDS (as `ros2 run` would): the MCAP
recorder, the sphere detector, the geometry solver, the error-motion node and
the CT projection simulator. Waits for the campaign to be rendered, detected
and solved, stops the graph (the recorder closes the bag), then writes the
report (Figs 7-12 style plots against the simulator's reference), the
reconstruction geometry export and a recovered-vs-truth table, and prints
where everything is.

    ct_demo [--positions 6] [--projections 24] [--rate 8] [--out out/] [--bags bags/]
"""

from __future__ import annotations

import argparse
import datetime
import os
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np

ARCSEC = 180.0 * 3600.0 / np.pi


def _exe(name: str) -> str:
    here = pathlib.Path(sys.argv[0]).resolve().parent
    cand = here / name
    return str(cand) if cand.is_file() else name


def _start(argv, log_path):
    log = open(log_path, "wb")
    return subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, start_new_session=True), log


# the recorder drains what DDS still holds for up to mcap_recorder.DRAIN_MAX_S (30 s) before it
# closes the file: give it longer than that before SIGKILL (a killed recorder leaves no summary)
RECORDER_STOP_S = 45.0


def _stop(proc, timeout=20.0):
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5)
    return proc.returncode



def campaign_over(latest: dict, seen: dict, n_positions: int, now: float, quiet_s: float = 6.0) -> bool:
    """Both error maps (multi and single) cover n_positions and are complete. A map carrying the
    ErrorMap ``final`` flag is complete only when the flag is set (the error-motion node's own word);
    a map without the field (an older recording or message set) falls back to: updated after the last
    observation and no observation for quiet_s seconds."""
    maps = [latest.get("multi"), latest.get("single")]
    if any(m is None or len(m.srd_reported_m) < n_positions for m in maps):
        return False
    if all(hasattr(m, "final") for m in maps):
        return all(bool(m.final) for m in maps)
    quiet = seen["all_obs_at"] is not None and now - seen["all_obs_at"] > quiet_s
    return quiet and seen["multi_after"] and seen["single_after"]

def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--positions", type=int, default=6, help="stage positions (default 6)")
    ap.add_argument("--projections", type=int, default=24, help="projections per position (default 24)")
    ap.add_argument("--step-mm", type=float, default=None,
                    help="stage step [mm] (default: the paper's travel, SRD 364 to 724 mm, split evenly: "
                         "72 mm for 6 positions, 20 mm for 19)")
    ap.add_argument("--rate", type=float, default=8.0, help="frame rate of the simulator [Hz]")
    ap.add_argument("--out", default="out", help="report directory root")
    ap.add_argument("--bags", default="bags", help="recording directory root")
    ap.add_argument("--timeout", type=float, default=900.0, help="give up after this long [s]")
    args = ap.parse_args(argv)
    if args.positions < 2:
        ap.error("--positions must be >= 2 (one static position and at least one error-motion position)")
    if args.step_mm is None:
        args.step_mm = 360.0 / (args.positions - 1)

    import rclpy  # noqa: PLC0415
    from metro_msgs.msg import CtGeometry, ErrorMap, SphereObservationArray  # noqa: PLC0415

    from ct_calib_nodes.nodes.runner import QOS_LATCHED  # noqa: PLC0415

    tag = datetime.datetime.now().strftime("ct_demo_%Y%m%d_%H%M%S")
    out = pathlib.Path(args.out).resolve() / tag
    bag = pathlib.Path(args.bags).resolve() / tag
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    bag.parent.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    print(f"[demo] ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')}; logs in {logs}")

    procs = {}
    ros = ["--ros-args", "-p"]
    procs["recorder"] = _start([_exe("mcap_recorder"), *ros, f"output:={bag}"], logs / "mcap_recorder.log")
    procs["detector"] = _start([_exe("ct_sphere_detector")], logs / "ct_sphere_detector.log")
    procs["geometry"] = _start([_exe("ct_geometry_solver")], logs / "ct_geometry_solver.log")
    procs["motion"] = _start([_exe("ct_error_motion")], logs / "ct_error_motion.log")
    time.sleep(1.0)
    procs["sim"] = _start([_exe("ct_projection_sim"), "--ros-args",
                           "-p", f"n_positions:={args.positions}", "-p", f"projections_per_position:={args.projections}",
                           "-p", f"step_m:={args.step_mm / 1000.0}", "-p", f"rate_hz:={args.rate}",
                           "-p", "wait_for_subscribers:=2",
                           "-p", f"truth_output:={out / 'simulation_truth.yaml'}",
                           "-p", f"reference_output:={out / 'reference_error_map.csv'}"],
                          logs / "ct_projection_sim.log")
    n_frames = args.positions * args.projections
    print(f"[demo] simulating {args.positions} positions x {args.projections} projections "
          f"({n_frames} frames of 1024x1024 mono16) at {args.rate} Hz")

    rclpy.init()
    node = rclpy.create_node("ct_demo_monitor")
    latest = {}
    seen = {"obs": 0, "all_obs_at": None, "multi_after": False, "single_after": False}

    def on_obs(_m):
        # the monitor may miss early messages during discovery: completion does not rely on the count
        seen["obs"] += 1
        seen["all_obs_at"] = time.monotonic()
        seen["multi_after"] = seen["single_after"] = False

    def on_map(mode, m):
        latest[mode] = m
        if seen["all_obs_at"] is not None:
            seen[mode + "_after"] = True

    from ct_calib_nodes.nodes.runner import QOS_RELIABLE_STREAM  # noqa: PLC0415
    node.create_subscription(SphereObservationArray, "/ct/observations", on_obs, QOS_RELIABLE_STREAM)
    node.create_subscription(ErrorMap, "/ct/error_map", lambda m: on_map("multi", m), QOS_LATCHED)
    node.create_subscription(ErrorMap, "/ct/error_map/single", lambda m: on_map("single", m), QOS_LATCHED)
    node.create_subscription(CtGeometry, "/ct/geometry", lambda m: latest.__setitem__("geometry", m), QOS_LATCHED)
    ok = False
    dead = []
    last_print = 0.0
    from rclpy.executors import SingleThreadedExecutor  # noqa: PLC0415
    executor = SingleThreadedExecutor()   # persistent: every ready subscription served in turn
    executor.add_node(node)
    try:
        while time.monotonic() - t_start < args.timeout:
            executor.spin_once(timeout_sec=0.2)
            # done: every frame detected, and both error maps updated after the last observation
            sim_done = procs["sim"][0].poll() == 0
            if sim_done and campaign_over(latest, seen, args.positions, time.monotonic()):
                ok = True
                break
            dead = [k for k, (p, _l) in procs.items() if p.poll() not in (None, 0)]
            if dead:
                print(f"[demo] node(s) {dead} exited with an error; see {logs}")
                for k in dead:
                    procs[k][1].flush()
                    tail = pathlib.Path(procs[k][1].name).read_text(errors="replace").strip().splitlines()[-3:]
                    for line in tail:
                        print(f"[demo]   {k}: {line}")
                break
            if time.monotonic() - last_print > 15:
                last_print = time.monotonic()
                em = latest.get("multi")
                print(f"[demo] {time.monotonic() - t_start:5.0f} s: geometry {'solved' if 'geometry' in latest else 'pending'}, "
                      f"{seen['obs']}/{n_frames} frames detected, "
                      f"error map {0 if em is None else len(em.srd_reported_m)}/{args.positions} positions")
    finally:
        for name in ("sim", "detector", "geometry", "motion", "recorder"):
            _stop(procs[name][0], timeout=RECORDER_STOP_S if name == "recorder" else 20.0)
            procs[name][1].close()
        node.destroy_node()
        rclpy.try_shutdown()
    wall = time.monotonic() - t_start
    if not ok:
        why = "a node exited with an error" if dead else f"the error map did not complete within {args.timeout:.0f} s"
        print(f"[demo] FAILED: {why}; logs in {logs}")
        return 1
    bag_mb = sum(f.stat().st_size for f in bag.glob("*")) / 1e6 if bag.exists() else 0.0
    index = write_outputs(out, latest, wall, bag, bag_mb)
    print(f"[demo] campaign wall time {wall:.0f} s; recording {bag} ({bag_mb:.0f} MB)")
    print(f"[demo] report: {index}")
    return 0


def _residuals_from_bag(bag, ref, inst, w, multi_map):
    """Reprojection residuals of the published geometry and multi-projection error motions at every
    stage position, from the recorded /ct/observations (the messages the solvers used), or None."""
    from ct_calib_nodes.core.ct_pipeline import CampaignAccumulator, campaign_residuals  # noqa: PLC0415
    from ct_calib_nodes.io.convert import MessageError  # noqa: PLC0415
    from ct_calib_nodes.io.mcap_io import iter_recording  # noqa: PLC0415
    from ct_calib_nodes.io.observations_msg import frame_observations  # noqa: PLC0415

    acc = CampaignAccumulator()
    id_to_index = {int(i): k for k, i in enumerate(ref.ids)}
    for m in iter_recording(bag, topics=["/ct/observations"]):
        try:
            acc.add_frame(*frame_observations(m.msg, id_to_index))
        except (MessageError, ValueError) as exc:
            print(f"[demo] residual plot: skipped a recorded observation message ({exc})")
    if not acc.positions or w.shape != (13,):
        return None
    motions = {}                       # the error map's rows 1.. are positions k >= 1, matched by SRD
    for srd, est in zip(list(multi_map.srd_reported_m)[1:], multi_map.motions):
        k = int(np.argmin([abs(p.srd_reported_m - srd) for p in acc.positions]))
        if k > 0 and abs(acc.positions[k].srd_reported_m - srd) < 1e-5:
            motions[k] = np.asarray(est.values, dtype=float)
    return campaign_residuals(acc, w, ref.centres_of_m, inst.detector, motions,
                              label="static model (k = 1) and multi-projection error motions (k > 1)")


def write_outputs(out: pathlib.Path, latest: dict, wall_s: float, bag, bag_mb: float) -> pathlib.Path:
    """Report, geometry export and recovered-vs-truth table from the published results."""
    from ct_calib_nodes.io import ct_files  # noqa: PLC0415
    from ct_calib_nodes.core.error_map import error_map  # noqa: PLC0415
    from ct_calib_nodes.io.campaign_outputs import write_report_and_export  # noqa: PLC0415
    from ct_calib_nodes.io.results import error_map_from_msg, static_from_geometry_msg, write_json_atomic  # noqa: PLC0415
    from ct_calib_nodes.io.truth_files import read_truth  # noqa: PLC0415

    ref = ct_files.load_reference_object(ct_files.default_reference_object_path())
    inst = ct_files.load_instrument(ct_files.default_instrument_path())
    g = latest["geometry"]
    w, cov, geom, _code = static_from_geometry_msg(g, ref.centres_of_m)
    est = g.static_estimate
    series = [error_map_from_msg(latest[mode], mode) for mode in ("multi", "single")]
    motions = np.array([[0.0] * 6] + [list(e.values) for e in latest["multi"].motions])
    # the paper's detector-frame positioning (Fig. 7 comparison) from the published motions and
    # their total per-position covariances: exact for the positioning, which involves no fit
    cov_k = np.array([np.zeros((6, 6))] + [np.reshape(e.covariance, (6, 6)) for e in latest["multi"].motions])
    series.append(error_map(latest["multi"].srd_reported_m, motions, cov_k, definition="detector", name="multi",
                            index_repeatability_rad=series[0].index_repeatability_rad))
    meta = {"recording": f"{bag} ({bag_mb:.0f} MB)", "campaign wall time": f"{wall_s:.0f} s",
            "static solve": f"{est.status.message}; rms {est.status.rms_residual:.4f} px; "
                            f"{est.status.observations // 2} centres; {est.status.rejected} rejected detections",
            "reference": "the simulator's true error map (a simulated independent measurement)"}
    index = write_report_and_export(out, names=est.names, units=est.units, values=est.values, covariance=cov,
                                    geometry=geom, series=series, motions=motions,
                                    srd_reported_m=latest["multi"].srd_reported_m, detector=inst.detector,
                                    reference_path=out / "reference_error_map.csv",
                                    residuals=_residuals_from_bag(bag, ref, inst, w, latest["multi"]), meta=meta)

    truth = read_truth(out / "simulation_truth.yaml")
    rows = []
    for s in series[:2]:
        tem = truth.error_map(s.definition)
        for f, unit, scale in (("positioning_m", "um", 1e6), ("straightness_x_m", "um", 1e6),
                               ("straightness_y_m", "um", 1e6), ("pitch_rad", "arcsec", ARCSEC),
                               ("yaw_rad", "arcsec", ARCSEC), ("roll_rad", "arcsec", ARCSEC)):
            err = (getattr(s, f) - tem[f][: len(getattr(s, f))]) * scale
            u = getattr(s, "u_" + f) * scale
            rows.append({"mode": s.name, "component": f, "unit": unit, "max_abs_error": float(np.max(np.abs(err))),
                         "rms_error": float(np.sqrt(np.mean(err ** 2))), "median_u": float(np.median(u[1:]))})
    static_err = (w - truth.static_w).tolist()
    write_json_atomic(out / "recovered_vs_truth.json", {"error_map": rows, "static_error_SI": static_err,
                                                         "static_names": list(est.names)})
    print("[demo] recovered error map vs simulation truth (max |error|, rms error, median standard uncertainty):")
    for r in rows:
        print(f"[demo]   {r['mode']:6s} {r['component']:17s} {r['max_abs_error']:8.2f} {r['rms_error']:8.2f} "
              f"{r['median_u']:8.2f} {r['unit']}")
    return index


if __name__ == "__main__":
    raise SystemExit(main())
