"""Stage positions from the sequence of readings in time (issue 12, item 5).

Before: frames were grouped by matching the reported SRD within a hard-coded 10 um against every
earlier position, so a return to the first SRD merged new frames into position 1 (no repeatability
or bidirectional check possible; the static fit mixed two poses) and 15 um of read-back jitter
split one position into several. Now positions are split on motion in time, the tolerance is a
parameter, positions not adjacent in time are never merged, and revisits give a repeatability.
"""

import numpy as np
import pytest

from ct_calib_nodes.core.ct_pipeline import (CampaignAccumulator, PositionSegmenter, campaign_error_map,
                                             repeatability, revisit_groups, solve_campaign_position,
                                             solve_campaign_static)
from ct_calib_nodes.core.scenario import default_campaign
from ct_calib_nodes.core.simulate_obs import simulate_observations

from ct_core_settings import CONTOUR_RADIUS_M, SIGMA_PX


def _feed(acc, srd_per_frame, t0=0):
    for j, s in enumerate(srd_per_frame):
        acc.add_frame(t0 + j * 1000, 0.01 * j, s, np.zeros(0, int), np.zeros((0, 2)))


def test_return_to_first_srd_is_a_new_position():
    srd = [0.364] * 5 + [0.384] * 5 + [0.364] * 5
    acc = CampaignAccumulator()
    _feed(acc, srd)
    assert [p.n_frames for p in acc.positions] == [5, 5, 5]
    assert [p.srd_reported_m for p in acc.positions] == [0.364, 0.384, 0.364]
    assert revisit_groups(acc.srd_reported_m) == [[0, 2]]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_read_back_jitter_does_not_split_a_position(seed):
    """15 um (sd) of read-back jitter on 3 positions 20 mm apart: 3 positions with the default
    tolerance; the former hard-coded 10 um splits them into many."""
    rng = np.random.default_rng(seed)
    nominal = np.repeat([0.364, 0.384, 0.404], 40)
    srd = nominal + rng.normal(0.0, 15e-6, nominal.size)
    acc = CampaignAccumulator()
    _feed(acc, srd)
    assert [p.n_frames for p in acc.positions] == [40, 40, 40]
    med = [np.median(srd[i * 40:(i + 1) * 40]) for i in range(3)]
    assert np.allclose(acc.srd_reported_m, med, rtol=0, atol=1e-12)
    tight = CampaignAccumulator(1e-5)
    _feed(tight, srd)
    assert len(tight.positions) > 3


def test_segmenter_tolerance_is_checked_and_used():
    with pytest.raises(ValueError, match="tolerance"):
        PositionSegmenter(0.0)
    seg = PositionSegmenter(5e-4)
    ks = [seg.push(s)[0] for s in (0.1, 0.1003, 0.0998, 0.1006, 0.1009)]
    assert ks == [0, 0, 0, 1, 1]          # 0.6 mm from the median 0.1 m moves; 0.3 mm does not


def test_bidirectional_campaign_repeatability(centres, detector):
    """Forward 364 -> 444 mm in 20 mm steps, back to 364 mm, with 15 um read-back jitter; on the
    way back the stage stops 10 um further along its travel than on the way out (a reversal error).
    Every revisit is a position of its own; the static fit uses the first 364 mm visit only; the
    repeatability at each revisited SRD is the reading difference minus the 10 um (positioning, the
    paper's sign: positive = travelled less), zero in straightness, within its uncertainty."""
    camp = default_campaign(5, 0.020)
    order = [0, 1, 2, 3, 4, 3, 2, 1, 0]
    back = 10e-6
    rng = np.random.default_rng(77)
    alphas = np.linspace(0.0, 2 * np.pi, 60, endpoint=False)
    acc = CampaignAccumulator()
    t = 0
    medians = []
    for visit, k in enumerate(order):
        motion = camp.motions[k].copy()
        if visit > 4:
            motion[:3] += back * camp.travel_direction_df
        sim = simulate_observations(camp.static_w, centres, detector, alphas, rng, SIGMA_PX, motion=motion,
                                    contour_radius_m=CONTOUR_RADIUS_M, report_sigma=True).obs
        readings = camp.srd_reported_m[k] + rng.normal(0.0, 15e-6, len(alphas))
        medians.append(np.median(readings))
        for j in range(len(alphas)):
            sel = sim.view_index == j
            acc.add_frame(t, alphas[j], readings[j], sim.sphere_index[sel], sim.uv_px[sel], sim.sigma_px[sel],
                          0, sim.minor_axis_px[sel])
            t += 1_000_000
    assert len(acc.positions) == 9 and all(p.n_frames == 60 for p in acc.positions)
    assert revisit_groups(acc.srd_reported_m) == [[0, 8], [1, 7], [2, 6], [3, 5]]
    static = solve_campaign_static(acc, centres, detector, camp.sdd_reported_m)
    assert static.success, static.message
    assert static.n_views == 60                               # the first visit only, not the return
    motions = {k: solve_campaign_position(acc, k, static, detector) for k in range(1, 9)}
    assert all(m.success for m in motions.values())
    em, ks = campaign_error_map(acc, motions, static)
    assert ks == list(range(9))
    groups = repeatability(em, ks)
    assert [g["positions"] for g in groups] == [[0, 8], [1, 7], [2, 6], [3, 5]]
    for g in groups:
        a, b = g["positions"]
        expect = (medians[b] - medians[a]) - back
        u = g["u_positioning_m"][0]
        assert 0 < u < 3e-6, g
        assert abs(g["positioning_m"][0] - expect) < 4 * u, (g["positioning_m"][0], expect, u)
        for f in ("straightness_x_m", "straightness_y_m"):
            assert abs(g[f][0]) < 4 * g["u_" + f][0] + 1e-8, (f, g)
    # the revisit of the reference position reads the same relative to itself: u > 0 only from its own noise
    assert groups[0]["positioning_m"][0] == pytest.approx(em.positioning_m[8], abs=1e-15)


def test_frame_rate_monitor_counts_falling_behind():
    """Frames stamped 100 ms apart (10 frames/s): 80 ms of processing keeps up, 150 ms does not."""
    from ct_calib_nodes.core.ct_pipeline import FrameRateMonitor

    ok, slow = FrameRateMonitor(), FrameRateMonitor()
    behind_ok = sum(ok.add(j * 100_000_000, 0.080) for j in range(30))
    behind_slow = sum(slow.add(j * 100_000_000, 0.150) for j in range(30))
    assert behind_ok == 0 and behind_slow == 30 - 5
    assert slow.arrival_hz == pytest.approx(10.0) and slow.processing_hz == pytest.approx(1 / 0.15)
