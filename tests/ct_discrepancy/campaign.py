"""Rendered CT recordings with one concealed effect, shared by the discrepancy tests and the validation benchmark.

Each campaign: a random misaligned instrument (rendered_mc.draw_instrument), random renderer physics (blur,
counts, support tube), helix49, ``n_views`` projections over one turn at ``frame_dt_s`` per frame, frames
through the same detection + identity + static solve as the offline tool; the effect is a render_effects /
RenderSettings switch the solver and the engine are never told about.

Two acquisitions of the same reference object (``acquisition=``, see ACQUISITIONS): ``standard`` (magnification
2.3-3.5, the object centred on the principal ray, one turn) and ``reveal`` (magnification 4.4-5.8, the object raised
20 mm off the principal ray, two turns of 72 projections), which separates the engine's degenerate groups
(ct_discrepancy.md, "An acquisition that separates the degenerate groups").
"""

from __future__ import annotations

import dataclasses
import pathlib
import sys
import time

import numpy as np

from ct_calib_nodes.core import ct_discrepancy, render_effects as fx
from ct_calib_nodes.core.geometry import DetectorSpec
from ct_calib_nodes.core.phantom import helix49
from ct_calib_nodes.core.render import RenderSettings, render_projection
from ct_calib_nodes.core.static_solver import solve_static

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))    # tests/: the shared detect_views
from ct_views import detect_views  # noqa: E402

DEG = np.pi / 180.0
ARCSEC = DEG / 3600.0
SDD = 1.04821
DET = DetectorSpec(1024, 1024, 0.0004)
STAMP0_NS = 1_700_000_000_000_000_000


# acquisitions: the source-to-rotary-axis range drawn (magnification SDD / SRD), the object raised along the rotary
# axis off the principal ray (its pose y_P), the number of turns (each of n_views projections)
ACQUISITIONS = {
    "standard": {"srd_range": (0.30, 0.45), "raise_m": 0.0, "turns": 1},
    # separates what `standard` leaves as degenerate groups: the spread of magnification over the object's depth
    # (stage vs focal-spot vs detector drift), an expansion about the object's centre instead of the principal
    # point (expansion vs axial drifts), M times the runout on the detector, twice the projections
    "reveal": {"srd_range": (0.18, 0.24), "raise_m": 0.020, "turns": 2},
    # each part of `reveal` alone (the raised object at a low magnification, so that its shadows stay on the panel)
    "magnified": {"srd_range": (0.18, 0.24), "raise_m": 0.0, "turns": 1},
    "raised": {"srd_range": (0.40, 0.45), "raise_m": 0.020, "turns": 1},
    "two_turns": {"srd_range": (0.30, 0.45), "raise_m": 0.0, "turns": 2},
}


def _acquisition(name):
    try:
        return ACQUISITIONS[name]
    except KeyError:
        raise ValueError(f"unknown acquisition {name!r}; known: {', '.join(ACQUISITIONS)}") from None


def draw_instrument(rng, srd_range=(0.30, 0.45)):
    srd = rng.uniform(*srd_range)
    z_r = srd + rng.uniform(-2e-3, 2e-3)
    w = np.array([
        z_r, rng.uniform(-3e-3, 3e-3), rng.uniform(-3e-3, 3e-3), SDD + rng.uniform(-3e-3, 3e-3),
        rng.uniform(-0.6, 0.6) * DEG, rng.uniform(-0.6, 0.6) * DEG, rng.uniform(-0.6, 0.6) * DEG,
        rng.uniform(-1e-3, 1e-3), rng.uniform(-1e-3, 1e-3), z_r + rng.uniform(-1e-3, 1e-3),
        rng.uniform(-0.5, 0.5) * DEG, rng.uniform(0.0, 2 * np.pi), rng.uniform(-0.5, 0.5) * DEG])
    return w, srd


