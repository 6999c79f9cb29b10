#!/usr/bin/env python3
"""Example plant subscriber: receives the CT cell's calibration (geometry and error map), checks it is
valid (status SUCCESS, error map final) and fresh, prints it, and exits. Plain rclpy; no project code needed, only metro_msgs.
With --measurement it also waits for the Pixel Probe cell's latest measurement result
(``picms/measurement/result``, std_msgs/String: the JSON of measurement.json without its raw points,
latched) and prints every feature's size with its uncertainty; usable when every planned point was
measured and every feature fitted.

    python plant_subscriber.py [--max-age-days 30] [--timeout 60] [--measurement] [--ros-args -r __ns:=/cell_a]

Topic names are relative: with ``-r __ns:=/cell_a`` it reads cell A's ``/cell_a/ct/geometry``.
Exit status: 0 both received and valid; 1 not received in time; 3 received but not usable.
"""
import argparse
import json
import math
import sys
import time

import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from metro_msgs.msg import CtGeometry, ErrorMap, SolveStatus
from std_msgs.msg import String

# The calibration topics are latched: a late subscriber gets the latest one only with this QoS.
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
STATUS = {v: k for k, v in vars(SolveStatus).items() if k.isupper() and isinstance(v, int)}
ARCSEC = 180 * 3600 / math.pi


def stamp_s(header):
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def usable(name, status, header, max_age_s):
    """A calibration is usable when its status is SUCCESS and its data are not older than max_age_s."""
    if status.code != SolveStatus.SUCCESS:
        return f"{name}: NOT USABLE, status {STATUS.get(status.code, status.code)}: {status.message}"
    age = time.time() - stamp_s(header)
    if max_age_s > 0 and age > max_age_s:
        return f"{name}: STALE, data {age / 86400:.1f} days old"
    return None


def print_geometry(g):
    e = g.static_estimate
    n = len(e.values)
    u = [math.sqrt(e.covariance[i * n + i]) if len(e.covariance) == n * n else float("nan") for i in range(n)]
    print(f"geometry ({e.model}, campaign {g.campaign_id or '-'}, data end {stamp_s(g.header):.3f} s, "
          f"status {STATUS[e.status.code]}, "
          f"rms {e.status.rms_residual:.4f} px, {e.status.observations} observations):")
    for name, unit, v, s in zip(e.names, e.units, e.values, u):
        print(f"  {name:6} = {v:+.9f} {unit}  (u = {s:.2e} {unit})")


def print_error_map(m):
    print(f"error map ({m.mode}, definition {m.definition}, campaign {m.campaign_id or '-'}, "
          f"{'final' if m.final else 'NOT FINAL (campaign still running)'}, on the geometry of stamp "
          f"{m.geometry_stamp.sec + m.geometry_stamp.nanosec * 1e-9:.3f} s, {len(m.srd_reported_m)} positions; "
          f"position 0 is the reference: value and u 0):")
    for k, srd in enumerate(m.srd_reported_m):
        print(f"  SRD {srd * 1e3:8.3f} mm: positioning {m.positioning_m[k] * 1e6:+8.3f} +- "
              f"{m.u_positioning_m[k] * 1e6:.3f} um, straightness x/y {m.straightness_x_m[k] * 1e6:+7.3f} / "
              f"{m.straightness_y_m[k] * 1e6:+7.3f} um, pitch/yaw/roll {m.pitch_rad[k] * ARCSEC:+6.2f} / "
              f"{m.yaw_rad[k] * ARCSEC:+6.2f} / {m.roll_rad[k] * ARCSEC:+6.2f} arcsec")
    for note in m.notes:
        print(f"  note: {note}")


