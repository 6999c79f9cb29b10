"""Tracker-vs-stage clock lag from the readings taken while the stage moves (core/timing_lag.py)."""
from dataclasses import replace

import numpy as np

from picms_nodes.core import campaign, cell
from picms_nodes.core import picms_discrepancy as pd
from picms_nodes.core import timing_lag
from picms_nodes.core.calibrate import in_window, settled_windows


def _session(seed, lag_s, stage_errors, **rates):
    # streams only (no frames): the lag lives in the tracker and stage streams
    rng = np.random.default_rng(seed)
    truth = cell.make_cell(rng, replace(cell.make_physics(rng, stage_error_motions=stage_errors), tracker_lag_s=lag_s))
    rec, _ = campaign.simulate_session(truth, rng, pattern=pd.grid_pattern(), dwell_s=1.2, mid_move_frames=0,
                                       render=False, **rates)
    return rec


def _estimate(rec):
    return timing_lag.estimate(rec.joint_stamps_ns, rec.joint_positions, rec.tracker,
                               rec.cell["tracker"]["constellation"])


def test_lag_measured_within_its_uncertainty_over_seeds():
    # 5 cells (random tracker distance 1.5-4 m, so reading noise 12-20 um; stage error motions on half of
    # them), lags of either sign up to 40 ms and none. The stated u must cover the error: every |z| < 4 and
    # the rms of z between 0.25 and 1.8 (5 draws; measured 0.95 over 8)
    z = []
    for k, lag in enumerate((0.0, -0.040, 0.012, 0.025, -0.008)):
        e = _estimate(_session(700 + k, lag, stage_errors=k % 2 == 0))
        assert e["seen"], e
        assert e["u_lag_s"] < 5e-4 and e["n_moves"] >= 30, e
        z.append((e["lag_s"] - lag) / e["u_lag_s"])
        if lag:
            # the lag explains the moving readings: their held-out rms falls to near the settled scatter
            assert e["held_out_rms_after_m"] < min(1.5 * e["sigma_m"], e["held_out_rms_before_m"]), e
    z = np.array(z)
    assert np.all(np.abs(z) < 4) and 0.25 < np.sqrt(np.mean(z ** 2)) < 1.8, z


def test_tracker_read_only_when_settled_cannot_show_a_lag():
    rec = _session(711, -0.030, stage_errors=False)
    win = settled_windows(rec.joint_stamps_ns, rec.joint_positions)
    rec.tracker = [r for r in rec.tracker if in_window(r[0], win) >= 0]
    e = _estimate(rec)
    assert not e["seen"] and "while moving" in e["reason"]
    # no stage readings at all
    e = timing_lag.estimate(np.zeros(0, np.int64), np.zeros((0, 3)), rec.tracker, ["smr_1"])
    assert not e["seen"] and "joint_states" in e["reason"]


def test_lag_with_slow_streams():
    # a 10 Hz joint_states stream (linear interpolation between readings 0.1 s apart) and a 15 Hz tracker
    # (3 readings per SMR per second): measured z 0.15 to 1.49 over 6 such sessions, u 0.34-0.60 ms
    e = _estimate(_session(901, 0.020, stage_errors=True, joint_rate_hz=10.0, tracker_rate_hz=15.0))
    assert e["seen"] and e["u_lag_s"] < 1.5e-3 and abs(e["lag_s"] - 0.020) < 4 * e["u_lag_s"], e
