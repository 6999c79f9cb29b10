"""Accuracy of core/detect.py against rendered frames with known truth.

Frames come from core/render.py (exact cone-beam chord lengths, 4x4
oversampling, 0.7 px Gaussian blur, Poisson noise at 50000 open-beam counts,
carbon-fibre tube on) at the first (SRD 364 mm, shadows ~21 px across) and the
last stage position (SRD 724 mm, ~11 px). The detector only gets the image,
the flat-field counts, the detector size and a diameter range from the nominal
geometry; truth is used only to score.

Run with ``-s`` to see the tables (also reproduced in doc/ct_detect.md).
"""

import numpy as np
import pytest

from ct_calib_nodes.core import detect
from ct_calib_nodes.core.geometry import DetectorSpec
from ct_calib_nodes.core.phantom import helix49
from ct_calib_nodes.core.render import RenderSettings, render_projection
from ct_calib_nodes.core.scenario import default_static_truth

DET = DetectorSpec(1024, 1024, 0.0004)
SDD = 1.04821
I0 = 50000.0
N_FRAMES = 6


def diameter_range(srd_m):
    """Nominal shadow diameters [px]: 3 mm sphere, object radius 37.5 mm nearer/farther."""
    lo = 3e-3 * SDD / (srd_m + 0.04) / DET.pixel_pitch_m
    hi = 3e-3 * SDD / (srd_m - 0.04) / DET.pixel_pitch_m
    return lo, hi


def render_set(srd_m, seed, *, output="mono16", bias=False, n=N_FRAMES):
    w = default_static_truth(srd_m)
    rng = np.random.default_rng(seed)
    rs = RenderSettings(ellipse_centre_bias=bias)
    alphas = np.linspace(0.0, 2 * np.pi, n, endpoint=False) + 0.1
    return [render_projection(w, np.zeros(6), a, helix49(), DET, rs, rng, output=output) for a in alphas]


def match(found_px, truth):
    """Index of the nearest true sphere for each found centre and the distance."""
    d = np.linalg.norm(found_px[:, None, :] - truth.centre_px[None, :, :], axis=2)
    j = d.argmin(axis=1)
    return j, d[np.arange(len(j)), j]


def robust_std(x):
    return 1.4826 * np.median(np.abs(x - np.median(x, axis=0)), axis=0)


@pytest.fixture(scope="module")
def frames():
    return {"k1": render_set(0.364, 11), "last": render_set(0.724, 12)}


@pytest.fixture(scope="module")
def results(frames):
    """Errors [px] per configuration and method, split near centre / near edge."""
    out = {}
    for key, frs in frames.items():
        srd = 0.364 if key == "k1" else 0.724
        rng_d = diameter_range(srd)
        rows = {m: [] for m in ("detector", "centroid", "contour_fitEllipse")}
        zs = []
        for fr in frs:
            tr = fr.truth
            det = detect.detect_spheres(fr.image, flat_field_counts=I0, expected_shape=(1024, 1024),
                                        diameter_px_range=rng_d)
            j, dist = match(det.centre_px, tr)
            assert np.all(dist < 0.5), "every accepted detection is a real sphere"
            assert not np.any(tr.overlapping[j]), "no overlapping sphere accepted"
            err = det.centre_px - tr.centre_px[j]
            rows["detector"].append(np.column_stack([err, tr.centre_px[j]]))
            zs.append(err / det.centre_std_px)
            for m, meth in (("centroid", "centroid"), ("contour_fitEllipse", "contour_ellipse")):
                c = detect.baseline_detect(fr.image, method=meth, flat_field_counts=I0)
                jj, dd = match(c, tr)
                keep = (dd < 3.0) & tr.usable[jj]
                rows[m].append(np.column_stack([c[keep] - tr.centre_px[jj[keep]], tr.centre_px[jj[keep]]]))
        out[key] = {m: np.vstack(v) for m, v in rows.items()}
        out[key]["z"] = np.vstack(zs)
    return out