def print_measurement(doc):
    """Print a measurement result; returns why it is not usable (None when it is)."""
    s = doc.get("summary", {})
    print(f"measurement of {doc.get('part', '?')} ({doc.get('mode', '?')} mode): {s.get('n_ok')}/{s.get('n_points')} points")
    bad = [f"{f.get('id')}: {f['error']}" for f in doc.get("features", []) if "error" in f]
    for f in doc.get("features", []):
        if "error" in f:
            continue
        size = f["size"] if isinstance(f["size"], list) else [f["size"]]
        u = f["u_size"] if isinstance(f["u_size"], list) else [f["u_size"]]
        print(f"  {f['id']:10} {f['type']:9} size " + " x ".join(f"{v * 1e3:.6f}" for v in size) + " mm  (u = "
              + " x ".join(f"{x * 1e6:.3f}" for x in u) + f" um), form rms {f['form_rms'] * 1e6:.3f} um, "
              f"{f['n_points']} points")
    for g in doc.get("dot_grids", []):
        for sp in g.get("spacings", []):
            print(f"  {g['id']:10} spacing {sp['k']} pitch: {sp['mean'] * 1e3:.6f} mm (n {sp['n']})")
    if s.get("n_ok") != s.get("n_points"):
        bad.append(f"only {s.get('n_ok')} of {s.get('n_points')} points measured")
    return f"measurement: NOT USABLE, {'; '.join(bad)}" if bad else None


def main():
    args = rclpy.utilities.remove_ros_args(sys.argv)[1:]
    ap = argparse.ArgumentParser()
    ap.add_argument("--max-age-days", type=float, default=30.0, help="older calibrations are stale (0 = no limit)")
    ap.add_argument("--timeout", type=float, default=60.0)
    ap.add_argument("--measurement", action="store_true", help="also wait for the Pixel Probe measurement result")
    a = ap.parse_args(args)
    rclpy.init()
    node = Node("plant_subscriber")
    got = {}
    node.create_subscription(CtGeometry, "ct/geometry", lambda m: got.__setitem__("geometry", m), LATCHED)
    node.create_subscription(ErrorMap, "ct/error_map", lambda m: got.__setitem__("error_map", m), LATCHED)
    want = {"geometry", "error_map"}
    if a.measurement:
        want.add("measurement")
        node.create_subscription(String, "picms/measurement/result", lambda m: got.__setitem__("measurement", m), LATCHED)
    t0 = time.monotonic()
    while rclpy.ok() and len(got) < len(want) and time.monotonic() - t0 < a.timeout:
        rclpy.spin_once(node, timeout_sec=0.1)
    code = 0
    if "geometry" in got:
        print_geometry(got["geometry"])
    if "error_map" in got:
        print_error_map(got["error_map"])
    missing = want - set(got)
    if missing:
        topics = {"geometry": "ct/geometry", "error_map": "ct/error_map", "measurement": "picms/measurement/result"}
        print(f"not received within {a.timeout} s: {sorted(missing)} on "
              f"{[node.resolve_topic_name(topics[t]) for t in sorted(missing)]}")
        code = 1
    max_age = a.max_age_days * 86400
    problems = []
    if "geometry" in got:
        problems.append(usable("geometry", got["geometry"].static_estimate.status, got["geometry"].header, max_age))
    if "error_map" in got:
        m = got["error_map"]
        problems += [usable(f"error map position {k + 1}", e.status, e.header, max_age)
                     for k, e in enumerate(m.motions)]
        if not m.final:
            problems.append("error map: NOT FINAL, the campaign is still running (positions to come)")
        if "geometry" in got and (m.geometry_stamp.sec, m.geometry_stamp.nanosec) != \
                (got["geometry"].header.stamp.sec, got["geometry"].header.stamp.nanosec):
            print("note: the error map rests on another geometry than the one received (a newer geometry "
                  "awaits its error map)")
    if "measurement" in got:
        try:
            problems.append(print_measurement(json.loads(got["measurement"].data)))
        except (ValueError, KeyError, TypeError) as exc:
            problems.append(f"measurement: NOT USABLE, unreadable result ({exc})")
    problems = [p for p in problems if p]
    for p in problems:
        print(p)
    if not problems and not missing:
        print("calibration valid")
    node.destroy_node()
    rclpy.try_shutdown()
    return code or (3 if problems else 0)


if __name__ == "__main__":
    sys.exit(main())
