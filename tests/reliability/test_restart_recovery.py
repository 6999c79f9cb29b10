"""The geometry solver and the error-motion node killed with SIGKILL mid-campaign and restarted: they
replay their campaign journals, say which frames they need again, the last valid calibration stays
published meanwhile, and the campaign completes with a geometry and an error map bit-identical to
those of an uninterrupted solver and error-motion node (run side by side in another namespace on
the same messages). Plus the journal file itself: torn tails, damage, foreign
files, atomic renewal."""
import os
import signal

import numpy as np
import pytest

from ct_calib_nodes.io.journal import Journal, JournalError, journal_path
from ct_obs_msg import observation_array


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


@pytest.mark.ros
def test_solver_killed_mid_campaign_resumes_bit_identical(start_node, ros_node, tmp_path):
    from metro_msgs.msg import CtGeometry, ErrorMap, SphereObservationArray

    from ct_calib_nodes.core.geometry import forward_df, static_to_detector_frame
    from ct_calib_nodes.core.scenario import default_campaign
    from ct_calib_nodes.io import ct_files
    from ct_calib_nodes.io.history import History
    from ct_calib_nodes.nodes.runner import QOS_LATCHED, QOS_RELIABLE_STREAM

    instrument = ct_files.load_instrument(ct_files.default_instrument_path())
    ref = ct_files.load_reference_object(ct_files.default_reference_object_path())
    truth = default_campaign(3, 0.02, 0.364, instrument.sdd_reported_m)
    geom = static_to_detector_frame(truth.static_w, ref.centres_of_m)
    n, n2 = 24, 8
    alphas = 2 * np.pi * np.arange(n) / n
    uv = [forward_df(geom, truth.motions[k], alphas, instrument.detector) for k in range(3)]
    srd = truth.srd_reported_m
    rng = np.random.default_rng(20261125)
    sigma = float(rng.uniform(0.03, 0.12))

    def campaign(t0, n_second=0):
        frames = [observation_array((t0 + j) * 10**9, float(a), srd[0], ref.ids, uv[0][j] + rng.normal(0, sigma, uv[0][j].shape))
                  for j, a in enumerate(alphas)]
        for j in range(n_second):      # position 2: every third angle
            frames.append(observation_array((t0 + 100 + j) * 10**9, float(alphas[3 * j]), srd[1], ref.ids,
                                            uv[1][3 * j] + rng.normal(0, sigma, uv[1][3 * j].shape)))
        # the stage moves on: one frame of the next position ends the last one
        k = 2 if n_second else 1
        frames.append(observation_array((t0 + 200) * 10**9, 0.0, srd[k], ref.ids[:1], uv[k][0][:1]))
        return frames

    camp_a, camp_b = campaign(100), campaign(20_000, n2)
    db, jdir = tmp_path / "cell.sqlite", tmp_path / "journal"
    args = ("--ros-args", "-p", "idle_solve_s:=0.0", "-p", f"history_db:={db}", "-p", f"journal_dir:={jdir}")
    ref_args = ("--ros-args", "-r", "__ns:=/uninterrupted", "-p", "idle_solve_s:=0.0",
                "-p", f"history_db:={tmp_path / 'ref.sqlite'}", "-p", f"journal_dir:={tmp_path / 'ref_journal'}")
    got, got_ref, maps, maps_ref = [], [], [], []
    ros_node.create_subscription(CtGeometry, "/ct/geometry", got.append, QOS_LATCHED)
    ros_node.create_subscription(CtGeometry, "/uninterrupted/ct/geometry", got_ref.append, QOS_LATCHED)
    ros_node.create_subscription(ErrorMap, "/ct/error_map", maps.append, QOS_LATCHED)
    ros_node.create_subscription(ErrorMap, "/uninterrupted/ct/error_map", maps_ref.append, QOS_LATCHED)
    pub = ros_node.create_publisher(SphereObservationArray, "/ct/observations", QOS_RELIABLE_STREAM)
    pub_ref = ros_node.create_publisher(SphereObservationArray, "/uninterrupted/ct/observations", QOS_RELIABLE_STREAM)

    def feed(p, frames, solver):
        assert ros_node.spin_until(lambda: p.get_subscription_count() >= 2, timeout=40), solver.log()
        for m in frames:
            p.publish(m)
            ros_node.spin_until(lambda: False, timeout=0.01)

    # campaign A, completed: the valid calibration of the cell
    s1 = start_node("ct_calib_nodes", "ct_geometry_solver", *args, name="solver1")
    e1 = start_node("ct_calib_nodes", "ct_error_motion", *args, name="emo1")
    ref_solver = start_node("ct_calib_nodes", "ct_geometry_solver", *ref_args, name="uninterrupted")
    ref_emo = start_node("ct_calib_nodes", "ct_error_motion", *ref_args, name="uninterrupted_emo")
    feed(pub, camp_a, s1)
    assert ros_node.spin_until(lambda: got, timeout=60), s1.log()[-3000:]
    g_a = got[-1]
    # stored and journaled once logged (published first: a stop before this would leave the journal
    # without its "solved" event, and the next start solves and stores it)
    assert ros_node.spin_until(lambda: "static geometry (the stage moved to position 2)" in s1.log(), timeout=30)
    assert g_a.static_estimate.status.code == 0 and g_a.header.stamp.sec == 100 + n - 1
    assert s1.stop() == 0 and e1.stop() == 0

    # campaign B: the uninterrupted reference gets it all; the solver under test dies half-way
    feed(pub_ref, camp_b, ref_solver)
    s2 = start_node("ct_calib_nodes", "ct_geometry_solver", *args, name="solver2")
    e2 = start_node("ct_calib_nodes", "ct_error_motion", *args, name="emo2")
    assert ros_node.spin_until(lambda: pub.get_subscription_count() >= 2, timeout=40), e2.log()[-2000:]
    half = 11
    feed(pub, camp_b[:half], s2)
    for node in ("ct_geometry_solver", "ct_error_motion"):
        jfile = journal_path(str(jdir), "/", node)
        assert ros_node.spin_until(lambda: len(Journal(jfile, node, "/").read().messages) == half,
                                   timeout=30), s2.log()[-3000:] + e2.log()[-3000:]
    assert "a new campaign begins" in s2.log() and "a new campaign begins" in e2.log(), s2.log()[-3000:]
    for p in (s2, e2):
        os.killpg(p.proc.pid, signal.SIGKILL)
        p.proc.wait(10)
    # frames published while no solver runs are lost in transport (volatile QoS)
    for m in camp_b[half:half + 3]:
        pub.publish(m)
    ros_node.spin_until(lambda: False, timeout=0.5)

    got.clear()
    # the killed nodes' readers stay in the graph until their lease expires: the publisher's match
    # count alone would count them, and frames sent then would miss the restarted nodes
    def reader_gids():
        return {bytes(i.endpoint_gid) for i in ros_node.get_subscriptions_info_by_topic("/ct/observations")}
    dead = reader_gids()
    s3 = start_node("ct_calib_nodes", "ct_geometry_solver", *args, name="solver3")
    e3 = start_node("ct_calib_nodes", "ct_error_motion", *args, name="emo3")
    last = camp_b[half - 1].header.stamp.sec
    for p in (s3, e3):
        assert ros_node.spin_until(lambda: "resumed the journaled campaign" in p.log(), timeout=40), p.log()[-3000:]
        assert f"{half} accepted message(s) replayed" in p.log(), p.log()[-3000:]
        assert f"Needed again: every frame stamped after {last:.3f} s" in p.log(), p.log()[-3000:]
    log3 = s3.log()
    assert ros_node.spin_until(lambda: len(reader_gids() - dead) >= 2
                               and pub.get_subscription_count() >= len(reader_gids()), timeout=40), e3.log()[-2000:]
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
    # the error map of campaign B on geometry B: the same as the uninterrupted node's
    def on_b(ms):
        return [m for m in ms if (m.geometry_stamp.sec, m.geometry_stamp.nanosec)
                == (g_b.header.stamp.sec, g_b.header.stamp.nanosec)]
    assert ros_node.spin_until(lambda: on_b(maps) and on_b(maps_ref), timeout=60), e3.log()[-3000:]
    m_b, m_ref = on_b(maps)[-1], on_b(maps_ref)[-1]
    assert len(m_b.positioning_m) == 2 and m_b.motions[0].status.code == 0, m_b.motions[0].status.message
    for f in ("positioning_m", "straightness_x_m", "straightness_y_m", "pitch_rad", "yaw_rad", "roll_rad",
              "u_positioning_m", "covariance"):
        assert list(getattr(m_b, f)) == list(getattr(m_ref, f)), f                      # bit-identical
    assert all(p.proc.poll() is None for p in (s3, e3, ref_solver, ref_emo)), s3.log()[-2000:]
    for node in ("ct_geometry_solver", "ct_error_motion"):       # every message taken (journaled) before the stop
        jfile = journal_path(str(jdir), "/", node)
        assert ros_node.spin_until(lambda: len(Journal(jfile, node, "/").read().messages) == len(camp_b), timeout=30)
    assert s3.stop() == 0 and e3.stop() == 0
    with History(db) as h:
        recs = h.list(cell="/", kind="ct_geometry", with_details=True)
        assert [r.status for r in recs] == ["success", "success"]           # one record per campaign
        assert h.latest_valid("/", "ct_geometry").data_start_ns == 20_000 * 10**9