def split(arr):
    r = np.linalg.norm(arr[:, 2:4] - np.array(DET.centre_px), axis=1)
    return {"centre (r<250 px)": arr[r < 250, :2], "edge (r>350 px)": arr[r > 350, :2], "all": arr[:, :2]}


def test_accuracy_table_and_targets(results):
    print("\nconfig  method               region              n    bias_col  bias_row  std_col  std_row  "
          "rstd_col rstd_row  max|e|")
    for key, per in results.items():
        for m in ("detector", "centroid", "contour_fitEllipse"):
            for reg, e in split(per[m]).items():
                if len(e) < 5:
                    continue
                b = e.mean(axis=0)
                s = e.std(axis=0)
                rs = robust_std(e)
                print(f"{key:6s}  {m:20s} {reg:18s} {len(e):4d}  {b[0]:+.4f}   {b[1]:+.4f}   {s[0]:.4f}   "
                      f"{s[1]:.4f}   {rs[0]:.4f}   {rs[1]:.4f}   {np.abs(e).max():.3f}")
    for key, per in results.items():
        e = per["detector"][:, :2]
        n = len(e)
        assert n > 200
        # Target of the issue: spread under 0.05 px at the default noise. The
        # photon-noise prediction from the edge scatter is ~0.005-0.01 px per
        # axis (see test_uncertainty_is_calibrated); 0.05 px is >= 5x that.
        assert np.all(e.std(axis=0) < 0.05), key
        # Bias: standard error of the mean is std/sqrt(n) < 0.002 px; allow
        # 3 SE plus 0.005 px of model error (iso-level vs. silhouette, pixel
        # integration), far below the 0.05 px target.
        se = e.std(axis=0) / np.sqrt(n)
        assert np.all(np.abs(e.mean(axis=0)) < 3 * se + 0.005), key
        # Baselines: the sub-pixel detector must be more precise than both.
        for m in ("centroid", "contour_fitEllipse"):
            eb = per[m][:, :2]
            assert np.all(robust_std(e) < robust_std(eb)), (key, m)


def test_uncertainty_is_calibrated(results):
    """The reported centre covariance predicts the spread within a factor of ~2.

    The covariance models photon noise on independent edge samples; the
    background normalisation and interpolation add a little, so robust
    |z| spreads between 0.7 and 2.5 are accepted (measured ~1.2-1.8).
    """
    for key, per in results.items():
        rz = robust_std(per["z"])
        print(f"{key}: robust std of (error / reported std) = {rz.round(2)}")
        assert np.all(rz > 0.7) and np.all(rz < 2.5), (key, rz)


def test_transmission_input_matches_mono16():
    """32FC1 (I/I0) frames give the same accuracy as mono16 counts."""
    frs = render_set(0.364, 21, output="transmission", n=2)
    errs = []
    for fr in frs:
        det = detect.detect_spheres(fr.image, encoding="32FC1", expected_shape=(1024, 1024),
                                    diameter_px_range=diameter_range(0.364))
        j, dist = match(det.centre_px, fr.truth)
        assert np.all(dist < 0.5)
        assert len(det) >= 35
        errs.append(det.centre_px - fr.truth.centre_px[j])
    e = np.vstack(errs)
    assert np.all(e.std(axis=0) < 0.05)


def test_ellipse_fitters_agree():
    """OpenCV's three fitters and the geometric refinement, measured on the same frames.

    With ~64 well-spread edge points and edge noise of a few 0.01 px the
    algebraic bias is O(sigma^2 / R) ~ 1e-4 px; the fitters must agree with
    truth equally well (robust spreads within 20 % of each other).
    """
    frs = render_set(0.364, 31, n=2)
    stats = {}
    for fitter in ("fitEllipse", "fitEllipseAMS", "fitEllipseDirect", "geometric"):
        st = detect.DetectionSettings(ellipse_fitter=fitter)
        errs = []
        for fr in frs:
            det = detect.detect_spheres(fr.image, flat_field_counts=I0, diameter_px_range=diameter_range(0.364),
                                        settings=st)
            j, _ = match(det.centre_px, fr.truth)
            errs.append(det.centre_px - fr.truth.centre_px[j])
        e = np.vstack(errs)
        stats[fitter] = (e.mean(axis=0), robust_std(e), len(e))
        print(f"{fitter:17s} n={len(e)} bias={e.mean(axis=0).round(4)} robust std={robust_std(e).round(4)}")
    ref = stats["fitEllipse"][1]
    for fitter, (b, s, n) in stats.items():
        assert np.all(np.abs(s - ref) < 0.2 * ref), fitter
        assert np.all(np.abs(b) < 0.01), fitter


