"""Simulated CT views through the offline tool's detection and identity (shared by the rendered Monte
Carlo, tests/ct_validation/rendered_mc.py, and the discrepancy campaigns, tests/ct_discrepancy/campaign.py)."""
from __future__ import annotations

import numpy as np

from ct_calib_nodes.core.ct_pipeline import CampaignAccumulator, FrameProcessor
from ct_calib_nodes.core.detect import FrameError


def detect_views(views, ref_file, det, sdd, flat_field_counts) -> CampaignAccumulator:
    """Detection and identity, in order, on ``views``: (stamp_ns, mono16 image, alpha [rad], reported SRD
    [m]) as the offline tool pairs them; unusable frames are skipped. Returns the campaign's observations
    (stage positions split by the reported SRD)."""
    proc = FrameProcessor(ref_file, det, sdd, flat_field_counts)
    acc = CampaignAccumulator()

    def take(results):
        for fr in results:
            ids, uv, sig, minor = fr.accepted()
            idx = np.searchsorted(ref_file.ids, ids) if len(ids) else np.zeros(0, np.int64)
            acc.add_frame(fr.stamp_ns, fr.alpha_rad, fr.srd_reported_m, idx, uv, sig, 0, minor)

    for stamp, image, alpha, srd in views:
        try:
            take(proc.push(stamp, image, "mono16", alpha, srd))
        except FrameError:
            continue
    take(proc.flush())
    return acc
