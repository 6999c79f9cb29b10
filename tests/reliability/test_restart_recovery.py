"""A geometry solver killed with SIGKILL mid-campaign and restarted: it replays its campaign journal,
says which frames it needs again, keeps the last valid calibration published meanwhile, and the
campaign completes with a result bit-identical to an uninterrupted solver's (run side by side in
another namespace on the same messages). Plus the journal file itself: torn tails, damage, foreign
files, atomic renewal."""
import os
import signal

import numpy as np
import pytest

from ct_calib_nodes.io.journal import Journal, JournalError, journal_path


def test_journal_torn_tail_damage_and_renewal(tmp_path):
    path = journal_path(str(tmp_path), "/cell_a", "ct_geometry_solver")
    assert path.name == "cell_a__ct_geometry_solver.journal"
    j = Journal(path, "ct_geometry_solver", "/cell_a").read().open_append()
    msgs = [bytes([k]) * (10 + k) for k in range(20)]
    for m in msgs[:10]:
        j.append_message(m)
    j.append_event("solved", n_messages=10, frames=10)
    for m in msgs[10:]:
        j.append_message(m)
    j.close()
    size = path.stat().st_size
    r = Journal(path, "ct_geometry_solver", "/cell_a").read()
    assert r.messages == msgs and r.damaged is None and not r.final
    assert [e["frames"] for e in r.events if e["event"] == "solved"] == [10]
    # a process killed inside a write: every cut point loses at most the torn record
    rng = np.random.default_rng(7)
    data = path.read_bytes()
    for cut in sorted(set(rng.integers(1, size, 60).tolist())):
        path.write_bytes(data[:cut])
        r = Journal(path, "ct_geometry_solver", "/cell_a").read()
        assert r.messages == msgs[:len(r.messages)]
        assert (r.damaged is None) == (r.valid_bytes == cut)
        r.open_append().append_message(b"next")            # appends after the last whole record
        r.close()
        again = Journal(path, "ct_geometry_solver", "/cell_a").read()
        assert again.damaged is None and again.messages[-1] == b"next" and again.messages[:-1] == r.messages[:-1]
    # a flipped bit inside a record: read up to it, the rest dropped and said
    flipped = bytearray(data)
    flipped[size // 2] ^= 0x10
    path.write_bytes(bytes(flipped))
    r = Journal(path, "ct_geometry_solver", "/cell_a").read()
    assert r.damaged and "dropped" in r.damaged and len(r.messages) < 20 and r.messages == msgs[:len(r.messages)]
    # another node's journal under this name: refused, not merged
    with pytest.raises(JournalError, match="belongs to node"):
        Journal(path, "ct_error_motion", "/cell_a").read()
    # final after the last message: nothing to resume; a new campaign replaces the file whole
    path.write_bytes(data)
    j = Journal(path, "ct_geometry_solver", "/cell_a").read().open_append()
    j.append_event("final", n_messages=20)
    j.close()
    assert Journal(path, "ct_geometry_solver", "/cell_a").read().final
    j = Journal(path, "ct_geometry_solver", "/cell_a").read().start_new()
    j.close()
    r = Journal(path, "ct_geometry_solver", "/cell_a").read()
    assert r.messages == [] and r.events == [] and not path.with_suffix(".journal.new").exists()


def _observations_msg(sec, alpha, srd, ids, uv):
    from builtin_interfaces.msg import Time
    from metro_msgs.msg import SphereObservation, SphereObservationArray

    a = SphereObservationArray(rotary_angle_rad=alpha, srd_reported_m=srd, image_cols=1024, image_rows=1024)
    a.header.stamp = Time(sec=sec)
    for i, (c, r) in zip(ids, uv):
        a.observations.append(SphereObservation(sphere_id=int(i), col_px=float(c), row_px=float(r), sigma_px=0.05))
    return a


@pytest.mark.ros
def test_solver_killed_mid_campaign_resumes_bit_identical(start_node, ros_node, tmp_path):
    from metro_msgs.msg import CtGeometry, SphereObservationArray

    from ct_calib_nodes.core.geometry import forward_srf
    from ct_calib_nodes.core.scenario import default_static_truth
    from ct_calib_nodes.io import ct_files
    from ct_calib_nodes.io.history import History
    from ct_calib_nodes.nodes.runner import QOS_LATCHED, QOS_RELIABLE_STREAM

    instrument = ct_files.load_instrument(ct_files.default_instrument_path())
    ref = ct_files.load_reference_object(ct_files.default_reference_object_path())
    truth = default_static_truth()
    n = 24
    alphas = 2 * np.pi * np.arange(n) / n
    uv = forward_srf(truth, ref.centres_of_m, alphas, instrument.detector)
    rng = np.random.default_rng(20261125)
    sigma = float(rng.uniform(0.03, 0.12))

    def campaign(t0):
        frames = [_observations_msg(t0 + j, float(a), 0.364, ref.ids, uv[j] + rng.normal(0, sigma, uv[j].shape))
                  for j, a in enumerate(alphas)]
        # the stage moves on: one frame of position 2 ends position 1
        frames.append(_observations_msg(t0 + n + 5, 0.0, 0.30, ref.ids[:1], uv[0][:1]))
        return frames

    camp_a, camp_b = campaign(100), campaign(20_000)
    db, jdir = tmp_path / "cell.sqlite", tmp_path / "journal"
    args = ("--ros-args", "-p", "idle_solve_s:=0.0", "-p", f"history_db:={db}", "-p", f"journal_dir:={jdir}")
    ref_args = ("--ros-args", "-r", "__ns:=/uninterrupted", "-p", "idle_solve_s:=0.0",
                "-p", f"history_db:={tmp_path / 'ref.sqlite'}", "-p", f"journal_dir:={tmp_path / 'ref_journal'}")
    got, got_ref = [], []
    ros_node.create_subscription(CtGeometry, "/ct/geometry", got.append, QOS_LATCHED)
    ros_node.create_subscription(CtGeometry, "/uninterrupted/ct/geometry", got_ref.append, QOS_LATCHED)
    pub = ros_node.create_publisher(SphereObservationArray, "/ct/observations", QOS_RELIABLE_STREAM)
    pub_ref = ros_node.create_publisher(SphereObservationArray, "/uninterrupted/ct/observations", QOS_RELIABLE_STREAM)

    def feed(p, frames, solver):
        assert ros_node.spin_until(lambda: p.get_subscription_count() > 0, timeout=40), solver.log()
        for m in frames:
            p.publish(m)
            ros_node.spin_until(lambda: False, timeout=0.01)

    # campaign A, completed: the valid calibration of the cell
    s1 = start_node("ct_calib_nodes", "ct_geometry_solver", *args, name="solver1")
    ref_solver = start_node("ct_calib_nodes", "ct_geometry_solver", *ref_args, name="uninterrupted")
    feed(pub, camp_a, s1)
    assert ros_node.spin_until(lambda: got, timeout=60), s1.log()[-3000:]
    g_a = got[-1]
    # stored and journaled once logged (published first: a stop before this would leave the journal
    # without its "solved" event, and the next start solves and stores it)
    assert ros_node.spin_until(lambda: "static geometry (the stage moved to position 2)" in s1.log(), timeout=30)
    assert g_a.static_estimate.status.code == 0 and g_a.header.stamp.sec == 100 + n - 1
    assert s1.stop() == 0

    # campaign B: the uninterrupted reference gets it all; the solver under test dies half-way
    feed(pub_ref, camp_b, ref_solver)
    s2 = start_node("ct_calib_nodes", "ct_geometry_solver", *args, name="solver2")
    half = 11
    jfile = journal_path(str(jdir), "/", "ct_geometry_solver")
    feed(pub, camp_b[:half], s2)
    assert ros_node.spin_until(lambda: len(Journal(jfile, "ct_geometry_solver", "/").read().messages) == half,
                               timeout=30), s2.log()[-3000:]
    assert "a new campaign begins" in s2.log() or "resumed the journaled campaign" in s2.log(), s2.log()[-3000:]
    os.killpg(s2.proc.pid, signal.SIGKILL)
    s2.proc.wait(10)
    # frames published while no solver runs are lost in transport (volatile QoS)
    for m in camp_b[half:half + 3]:
        pub.publish(m)
    ros_node.spin_until(lambda: False, timeout=0.5)

    got.clear()
    s3 = start_node("ct_calib_nodes", "ct_geometry_solver", *args, name="solver3")
    assert ros_node.spin_until(lambda: "resumed the journaled campaign" in s3.log(), timeout=40), s3.log()[-3000:]
    log3 = s3.log()
    assert f"{half} accepted message(s) replayed" in log3, log3[-3000:]
    last = camp_b[half - 1].header.stamp.sec
    assert f"Needed again: every frame stamped after {last:.3f} s" in log3, log3[-3000:]
    # meanwhile the cell's last valid calibration (A) is what ct/geometry carries
    assert ros_node.spin_until(lambda: got, timeout=20), log3[-3000:]
    assert list(got[-1].static_estimate.values) == list(g_a.static_estimate.values)
    # the missing frames re-sent, the campaign completes
    feed(pub, camp_b[half:], s3)
    assert ros_node.spin_until(lambda: got_ref and any(g.header.stamp.sec >= 20_000 for g in got), timeout=60), \
        s3.log()[-3000:] + ref_solver.log()[-2000:]
    g_b, g_ref = got[-1], got_ref[-1]
    assert ros_node.spin_until(lambda: "static geometry (the stage moved to position 2)" in s3.log(), timeout=30)
    assert g_b.static_estimate.status.code == 0, g_b.static_estimate.status.message
    assert list(g_b.static_estimate.values) == list(g_ref.static_estimate.values)          # bit-identical
    assert list(g_b.static_estimate.covariance) == list(g_ref.static_estimate.covariance)
    assert g_b.static_estimate.status.observations == g_ref.static_estimate.status.observations
    # and it differs from A (a real new solve, not the old calibration)
    assert list(g_b.static_estimate.values) != list(g_a.static_estimate.values)
    assert all(p.proc.poll() is None for p in (s3, ref_solver)), s3.log()[-2000:]
    assert s3.stop() == 0
    with History(db) as h:
        recs = h.list(cell="/", kind="ct_geometry", with_details=True)
        assert [r.status for r in recs] == ["success", "success"]           # one record per campaign
        assert h.latest_valid("/", "ct_geometry").data_start_ns == 20_000 * 10**9