def effect_settings(name: str, scale: float, duration_s: float, rng) -> tuple:
    """(RenderSettings kwargs, true term id, true magnitude in the catalogue's display unit)."""
    ph = rng.uniform(0, 2 * np.pi)
    c, s = np.cos(ph), np.sin(ph)
    t_ref = 0.0                                        # time 0 = mid-scan: the calibrated geometry's instant
    if name == "clean":
        return {}, None, 0.0
    if name == "focal_spot_drift":                     # 30 um over the scan (issue 11)
        d = 30e-6 * scale
        return {"focal_spot_drift_m_per_s": (d * c / duration_s, d * s / duration_s, 0.0)}, name, d * 1e6
    if name == "detector_bow":                         # 0.5 px at the corner: sag 0.72 mm at the corner
        sag = 0.72e-3 * scale
        return {"effects": (fx.DetectorBow(sag_x_m=sag, sag_y_m=0.0),)}, name, sag * 1e3
    if name == "encoder_eccentricity":                 # 10 arcsec
        a = 10 * ARCSEC * scale
        return {"encoder_eccentricity_rad": a, "encoder_phase_rad": ph}, name, 10 * scale
    if name == "encoder_second_harmonic":              # 6 arcsec twice per turn
        a = 6 * ARCSEC * scale
        return {"effects": (fx.EncoderHarmonic(2, a, ph),)}, name, 6 * scale
    if name == "rotary_radial_runout":                 # 3 um
        e = 3e-6 * scale
        return {"effects": (fx.RotaryRunout(h_cos_m=e * c, h_sin_m=e * s),)}, name, 3 * scale
    if name == "rotary_tilt_error":                    # 15 arcsec wobble about the across-beam axis
        a = 15 * ARCSEC * scale
        return {"effects": (fx.RotaryTiltError(h_cos_rad=a * c, h_sin_rad=a * s),)}, name, 15 * scale
    if name == "stage_drift":                          # 8 um over the scan
        d = 8e-6 * scale
        return {"effects": (fx.StageDrift((d * c / duration_s, d * s / duration_s, 0.0), t_ref),)}, name, d * 1e6
    if name == "object_thermal_expansion":             # 40 ppm over the scan (steel, +3.5 K)
        e = 40e-6 * scale
        return {"effects": (fx.ObjectExpansion(e / duration_s, t_ref),)}, name, e * 1e6
    if name == "detector_distortion":                  # 0.4 px at the corner
        r = np.hypot(0.2048, 0.2048)
        k1 = 0.4 * DET.pixel_pitch_m / r ** 3 * scale
        return {"detector_distortion_k1_per_m2": k1}, name, k1
    raise ValueError(name)


EFFECTS = ("focal_spot_drift", "detector_bow", "encoder_eccentricity", "encoder_second_harmonic",
           "rotary_radial_runout", "rotary_tilt_error", "stage_drift", "object_thermal_expansion",
           "detector_distortion")


# detector formats with the same 0.41 m field (renderer settings varied in the rendered clean controls)
DETECTORS = (DET, DetectorSpec(768, 768, 0.4096 / 768), DetectorSpec(512, 512, 0.0008))


IMAGE_EFFECTS = ("detector_lag", "scatter_glare", "source_output_drift")


def _image_effect(name, amp, img, prev, i0, tau):
    """Hidden image-level physics on a counts frame (float): lag of the previous frame's deficit, a glare halo
    of a 6 px Gaussian, or the open-beam intensity drifting linearly over the scan (flat field from before)."""
    import cv2  # noqa: PLC0415

    if name == "detector_lag":
        return img if prev is None else img - amp * (i0 - prev)
    if name == "scatter_glare":
        return (1 - amp) * img + amp * cv2.GaussianBlur(img, (0, 0), 6.0, borderType=cv2.BORDER_REPLICATE)
    if name == "source_output_drift":
        return img * (1 + amp * tau)
    raise ValueError(name)