def test_deng_correction_of_exact_silhouettes():
    """Exact cone-sphere silhouettes: the ellipse centre sits radially outward.

    The renderer's ``ellipse_centre_bias=True`` draws the exact silhouette, whose
    centre lies ~ r_det (b / D)^2 further from the principal point than the
    projected sphere centre (up to ~0.01 px here). The radial component of
    the raw error must be positive on average for spheres far from the centre,
    and the Deng/Clackdoyle correction must remove most of it.
    """
    frs = render_set(0.364, 41, bias=True, n=4)
    raw_rad, cor_rad, expect = [], [], []
    for fr in frs:
        det = detect.detect_spheres(fr.image, flat_field_counts=I0, diameter_px_range=diameter_range(0.364),
                                    sdd_px=SDD / DET.pixel_pitch_m)
        j, _ = match(det.centre_px, fr.truth)
        tc = fr.truth.centre_px[j]
        u = tc - np.array(DET.centre_px)
        rr = np.linalg.norm(u, axis=1)
        far = rr > 300
        u = u[far] / rr[far, None]
        raw_rad.append(np.sum((det.centre_px[far] - tc[far]) * u, axis=1))
        cor_rad.append(np.sum((det.centre_corrected_px[far] - tc[far]) * u, axis=1))
        expect.append(np.sum((fr.truth.ellipse_centre_px[j][far] - tc[far]) * u, axis=1))
    raw, cor, exp_ = (np.concatenate(v) for v in (raw_rad, cor_rad, expect))
    se = raw.std() / np.sqrt(len(raw))
    print(f"\nfar spheres n={len(raw)}: true silhouette shift {exp_.mean():.4f} px, raw radial error "
          f"{raw.mean():.4f} +- {se:.4f}, corrected {cor.mean():.4f} +- {se:.4f}")
    assert exp_.mean() > 0.004
    # The effect (~0.006 px) is about 2 standard errors of these 4 frames, so
    # the rendered check only asserts that the corrected centres are unbiased
    # within 3 standard errors + 0.002 px; the formula itself is checked
    # exactly in test_deng_formula_on_true_silhouettes.
    assert abs(cor.mean()) < 3 * se + 0.002


def test_deng_formula_on_true_silhouettes():
    """deng_correction maps the exact silhouette ellipse to the projected centre.

    Truth silhouettes from the renderer's analytic cone-sphere sections (no
    image, no noise). The formula assumes a detector perpendicular to the
    principal ray; the truth detector is tilted by <= 0.6 deg and the principal
    point is taken as the detector centre (~27 px off), which leaves a
    second-order error ~ 27 px x (b/D)^2 ~ 1e-4 px. Tolerance 1e-3 px, against
    raw shifts of up to ~0.012 px.
    """
    from ct_calib_nodes.core.render import frame_truth
    w = default_static_truth(0.364)
    rs = RenderSettings(ellipse_centre_bias=True)
    raw, fixed = [], []
    for a in np.linspace(0, 2 * np.pi, 8, endpoint=False):
        tr = frame_truth(w, np.zeros(6), a, helix49(), DET, rs)
        corr = detect.deng_correction(tr.ellipse_centre_px, tr.semi_axes_px, SDD / DET.pixel_pitch_m,
                                      DET.centre_px)
        raw.append(np.linalg.norm(tr.ellipse_centre_px - tr.centre_px, axis=1))
        fixed.append(np.linalg.norm(corr - tr.centre_px, axis=1))
    raw, fixed = np.concatenate(raw), np.concatenate(fixed)
    print(f"\nsilhouette centre shift: max {raw.max():.4f} px; after correction max {fixed.max():.5f} px")
    assert raw.max() > 0.005
    assert fixed.max() < 1e-3


