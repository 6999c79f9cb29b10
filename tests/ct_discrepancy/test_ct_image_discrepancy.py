"""Image-level discrepancy checks (core/ct_image_discrepancy.py): rendered frames with hidden image physics
(detector lag, glare halo, source output drift) applied to the counts, the model told nothing; a clean scene
names nothing. Blur, counts, instrument and seed vary per case; tolerances from the reported uncertainty."""
import cv2
import numpy as np
import pytest

from ct_calib_nodes.core import ct_image_discrepancy as imd
from ct_calib_nodes.core.geometry import DetectorSpec
from ct_calib_nodes.core.phantom import helix49
from ct_calib_nodes.core.render import RenderSettings, render_projection

from campaign import draw_instrument

DET = DetectorSpec(512, 512, 0.0008)
N_VIEWS = 72


def _frames(seed, effect=None, amp=0.0, n_pairs=2):
    rng = np.random.default_rng(seed)
    w, _srd = draw_instrument(rng)
    i0, blur = float(rng.uniform(2e4, 6e4)), float(rng.uniform(0.4, 1.0))
    st = RenderSettings(flat_field_counts=i0, blur_sigma_px=blur)
    ref = helix49()
    import dataclasses
    scene = dataclasses.replace(ref, tube=None)
    pairs = imd.pick_pairs(N_VIEWS, n_pairs)
    frames = {}
    alphas = 2 * np.pi * np.arange(N_VIEWS) / N_VIEWS
    for kp, k in pairs:
        prev = render_projection(w, np.zeros(6), alphas[kp], scene, DET, st, rng).image.astype(np.float32)
        img = render_projection(w, np.zeros(6), alphas[k], scene, DET, st, rng).image.astype(np.float32)
        tau = k / (N_VIEWS - 1) - 0.5
        if effect == "detector_lag":
            img = img - amp * (i0 - prev)
        elif effect == "scatter_glare":
            img = (1 - amp) * img + amp * cv2.GaussianBlur(img, (0, 0), 6.0, borderType=cv2.BORDER_REPLICATE)
        elif effect == "source_output_drift":
            img = img * (1 + amp * tau)
            prev = prev * (1 + amp * (kp / (N_VIEWS - 1) - 0.5))
        frames[kp] = imd.ImageFrame(np.rint(prev) / i0, float(alphas[kp]), int(kp * 1e9))
        frames[k] = imd.ImageFrame(np.rint(img) / i0, float(alphas[k]), int(k * 1e9))
    return imd.analyse_images(frames, pairs, w, scene, DET, (0, int((N_VIEWS - 1) * 1e9))), blur


@pytest.mark.parametrize("seed", [21])
def test_clean_scene_names_nothing_and_states_limits(seed):
    out, blur = _frames(seed)
    assert out["performed"] and out["findings"] == [], out["terms"]
    assert abs(out["blur_sigma_px"] - blur) < 0.05
    for t in ("detector_lag", "scatter_glare"):
        assert 0 < out["terms"][t]["limit"] < 1.0          # percent: what this recording could have seen


@pytest.mark.parametrize("seed,effect,amp", [(31, "detector_lag", 0.004), (32, "scatter_glare", 0.03)])
def test_hidden_image_physics_is_named_with_its_size(seed, effect, amp):
    out, _ = _frames(seed, effect, amp)
    named = [f["term"] for f in out["findings"]]
    assert named and named[0] == effect, out["terms"]
    t = out["terms"][effect]
    assert abs(t["value"] - 100 * amp) < max(4 * t["u"], 0.15 * 100 * amp), t


def test_source_output_drift_needs_enough_projections():
    out, _ = _frames(41, "source_output_drift", 0.02, n_pairs=1)
    assert out["terms"]["source_output_drift"].get("cannot_see")       # 1 projection analysed: no trend to test
    out, _ = _frames(41, "source_output_drift", 0.02, n_pairs=4)
    t = out["terms"]["source_output_drift"]
    assert "source_output_drift" in [f["term"] for f in out["findings"]], t
    assert abs(t["value"] - 2.0) < max(4 * t["u"], 0.3), t