def render_campaign(seed: int, effect: str = "clean", scale: float = 1.0, n_views: int = 72,
                    frame_dt_s: float = 1.0, det: DetectorSpec | None = None, image_effect=None, keep_frames=(),
                    acquisition: str = "standard"):
    """Returns (obs, truth dict) for the first (only) stage position (``det``: detector format, default DET).

    ``image_effect`` (name, amplitude) from IMAGE_EFFECTS: hidden image-level physics on the counts (the
    detection sees it too); frames whose index is in ``keep_frames`` are returned in truth["frames"] as
    ct_image_discrepancy.ImageFrame (transmission with the campaign's flat-field level)."""
    from ct_calib_nodes.core.ct_image_discrepancy import ImageFrame  # noqa: PLC0415

    rng = np.random.default_rng(seed)
    det = det or DET
    acq = _acquisition(acquisition)
    w, srd = draw_instrument(rng, acq["srd_range"])
    phys = {"blur_sigma_px": float(rng.uniform(0.4, 1.0)), "flat_field_counts": float(rng.uniform(2e4, 6e4)),
            "tube": bool(rng.random() < 0.5), "detector_px": det.cols, "acquisition": acquisition}
    n_views = n_views * acq["turns"]
    duration = (n_views - 1) * frame_dt_s
    kw, term, mag = effect_settings(effect, scale, duration, rng)
    w = w.copy()
    w[8] += acq["raise_m"]                                 # y_P: drawn first, so the draws match `standard`'s
    ref = helix49()
    obj = dataclasses.replace(ref, tube=ref.tube if phys["tube"] else None)
    settings = RenderSettings(flat_field_counts=phys["flat_field_counts"], blur_sigma_px=phys["blur_sigma_px"], **kw)
    kept = {}
    keep = set(keep_frames)

    def views():
        prev = None
        for j, a in enumerate(np.linspace(0.0, 2 * np.pi * acq["turns"], n_views, endpoint=False)):
            t = j * frame_dt_s - duration / 2               # renderer time 0 at mid-scan (see effect_settings)
            image = render_projection(w, np.zeros(6), a, obj, det, settings, rng, time_s=t).image
            if image_effect is not None:
                raw = image.astype(np.float32)
                image = np.clip(np.rint(_image_effect(image_effect[0], image_effect[1], raw, prev,
                                                      phys["flat_field_counts"], t / duration if duration > 0 else 0.0)),
                                0, 65535).astype(np.uint16)
                prev = raw
            stamp = STAMP0_NS + int(round(t * 1e9))
            if j in keep:
                kept[j] = ImageFrame(image.astype(np.float32) / np.float32(phys["flat_field_counts"]), float(a), stamp)
            yield stamp, image, a, srd

    obs = detect_views(views(), ref, det, SDD, phys["flat_field_counts"]).positions[0].observations()
    return obs, {"w": w, "srd": srd, "sdd": SDD, "effect": effect, "term": term, "magnitude": mag,
                 "physics": phys, "ref": ref, "det": det, "frames": kept, "image_effect": image_effect,
                 "scan_ns": (STAMP0_NS + int(round(-duration / 2 * 1e9)), STAMP0_NS + int(round(duration / 2 * 1e9)))}


def analyse_campaign(seed: int, effect: str = "clean", scale: float = 1.0, n_views: int = 72, frame_dt_s: float = 1.0,
                     det: DetectorSpec | None = None, image_effect=None, image_pairs: int = 0,
                     acquisition: str = "standard"):
    """Rendered campaign -> detection -> static solve -> ct_discrepancy.run (+ image level with image_pairs > 0,
    on the reference object WITHOUT its support tube: what reference_object.yaml describes)."""
    from ct_calib_nodes.core import ct_image_discrepancy as imd  # noqa: PLC0415

    pairs = imd.pick_pairs(n_views * _acquisition(acquisition)["turns"], image_pairs) if image_pairs > 0 else []
    t0 = time.perf_counter()
    obs, truth = render_campaign(seed, effect, scale, n_views, frame_dt_s, det, image_effect,
                                 keep_frames={k for p in pairs for k in p}, acquisition=acquisition)
    det = truth["det"]
    t1 = time.perf_counter()
    st = solve_static(obs, truth["ref"].centres_of_m, det, truth["srd"], truth["sdd"])
    t2 = time.perf_counter()
    out = ct_discrepancy.run(obs, st, det)
    t3 = time.perf_counter()
    if pairs:
        ref_yaml = dataclasses.replace(truth["ref"], tube=None)
        out["image_level"] = imd.analyse_images(truth["frames"], pairs, np.asarray(st.x[:13], float), ref_yaml, det,
                                                truth["scan_ns"])
    t4 = time.perf_counter()
    out["_timing"] = {"render_detect_s": t1 - t0, "static_s": t2 - t1, "engine_s": t3 - t2, "image_s": t4 - t3}
    out["_static"] = st
    return out, truth


