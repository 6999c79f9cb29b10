"""Resident memory of the sphere detector when stage readings never arrive (issue 10).

    source scripts/env.sh; python tests/benchmarks/bench_pairing_memory.py [--seconds 300] [--rate 10] [--size 512]

Two detector nodes run side by side on the same image stream (no stage readings at all):
- ``bounded``: the defaults (pair_max_pending 100 messages, pair_max_bytes 256 MiB, pair_timeout_s 120);
- ``timeout_only``: the obvious alternative, the former behaviour (unpaired messages dropped only after
  pair_timeout_s = 120 s; the count and byte bounds set out of reach).
Frames of ``--size``^2 mono16 are published at ``--rate`` per second for ``--seconds``; the
resident size (VmRSS) of both processes is sampled every 5 s. Ends with ONE JSON line: RSS at
start, end and peak [MiB], growth over the second half [MiB/min], frames published.
"""

import argparse
import json
import os
import pathlib
import random
import signal
import subprocess
import sys
import time

import numpy as np

from _memory import rss_mib, rss_summary  # sibling module (this folder is on sys.path)

ROOT = pathlib.Path(__file__).resolve().parents[2]
EXE = ROOT / "ros_ws" / "install" / "ct_calib_nodes" / "lib" / "ct_calib_nodes" / "ct_sphere_detector"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=300.0)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--size", type=int, default=512)
    args = ap.parse_args()
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(120, 200)))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    import rclpy
    from sensor_msgs.msg import Image

    from ct_calib_nodes.io import ct_files
    from ct_calib_nodes.nodes.runner import QOS_RELIABLE_STREAM

    tmp = pathlib.Path(os.environ.get("TMPDIR", "/tmp")) / f"bench_pairing_{os.getpid()}"
    tmp.mkdir(parents=True, exist_ok=True)
    inst = tmp / "ct_instrument.yaml"
    ct_files.write_yaml(inst, {"units": "SI", "source_to_detector": 1.04821,
                               "detector": {"cols": args.size, "rows": args.size, "pixel_pitch": 0.0004}})
    variants = {"bounded": [], "timeout_only": ["-p", "pair_max_pending:=100000000", "-p", "pair_max_bytes:=1000000000000"]}
    procs = {}
    for name, extra in variants.items():
        log = open(tmp / f"{name}.log", "wb")
        procs[name] = subprocess.Popen([str(EXE), "--ros-args", "-r", f"__node:=det_{name}", "-p",
                                        f"instrument_file:={inst}", *extra], stdout=log, stderr=subprocess.STDOUT,
                                       start_new_session=True)
    rclpy.init()
    node = rclpy.create_node("bench_pairing_pub")
    pub = node.create_publisher(Image, "/ct/detector/image", QOS_RELIABLE_STREAM)
    t0 = time.monotonic()
    while pub.get_subscription_count() < 2 and time.monotonic() - t0 < 60:
        rclpy.spin_once(node, timeout_sec=0.1)
    time.sleep(2.0)
    data = np.random.default_rng(0).integers(0, 60000, (args.size, args.size)).astype(np.uint16).tobytes()
    samples = {n: [] for n in procs}
    start = {n: rss_mib(p.pid) for n, p in procs.items()}
    t0 = time.monotonic()
    sent, next_sample = 0, t0
    try:
        while time.monotonic() - t0 < args.seconds:
            img = Image(height=args.size, width=args.size, encoding="mono16", step=2 * args.size, data=data)
            t = time.time_ns()
            img.header.stamp.sec, img.header.stamp.nanosec = t // 10**9, t % 10**9
            pub.publish(img)
            sent += 1
            now = time.monotonic()
            if now >= next_sample:
                for n, p in procs.items():
                    samples[n].append((now - t0, rss_mib(p.pid)))
                next_sample += 5.0
            delay = t0 + sent / args.rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        elapsed = time.monotonic() - t0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs.values():
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
    out = {"benchmark": "bench_pairing_memory", "frame": f"{args.size}x{args.size} mono16",
           "rate_hz_asked": args.rate, "rate_hz_achieved": round(sent / elapsed, 2), "seconds": round(elapsed, 1),
           "frames_published": sent, "note": "2-core machine shared with other jobs; RSS of the node processes"}
    for n, s in samples.items():
        r = rss_summary(s)
        out[n] = {"rss_start_mib": round(start[n], 1), "rss_end_mib": r["end_mib"], "rss_peak_mib": r["peak_mib"],
                  "growth_second_half_mib_per_min": r["growth_second_half_mib_per_min"]}
        log = (tmp / f"{n}.log").read_text(errors="replace")
        tail = [ln for ln in log.splitlines() if "detector counts" in ln]
        out[n]["final_counts"] = tail[-1].split("detector counts: ", 1)[1][:400] if tail else None
    print(json.dumps(out))


if __name__ == "__main__":
    sys.exit(main())
