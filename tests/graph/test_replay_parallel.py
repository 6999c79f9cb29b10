"""Offline replay in worker processes gives the sequential results bit for bit (issue 14, item 4).

A small rendered recording (3 stage positions, the third a return to the first SRD, 8 frames
each) is replayed with ``workers`` = 1 (everything in one process, the generic message decoder)
and ``workers`` = 2 (raw image bytes to worker processes, zero-copy view, detection there;
identity and solvers in order in the main process). Every frame's observations, the static
estimate with its covariance and every error motion must be identical; identity at the later
positions is tracked from the previous one; the revisit is a position of its own. Speed is
measured by tests/benchmarks/bench_ct_replay.py, not here.
"""

import numpy as np
import pytest

from ct_calib_nodes.core.phantom import helix49
from ct_calib_nodes.core.render import RenderSettings, render_projection
from ct_calib_nodes.core.scenario import default_campaign
from ct_calib_nodes.io import ct_files

pytestmark = pytest.mark.ros
N_PROJ = 8


def _record(path, inst):
    from builtin_interfaces.msg import Time
    from sensor_msgs.msg import JointState

    from ct_calib_nodes.io.convert import image_from_array
    from ct_calib_nodes.io.mcap_io import Rosbag2McapWriter

    camp = default_campaign(2, 0.05, 0.364, inst.sdd_reported_m)
    rng = np.random.default_rng(5)
    ref = helix49()
    n = 0
    with Rosbag2McapWriter(path) as w:
        for k in (0, 1, 0):
            for j in range(N_PROJ):
                a = 2 * np.pi * j / N_PROJ + 0.1
                img = render_projection(camp.static_w, camp.motions[k], a, ref, inst.detector, RenderSettings(),
                                        rng).image
                t = 1_700_000_000_000_000_000 + n * 100_000_000
                n += 1
                stamp = Time(sec=t // 10**9, nanosec=t % 10**9)
                js = JointState(name=["rotary", "magnification"], position=[a, float(camp.srd_reported_m[k])])
                js.header.stamp = stamp
                w.write("/ct/stage/joint_states", js, t)
                w.write("/ct/detector/image", image_from_array(img, stamp, "ct_detector"), t)


def _same(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """(recording, instrument, reference object, sequential full-detection result), shared."""
    from ct_calib_nodes.offline import solve_recording

    inst = ct_files.load_instrument(ct_files.default_instrument_path())
    ref = ct_files.load_reference_object(ct_files.default_reference_object_path())
    rec = tmp_path_factory.mktemp("replay") / "small.mcap"
    _record(rec, inst)
    return rec, inst, ref, solve_recording(rec, inst, ref, workers=1)


def test_parallel_replay_is_bit_identical(small):
    from ct_calib_nodes.offline import solve_recording

    rec, inst, ref, seq = small
    par = solve_recording(rec, inst, ref, workers=2)
    assert seq.counts == par.counts and not seq.problems and not par.problems, (seq.problems, par.problems)
    assert [p.n_frames for p in par.acc.positions] == [N_PROJ] * 3          # the return is a new position
    assert len(seq.frames) == len(par.frames) == 3 * N_PROJ
    for f1, f2 in zip(seq.frames, par.frames):
        assert f1.stamp_ns == f2.stamp_ns and f1.reason == f2.reason
        for name in ("ids", "flag", "centre_px", "sigma_px", "semi_axes_px", "angle_rad", "fit_rms_px"):
            assert _same(getattr(f1, name), getattr(f2, name)), name
    assert seq.static.success
    assert _same(seq.static.x, par.static.x) and _same(seq.static.covariance, par.static.covariance)
    for mode in seq.motions:
        assert seq.motions[mode].keys() == par.motions[mode].keys() == {1, 2}
        for k in seq.motions[mode]:
            assert _same(seq.motions[mode][k].x, par.motions[mode][k].x)
    assert [m for _s, m in par.identity] == [m for _s, m in seq.identity]
    assert sum("tracked from the previous stage position" in m and m.startswith("pose found")
               for _s, m in par.identity) == 2, par.identity
    groups = par.repeatability["multi"]["travel"]
    assert [g["positions"] for g in groups] == [[0, 2]]
    # the return to the first SRD repeats it: zero within its uncertainty (the renderer has no stage error there)
    assert abs(groups[0]["positioning_m"][0]) < 4 * groups[0]["u_positioning_m"][0] + 1e-7
    # results.json carries the positions (with their time spans) and the repeatability; the report line names them
    import json

    from ct_calib_nodes.offline import _result_dict, repeatability_text

    d = json.loads(json.dumps(_result_dict(par, inst, ref, rec, {"instrument": "i", "reference_object": "r"})))
    assert [p["index"] for p in d["stage_positions"]] == [0, 1, 2]
    assert d["stage_positions"][2]["first_stamp_ns"] > d["stage_positions"][1]["last_stamp_ns"]
    assert d["repeatability"]["multi"]["travel"][0]["positions"] == [0, 2]
    assert "positions 1, 3" in repeatability_text(groups)


def test_windowed_replay_parallel_is_bit_identical_and_close_to_full(small, monkeypatch):
    """Windowed detection (core/track.py, blocks of 3 frames): 2 workers == 1 process bit for bit
    (a block goes to one worker); the solved static geometry agrees with the full-frame one
    within a small fraction of its standard uncertainty. Here the shared memory has room for
    one frame only: the frames in flight beside it go through the pool's pipe (both hand-overs
    in one run; the full-detection test above uses the slots alone)."""
    from ct_calib_nodes import offline
    from ct_calib_nodes.core.track import TrackSettings
    from ct_calib_nodes.offline import solve_recording

    rec, inst, ref, full = small
    ts = TrackSettings(block_frames=3)
    seq = solve_recording(rec, inst, ref, workers=1, tracking=ts)
    monkeypatch.setattr(offline._FrameSlots, "MAX_BYTES", 1)
    par = solve_recording(rec, inst, ref, workers=2, tracking=ts)
    assert not seq.problems and not par.problems, (seq.problems, par.problems)
    assert seq.counts == par.counts == full.counts
    # blocks start at each position's first frame and every 3 frames: 3 x ceil(8 / 3) key frames
    assert seq.detection_modes == par.detection_modes
    # (45 deg between these frames: some move too far for the crop and fall back to the whole frame)
    assert seq.detection_modes["full"] == 9
    assert seq.detection_modes["window"] >= 6, seq.detection_modes
    assert sum(seq.detection_modes.values()) == 3 * N_PROJ
    for f1, f2 in zip(seq.frames, par.frames):
        assert f1.stamp_ns == f2.stamp_ns and f1.reason == f2.reason
        for name in ("ids", "flag", "centre_px", "sigma_px", "semi_axes_px", "angle_rad", "fit_rms_px"):
            assert _same(getattr(f1, name), getattr(f2, name)), name
    assert _same(seq.static.x, par.static.x) and _same(seq.static.covariance, par.static.covariance)
    for mode in seq.motions:
        for k in seq.motions[mode]:
            assert _same(seq.motions[mode][k].x, par.motions[mode][k].x)
    assert seq.static.success and full.static.success
    u = np.sqrt(np.diag(full.static.covariance))
    assert np.max(np.abs(seq.static.x - full.static.x) / u) < 0.1, np.abs(seq.static.x - full.static.x) / u


def test_frame_slots_hand_over_and_refuse_cleanly():
    """A frame's bytes come back unchanged from its slot; a frame larger than a slot, every slot
    busy, or no room for the shared file at all: None (the caller sends the bytes instead); the
    file is gone after close."""
    import os

    from ct_calib_nodes.offline import _WORKER, _FrameSlots

    s = _FrameSlots(2, 5000)
    a, b = os.urandom(4999), os.urandom(17)
    ra, rb = s.put(a), s.put(b)
    assert bytes(_FrameSlots.view(ra)) == a and bytes(_FrameSlots.view(rb)) == b
    assert s.put(b"x") is None                      # both slots busy
    s.release(ra)
    assert s.put(os.urandom(8193)) is None          # larger than a slot (5000 -> 8192 bytes)
    rc = s.put(b"abc")
    assert rc[1] == ra[1] and bytes(_FrameSlots.view(rc)) == b"abc"
    path = s.path
    _WORKER.pop("slots").clear()                    # this process's views (a worker keeps its own)
    s.close()
    assert not os.path.exists(path)
    huge = type("Huge", (_FrameSlots,), {"MAX_BYTES": 1 << 62})(1 << 40, 1 << 20)   # an exabyte: no room
    assert huge.put(b"x") is None and huge.path is None
    huge.close()


def test_frame_slots_of_a_killed_replay_are_removed(tmp_path):
    """A replay killed with SIGKILL leaves its slot file; the next replay removes files whose
    creating process is gone and keeps those of running processes and foreign names."""
    import os
    import subprocess

    from ct_calib_nodes.offline import _FrameSlots

    dead = subprocess.Popen(["true"])
    dead.wait()                                     # a process id that no longer runs
    orphan = tmp_path / f"metro_replay_{dead.pid}_abc123"
    alive = tmp_path / f"metro_replay_{os.getpid()}_def456"
    other = tmp_path / "metro_replay_notapid_x"
    for f in (orphan, alive, other):
        f.write_bytes(b"\0" * 4096)
    assert _FrameSlots.sweep_orphans(str(tmp_path)) == [str(orphan)]
    assert not orphan.exists() and alive.exists() and other.exists()