def test_shadows_on_the_tube_end_rim(frames):
    """Spheres whose shadow straddles the tube's end rim (a ~2.5 % horizontal background step):
    the local background model turns its interpolation along the step, so their row error stays
    within the noise; with the orientation fixed to vertical lines (the former vertical-closing
    model's assumption) the same frames show the 0.05-0.1 px row bias. A shadow no single model
    holds round (kept by the two-model pass, ``two_models``) is not held to the noise level but
    to its own reported sd, which carries the two models' difference."""
    errs, zs = {}, []
    for fixed in (False, True):
        st = detect.DetectionSettings(fixed_orientation_deg=0.0 if fixed else None)
        e = []
        for fr in frames["k1"]:
            det = detect.detect_spheres(fr.image, flat_field_counts=I0, expected_shape=(1024, 1024),
                                        diameter_px_range=diameter_range(0.364), settings=st)
            j, _ = match(det.centre_px, fr.truth)
            ej = det.centre_px - fr.truth.centre_px[j]
            e.append(ej[~det.two_models])
            if not fixed:
                zs.append(ej[det.two_models] / det.centre_std_px[det.two_models])
        errs[fixed] = np.vstack(e)
        print(f"vertical only={fixed}: n={len(errs[fixed])} rms col,row="
              f"{np.sqrt(np.mean(errs[fixed] ** 2, axis=0)).round(4)} max|row|={np.abs(errs[fixed][:, 1]).max():.3f}")
    z = np.vstack(zs)
    print(f"two-model shadows: {len(z)}, z {z.round(2).tolist()}")
    assert np.abs(errs[True][:, 1]).max() > 0.04          # the effect is present in these frames
    assert np.abs(errs[False][:, 1]).max() < 0.03
    assert np.sqrt(np.mean(errs[False][:, 1] ** 2)) < 0.8 * np.sqrt(np.mean(errs[True][:, 1] ** 2))
    assert np.all(np.abs(z) < 4.0)


def test_band_edge_uncertainty_is_calibrated():
    """Shadows whose edge crosses a tube-wall band edge carry the extra column uncertainty
    (background_edge_sigma_px, measured on other seeds): on fresh frames their column errors are
    explained by the reported sd, and the other shadows stay at the photon-noise level."""
    z_edge, e_other, n_all = [], [], 0
    for srd, seed in ((0.364, 21), (0.724, 22)):
        for fr in render_set(srd, seed, n=8):
            det = detect.detect_spheres(fr.image, flat_field_counts=I0, expected_shape=(1024, 1024),
                                        diameter_px_range=diameter_range(srd))
            j, _ = match(det.centre_px, fr.truth)
            e = det.centre_px - fr.truth.centre_px[j]
            on = det.on_background_edge
            z_edge.append(e[on, 0] / det.centre_std_px[on, 0])
            e_other.append(e[~on, 0])
            n_all += len(j)
    z = np.concatenate(z_edge)
    eo = np.concatenate(e_other)
    print(f"on a band edge: {z.size} of {n_all}; rms z(col) {np.sqrt(np.mean(z ** 2)):.2f}, "
          f"robust {robust_std(z):.2f}; others: col rms {np.sqrt(np.mean(eo ** 2)):.4f} px")
    assert z.size > 0.1 * n_all                     # the case is common with the tube in view
    # rms of z over > 100 shadows: 1 within its sampling error and the model's coarseness
    assert 0.7 < np.sqrt(np.mean(z ** 2)) < 1.4
    assert np.sqrt(np.mean(eo ** 2)) < 0.009
