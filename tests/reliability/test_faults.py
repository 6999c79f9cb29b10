"""Faults over real DDS: frames lost in transport, and the recorder killed with SIGKILL.

A best-effort publisher sends a 20-frame campaign (one stage position) and drops every tenth
frame (the stage reading still goes out). The detector (sensor-data QoS), the geometry solver
and the recorder run as processes. The live graph must solve from the frames that arrived and
report the loss (stage readings without a frame, dropped when the next frame overtakes them or after the pairing timeout). Then five
more frames go out and the recorder is killed with SIGKILL at once: its file must give the offline
tool everything up to the last flushed chunk, with what was lost said, and a solve.
"""

import json
import os
import re
import signal

import pytest
from metro_msgs.msg import CtGeometry, SphereObservationArray
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image, JointState

from ct_calib_nodes import offline
from ct_calib_nodes.io.mcap_io import ReadReport, iter_recording
from ct_calib_nodes.nodes.runner import QOS_LATCHED, QOS_RELIABLE_STREAM
from reliab_recordings import IMAGE, STAGE, ct_recording

pytestmark = pytest.mark.ros


def test_frame_loss_and_recorder_sigkill(tmp_path, start_node, ros_node, capsys):
    good = []
    cell = tmp_path / "cell"
    ct_recording(cell, n_positions=1, n_proj=20, messages=good)
    files = ["-p", f"instrument_file:={cell / 'ct_instrument.yaml'}",
             "-p", f"reference_object_file:={cell / 'reference_object.yaml'}"]
    bag = tmp_path / "killed.mcap"
    rec = start_node("ct_calib_nodes", "mcap_recorder", "--ros-args", "-p", f"output:={bag}",
                     "-p", f"topics:=[{IMAGE}, {STAGE}]", "-p", "flush_period_s:=0.5")
    det = start_node("ct_calib_nodes", "ct_sphere_detector", "--ros-args", *files, "-p", "reliable:=false",
                     "-p", "pair_timeout_s:=2.0", "-p", "init_frames:=4")
    sol = start_node("ct_calib_nodes", "ct_geometry_solver", "--ros-args", *files, "-p", "idle_solve_s:=2.0")
    pub_i = ros_node.create_publisher(Image, IMAGE, qos_profile_sensor_data)
    pub_j = ros_node.create_publisher(JointState, STAGE, qos_profile_sensor_data)
    geometries, observations = [], []
    ros_node.create_subscription(CtGeometry, "/ct/geometry", geometries.append, QOS_LATCHED)
    ros_node.create_subscription(SphereObservationArray, "/ct/observations", observations.append, QOS_RELIABLE_STREAM)
    assert ros_node.spin_until(lambda: pub_i.get_subscription_count() >= 2 and pub_j.get_subscription_count() >= 2
                               and "recording /ct/stage" in rec.log() and "recording /ct/detector" in rec.log(),
                               timeout=40), rec.log() + det.log()
    frames = [(good[i][2], good[i + 1][2]) for i in range(0, len(good), 2)]
    dropped = 0
    for k, (img, js) in enumerate(frames):
        pub_j.publish(js)
        if k % 10 == 9:                     # the transport loses this frame: 10 %
            dropped += 1
            continue
        pub_i.publish(img)
        # paced like a detector that waits for the reader (a best-effort queue of depth 5 would
        # otherwise also lose frames while identity initialises; that loss would be reported too)
        n_before = len(observations)
        if k < 3:
            ros_node.spin_until(lambda: False, timeout=0.15)
        else:
            ros_node.spin_until(lambda n=n_before: len(observations) > n, timeout=30 if k == 3 else 3)
    assert ros_node.spin_until(lambda: len(geometries) > 0, timeout=60), sol.log()[-3000:] + det.log()[-3000:]
    ros_node.spin_until(lambda: "unpaired message(s) dropped" in det.log(), timeout=10)
    n_frames_used = geometries[-1].static_estimate.status.observations
    # the recorder has flushed the campaign; five more frames go out and it is killed at once
    ros_node.spin_until(lambda: False, timeout=1.5)
    for img, js in frames[:5]:
        img.header.stamp.sec += 1000
        js.header.stamp.sec += 1000
        pub_i.publish(img)
        pub_j.publish(js)
    os.kill(rec.proc.pid, signal.SIGKILL)
    rec.proc.wait(10)
    assert rec.proc.returncode == -signal.SIGKILL
    alive = [p.proc.poll() is None for p in (det, sol)]
    for p in (det, sol):
        p.stop()
    assert all(alive), det.log()[-2000:] + sol.log()[-2000:]

    # live: solved from what arrived, the loss reported
    dlog, slog = det.log(), sol.log()
    published = int(re.findall(r"'published': (\d+)", dlog)[-1])
    # the campaign's frames (the five sent just before the kill may or may not be detected before
    # the detector stops: they are not part of the campaign)
    campaign = sum(1 for o in observations if o.header.stamp.sec < 1000 + 1_700_000_000)
    lost = re.findall(r"dropped unpaired (\{.*?\}\})", dlog)[-1]
    # Besides the 10 % the test withholds, a loaded machine's best-effort transport may lose more
    # (CI, 2 cores under the full suite: 15 of the 18 frames sent were published; one image came
    # without its stage reading and was dropped unpaired, counted; the other two never reached the
    # detector, image nor stage reading, which nothing downstream can count). The solve must come
    # from most of the campaign.
    sent = len(frames) - dropped
    assert 12 <= campaign <= sent and published >= campaign, dlog[-2000:]
    assert geometries[-1].static_estimate.status.code == 0, geometries[-1].static_estimate.status.message
    assert n_frames_used > 0
    assert "'stage': {'count_bound': 0, 'byte_bound': 0, 'timeout': " in lost, lost
    # a stage reading whose frame was lost is dropped when the next frame arrives (overtaken), or
    # after the pairing timeout when no frame follows
    n_lost_stage = sum(int(re.search(rf"'stage': \{{[^}}]*'{k}': (\d+)", lost).group(1)) for k in ("timeout", "overtaken"))
    # the last lost frame's stage reading may not have reached its pairing timeout when the
    # detector stops: it is then reported as still unpaired at stop, not as dropped
    n_waiting_stage = int(re.findall(r"still unpaired at stop \{'image': \d+, 'stage': (\d+)\}", dlog)[-1])
    assert n_lost_stage + n_waiting_stage >= dropped, dlog[-2000:]
    assert f"{campaign} frames" in slog or "converged" in slog

    # the killed recording: read up to the last complete chunk, the tail reported
    rep = ReadReport()
    msgs = list(iter_recording(bag, report=rep))
    imgs = [m for m in msgs if m.topic == IMAGE and m.msg.header.stamp.sec < 1000 + 1_700_000_000]
    assert len(imgs) >= campaign, rep.summary()       # every flushed frame of the campaign is there
    assert rep.lost and ("truncated" in rep.lost[-1].reason or "without its data-end" in rep.lost[-1].reason)
    assert rep.lost[-1].offset + rep.lost[-1].nbytes == bag.stat().st_size
    out = tmp_path / "offline"
    rc = offline.main([str(bag), "--instrument", str(cell / "ct_instrument.yaml"),
                       "--reference-object", str(cell / "reference_object.yaml"), "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0, text[-3000:]
    assert "[offline] lost:" in text and "without a partner" in text, text[-3000:]
    res = json.loads((out / "results.json").read_text())
    assert res["static"] is not None and res["counts"]["frames"] >= campaign
    with capsys.disabled():
        print(f"\nframes sent {len(frames) - dropped} of {len(frames)}, detected and published {published}, "
              f"stage readings without a frame {n_lost_stage} (+{n_waiting_stage} unpaired at stop); killed recording: {rep.summary()}; "
              f"{rep.lost[-1].describe()}")