def noisy_centres(w, motion, alphas, times_s, ref, settings, rng, sigma, tau, stated):
    """Feature-level views: the renderer's exact ellipse centres (``frame_truth``) of the usable spheres with
    detection-like noise of sd ``sigma`` px, a shift of sd ``tau`` shared by each view's spheres, and a stated
    sigma ``stated`` (what a detector would claim). Returns CentreObservations stamped at ``times_s``."""
    from ct_calib_nodes.core.observations import CentreObservations  # noqa: PLC0415
    from ct_calib_nodes.core.render import frame_truth  # noqa: PLC0415

    uv, idx, minor, sig, stamps = [], [], [], [], []
    for a, t in zip(alphas, times_s):
        ft = frame_truth(w, motion, a, ref, DET, settings, time_s=t)
        use = np.flatnonzero(ft.usable)
        shift = rng.normal(0.0, tau, 2) if tau > 0 else np.zeros(2)
        uv.append(ft.ellipse_centre_px[use] + rng.normal(0.0, sigma, (use.size, 2)) + shift)
        idx.append(use)
        minor.append(ft.semi_axes_px[use, 1])
        sig.append(np.full(use.size, stated))
        stamps.append(STAMP0_NS + int(round(t * 1e9)))
    return CentreObservations.from_views(uv, idx, np.asarray(alphas), stamp_ns_per_view=np.array(stamps, dtype=np.int64),
                                         sigma_px_per_view=sig, minor_axis_px_per_view=minor)


def truth_campaign(seed: int, effect: str = "clean", scale: float = 1.0, n_views: int = 72, frame_dt_s: float = 1.0,
                   acquisition: str = "standard"):
    """Feature-level recording: the renderer's exact truth (render.frame_truth, hidden physics applied, no image)
    plus detection-like noise of a random size, a random per-projection shared shift and a misstated sigma.

    ``n_views`` projections per turn (ACQUISITIONS[acquisition]["turns"] turns); a time effect has its magnitude
    over the whole scan. Fast (milliseconds per view); the image-level path is :func:`render_campaign`.
    Returns (obs, truth).
    """

    rng = np.random.default_rng(seed)
    acq = _acquisition(acquisition)
    w, srd = draw_instrument(rng, acq["srd_range"])
    n_views = n_views * acq["turns"]
    duration = (n_views - 1) * frame_dt_s
    kw, term, mag = effect_settings(effect, scale, duration, rng)
    sigma = float(rng.uniform(0.005, 0.03))
    tau = float(rng.choice([0.0, 0.5]) * sigma)
    stated = sigma * float(rng.uniform(0.6, 1.6))
    w = w.copy()
    w[8] += acq["raise_m"]                                 # y_P, after the draws (they match `standard`'s)
    ref = helix49()
    settings = RenderSettings(**kw)
    obs = noisy_centres(w, np.zeros(6), np.linspace(0.0, 2 * np.pi * acq["turns"], n_views, endpoint=False),
                        np.arange(n_views) * frame_dt_s - duration / 2, ref, settings, rng, sigma, tau, stated)
    return obs, {"w": w, "srd": srd, "sdd": SDD, "effect": effect, "term": term, "magnitude": mag,
                 "physics": {"sigma_px": sigma, "shared_px": tau, "stated_px": stated, "acquisition": acquisition},
                 "ref": ref}


def analyse_truth_campaign(seed: int, effect: str = "clean", scale: float = 1.0, n_views: int = 72,
                           acquisition: str = "standard"):
    obs, truth = truth_campaign(seed, effect, scale, n_views, acquisition=acquisition)
    st = solve_static(obs, truth["ref"].centres_of_m, DET, truth["srd"], truth["sdd"])
    return ct_discrepancy.run(obs, st, DET), truth, st


