"""Frames left out of a failed identity initialisation are not lost (ct_pipeline.FrameProcessor).

When the first window of frames does not initialise identity, the oldest frame is set aside and the next
frame tried. Those frames used to be dropped without a trace (found on a two-turn recording whose first
frame was missing from the observations with no problem reported); they are now assigned, in recording
order, once an initialisation succeeds, or come out rejected with the reason when none does."""

import dataclasses

import numpy as np

from ct_calib_nodes.core import identify
from ct_calib_nodes.core.ct_pipeline import FrameProcessor
from ct_calib_nodes.core.geometry import DetectorSpec
from ct_calib_nodes.core.phantom import helix49
from ct_calib_nodes.core.render import RenderSettings, render_projection
from ct_calib_nodes.core.scenario import default_static_truth

DET = DetectorSpec(1024, 1024, 0.0004)
SRD, SDD = 0.364, 1.04821


def _frames(n=9):
    w = default_static_truth(SRD, SDD)
    rng = np.random.default_rng(5)
    proc = FrameProcessor(helix49(), DET, SDD, 60000.0)
    out = []
    for j, a in enumerate(np.linspace(0.0, 2 * np.pi, 72, endpoint=False)[:n]):
        img = render_projection(w, np.zeros(6), a, helix49(), DET, RenderSettings(), rng).image
        out.append((1_000_000_000 * (j + 1), proc.detect(img, "mono16", SRD), float(a)))
    return out


def _processor(fail_first: int, monkeypatch):
    proc = FrameProcessor(helix49(), DET, SDD, 60000.0, init_frames=4)
    calls = {"n": 0}
    real = identify.SphereIdentifier.initialise

    def flaky(self, *args, **kwargs):
        calls["n"] += 1
        res = real(self, *args, **kwargs)
        if calls["n"] <= fail_first:            # an initialisation that fails (as on a bad first window)
            self._w, self._geom = None, None
            return dataclasses.replace(res, success=False, message=f"failed on purpose ({calls['n']})")
        return res
    monkeypatch.setattr(identify.SphereIdentifier, "initialise", flaky)
    return proc, calls


def test_frames_set_aside_are_assigned_once_identity_initialises(monkeypatch):
    frames = _frames()
    proc, calls = _processor(2, monkeypatch)
    out = []
    for stamp, det, a in frames:
        out += proc.push_detections(stamp, det, a, SRD)
    out += proc.flush()
    assert calls["n"] >= 3
    assert [fr.stamp_ns for fr in out] == [f[0] for f in frames]          # every frame, in recording order
    for fr in out:                                                         # the set-aside ones identified too
        assert np.count_nonzero(fr.flag == 0) >= 20, (fr.stamp_ns, fr.reason[:3])


def test_frames_come_out_rejected_when_identity_never_initialises(monkeypatch):
    frames = _frames(6)
    proc, calls = _processor(10 ** 6, monkeypatch)
    out = []
    for stamp, det, a in frames:
        out += proc.push_detections(stamp, det, a, SRD)
    out += proc.flush()
    assert [fr.stamp_ns for fr in out] == [f[0] for f in frames]
    assert all(np.count_nonzero(fr.flag == 0) == 0 and len(fr.flag) > 0 for fr in out)