def truth_multi_campaign(seed: int, n_positions: int = 4, n_views: int = 48, frame_dt_s: float = 1.0,
                         gap_s: float = 600.0, step_m: float = 0.04, focal_drift_um: float = 0.0,
                         noise_px: float | None = None):
    """Feature-level campaign of ``n_positions`` stage positions on ONE instrument (the multi-position helper).

    The stage travels ``step_m`` towards the detector between positions (reported SRD grows by it) with small
    true error motions (a few um of positioning and straightness, a few arcsec of pitch/yaw/roll); each
    position is one turn of ``n_views`` projections, ``gap_s`` seconds between the positions' scans (travel,
    settling). ``focal_drift_um``: the focal spot drifts linearly over the WHOLE campaign by this much across
    the beam (random direction in the detector plane), a campaign-long effect; per scan it moves by only
    that times scan / campaign duration. Noise, shared shift and misstated sigma as :func:`truth_campaign`.

    Returns (positions [(srd_reported_m, CentreObservations)], truth dict).
    """

    rng = np.random.default_rng(seed)
    w, srd = draw_instrument(rng, srd_range=(0.30, 0.34))
    scan = (n_views - 1) * frame_dt_s
    campaign = n_positions * scan + (n_positions - 1) * gap_s
    ph = rng.uniform(0, 2 * np.pi)
    rate = focal_drift_um * 1e-6 / campaign * np.array([np.cos(ph), np.sin(ph), 0.0])
    settings = RenderSettings(focal_spot_drift_m_per_s=tuple(rate))
    sigma = float(noise_px if noise_px is not None else rng.uniform(0.005, 0.03))
    tau = float(rng.choice([0.0, 0.5]) * sigma)
    stated = sigma * float(rng.uniform(0.6, 1.6))
    ref = helix49()
    positions, motions = [], []
    for k in range(n_positions):
        m = np.zeros(6) if k == 0 else np.concatenate([rng.normal(0, 3e-6, 3), rng.normal(0, 3 * ARCSEC, 3)])
        m[2] += k * step_m                             # along {DF} +Z, towards the detector: the SRD grows
        motions.append(m)
        t0 = k * (scan + gap_s) - 0.5 * campaign       # renderer time 0 = campaign middle
        obs = noisy_centres(w, m, np.linspace(0.0, 2 * np.pi, n_views, endpoint=False),
                            t0 + np.arange(n_views) * frame_dt_s, ref, settings, rng, sigma, tau, stated)
        positions.append((srd + k * step_m, obs))
    return positions, {"w": w, "srd": srd, "sdd": SDD, "ref": ref, "motions": motions,
                       "focal_drift_um": focal_drift_um, "focal_rate_m_per_s": rate,
                       "per_scan_um": focal_drift_um * scan / campaign, "campaign_s": campaign,
                       "physics": {"sigma_px": sigma, "shared_px": tau, "stated_px": stated}}


def render_multi_campaign(seed: int, n_positions: int = 3, n_views: int = 36, frame_dt_s: float = 1.0,
                          gap_s: float = 3600.0, step_m: float = 0.04, focal_drift_um: float = 0.0,
                          det: DetectorSpec | None = None):
    """Rendered counterpart of :func:`truth_multi_campaign`: the same campaign (one random instrument, true error
    motions, a focal spot drifting ``focal_drift_um`` across the beam over the whole campaign) rendered with
    random physics (blur, counts, support tube) and run through detection + identity, positions split by the
    reported SRD as the offline tool does. Returns (positions [(srd_reported_m, CentreObservations)], truth)."""
    rng = np.random.default_rng(seed)
    det = det or DET
    w, srd = draw_instrument(rng, srd_range=(0.30, 0.34))
    scan = (n_views - 1) * frame_dt_s
    campaign = n_positions * scan + (n_positions - 1) * gap_s
    ph = rng.uniform(0, 2 * np.pi)
    rate = focal_drift_um * 1e-6 / campaign * np.array([np.cos(ph), np.sin(ph), 0.0])
    phys = {"blur_sigma_px": float(rng.uniform(0.4, 1.0)), "flat_field_counts": float(rng.uniform(2e4, 6e4)),
            "tube": bool(rng.random() < 0.5), "detector_px": det.cols}
    ref = helix49()
    obj = dataclasses.replace(ref, tube=ref.tube if phys["tube"] else None)
    settings = RenderSettings(flat_field_counts=phys["flat_field_counts"], blur_sigma_px=phys["blur_sigma_px"],
                              focal_spot_drift_m_per_s=tuple(rate))
    motions = []

    def views():
        for k in range(n_positions):
            m = np.zeros(6) if k == 0 else np.concatenate([rng.normal(0, 3e-6, 3), rng.normal(0, 3 * ARCSEC, 3)])
            m[2] += k * step_m
            motions.append(m)
            t0 = k * (scan + gap_s) - 0.5 * campaign
            for j, a in enumerate(np.linspace(0.0, 2 * np.pi * acq["turns"], n_views, endpoint=False)):
                t = t0 + j * frame_dt_s
                frame = render_projection(w, m, a, obj, det, settings, rng, time_s=t)
                yield STAMP0_NS + int(round(t * 1e9)), frame.image, a, srd + k * step_m

    acc = detect_views(views(), ref, det, SDD, phys["flat_field_counts"])
    positions = [(p.srd_reported_m, p.observations()) for p in acc.positions]
    return positions, {"w": w, "srd": srd, "sdd": SDD, "ref": ref, "motions": motions, "physics": phys,
                       "focal_drift_um": focal_drift_um, "focal_rate_m_per_s": rate,
                       "per_scan_um": focal_drift_um * scan / campaign, "campaign_s": campaign}
