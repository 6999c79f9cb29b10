"""Chrome-on-glass targets (bright field) and the flange face (dark field), rendered in the
three cameras at two part poses and two blur/noise settings, measured here independently of the
renderer (mid-level sub-pixel crossings, ellipse and line fits, blob centroids) and compared with
the projection of the true geometry through the true camera model (perspective conic centres,
not projected centres)."""
import zlib
from dataclasses import replace

import cv2
import numpy as np
import pytest

from picms_nodes.core import camera, cell, render, scenes

POSES = {  # position (m), tilt rotation vector (rad), in-plane rotation (rad)
    "flat": ((0.0, 0.0, 0.0), (0.0, 0.0), 0.0),
    "tilted": ((0.0012, -0.0008, 0.0006), (0.04, -0.03), 0.4),
}
SETTINGS = {
    "clean": dict(psf_sigma_px=0.6, full_well_dn=60.0, read_noise_dn=0.8, vignetting=0.15),
    "hard": dict(psf_sigma_px=1.4, full_well_dn=15.0, read_noise_dn=3.0, vignetting=0.4),
}


@pytest.fixture(scope="module")
def cam_cell():
    return cell.make_cell(np.random.default_rng(21))


def _frames(c, part_name, pose_key, setting):
    part = scenes.make_part(part_name, *POSES[pose_key])
    phys = replace(c.physics, **SETTINGS[setting])
    rng = np.random.default_rng(zlib.crc32(f"{part_name}{pose_key}{setting}".encode()))
    imgs = [render.render_frame(cam.pose, cam.true_intrinsics, phys, rng, part=part) for cam in c.cameras]
    return part, scenes.part_truth(part), imgs


def _proj(cam, pts):
    return camera.project(cam.pose, cam.true_intrinsics, pts)


def _roi_of(uv, pad, shape):
    x0, y0 = np.floor(uv.min(0) - pad).astype(int)
    x1, y1 = np.ceil(uv.max(0) + pad).astype(int)
    return max(x0, 0), max(y0, 0), min(x1, shape[1]), min(y1, shape[0])


def _crossings(sub, t):
    """Sub-pixel points where the image crosses level t along rows and columns (linear)."""
    a = sub.astype(np.float64)
    pts = []
    for axis in (1, 0):
        i0 = a[:, :-1] if axis == 1 else a[:-1, :]
        i1 = a[:, 1:] if axis == 1 else a[1:, :]
        r, cidx = np.nonzero((i0 - t) * (i1 - t) < 0)
        f = (t - i0[r, cidx]) / (i1[r, cidx] - i0[r, cidx])
        pts.append(np.column_stack([cidx + f, r]) if axis == 1 else np.column_stack([cidx, r + f]))
    return np.vstack(pts)


def _flat(sub):
    """The ROI divided by a quadratic fitted to its bright (back-lit) pixels (flat field, which
    removes the vignetting trend), and the mid level between its dark and bright levels."""
    a = sub.astype(np.float64)
    dark, bright = np.percentile(a, [2, 98])
    # bright plateau: well above the mid level, 6 px away from any edge ramp
    mask = cv2.erode((a > dark + 0.75 * (bright - dark)).astype(np.uint8), np.ones((13, 13), np.uint8))
    yy, xx = np.nonzero(mask)
    h, w = a.shape
    basis = lambda x, y: np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
    coef = np.linalg.lstsq(basis(xx / w, yy / h), a[yy, xx], rcond=None)[0]
    gy, gx = np.mgrid[0:h, 0:w]
    norm = a / (basis(gx.ravel() / w, gy.ravel() / h) @ coef).reshape(h, w)
    dmask = cv2.erode((a < dark + 0.25 * (bright - dark)).astype(np.uint8), np.ones((5, 5), np.uint8))
    dark_n = np.median(norm[dmask > 0]) if dmask.any() else np.percentile(norm, 1)
    return norm, 0.5 * (dark_n + 1.0), bright - dark


def _rim(center_stage, radius, R, n=360):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return center_stage + radius * (np.outer(np.cos(a), R[:, 0]) + np.outer(np.sin(a), R[:, 1]))


def _ellipse_residual_rms(pts, ell):
    (cx, cy), (w, h), ang = ell
    t = np.deg2rad(ang)
    u = (pts[:, 0] - cx) * np.cos(t) + (pts[:, 1] - cy) * np.sin(t)
    v = -(pts[:, 0] - cx) * np.sin(t) + (pts[:, 1] - cy) * np.cos(t)
    rr = np.hypot(u / (w / 2), v / (h / 2))
    return float(np.sqrt(np.mean(((rr - 1) * 0.25 * (w + h)) ** 2)))


ERRORS = {"persp_offset": [], "circle_centre": [], "circle_axes": [], "square_edge": [], "dot_centre": [], "pitch": [], "ring_centre": []}


@pytest.mark.parametrize("pose_key", list(POSES))
@pytest.mark.parametrize("setting", list(SETTINGS))
def test_chrome_targets_geometry(cam_cell, pose_key, setting):
    part, truth, imgs = _frames(cam_cell, "chrome_targets", pose_key, setting)
    R = truth["R_stage_part"]
    feats = {f["id"]: f for f in truth["features"]}
    for cam, img in zip(cam_cell.cameras, imgs):
        # circles: ellipse fit to mid-level crossings vs the centre of the projected true rim
        for fid in ("c5", "c7"):
            f = feats[fid]
            rim_uv = _proj(cam, _rim(f["center_stage"], f["diameter"] / 2, R))
            x0, y0, x1, y1 = _roi_of(rim_uv, 25, img.shape)
            sub, mid, contrast = _flat(img[y0:y1, x0:x1])
            assert contrast > 100
            pts = _crossings(sub, mid) + [x0, y0]
            ell = cv2.fitEllipse(pts.astype(np.float32))
            true_ell = cv2.fitEllipse(rim_uv.astype(np.float32))
            err = np.hypot(*(np.array(ell[0]) - true_ell[0]))
            # tolerance from the noise: edge scatter (ellipse-fit residual) -> centre sd
            # sqrt(2/N) sigma_e; 5 sigma plus 0.02 px of physics the truth conic leaves out: a
            # blurred curved edge's mid-level contour shrinks by ~ sigma^2 / 2r, and sigma varies
            # with depth across an obliquely seen circle (defocus 1.5-3 px here), which moves the
            # contour's centre by ~0.01 px (measured noiseless, without vignetting or distortion)
            sd_c = _ellipse_residual_rms(pts, ell) * np.sqrt(2 / len(pts))
            assert err < 5 * sd_c + 0.02, (fid, cam.name, err, sd_c)
            ERRORS["circle_centre"].append(err)
            # axes: blur moves a curved edge's mid-level contour inward by ~ sigma^2 / (2 rho)
            # (rho: radius of curvature, smallest b^2/a at the major-axis ends); with total blur
            # sigma <= 3.5 px here (lens psf + defocus) both axes shrink by at most 2 x that
            diff = np.sort(ell[1]) - np.sort(true_ell[1])
            b, a = np.sort(true_ell[1]) / 2
            assert np.all(diff < 0.03) and np.all(diff > -2 * 3.5 ** 2 / (2 * b * b / a) - 0.03), (fid, cam.name, diff)
            ERRORS["circle_axes"].append(float(np.abs(diff).max()))
            # true perspective: the projected circle centre is not the projected centre
            off = np.hypot(*(_proj(cam, f["center_stage"])[0] - true_ell[0]))
            ERRORS["persp_offset"].append(off)
            if off > 10 * (5 * sd_c + 0.01):
                assert err < 0.2 * off
        # squares: points on each side vs the projected true side
        for fid in ("sq5", "sq7"):
            f = feats[fid]
            cs = f["corners_stage"]
            x0, y0, x1, y1 = _roi_of(_proj(cam, cs), 25, img.shape)
            sub, mid, _ = _flat(img[y0:y1, x0:x1])
            pts = _crossings(sub, mid) + [x0, y0]
            for k in range(4):
                a, b = cs[k], cs[(k + 1) % 4]
                line = _proj(cam, a + np.outer(np.linspace(0.15, 0.85, 400), b - a))
                tang = line[-1] - line[0]
                tang /= np.linalg.norm(tang)
                nrm = np.array([-tang[1], tang[0]])
                s = (pts - line[0]) @ tang
                d = (pts - line[0]) @ nrm
                ok = (s > 0) & (s < (line[-1] - line[0]) @ tang) & (np.abs(d) < 6)
                assert ok.sum() > 100, (fid, k, cam.name)
                # distance to the projected true side (a slightly curved polyline under distortion)
                dl = np.interp(s[ok], (line - line[0]) @ tang, (line - line[0]) @ nrm)
                res = d[ok] - dl
                fit = np.polyfit(s[ok], res, 1)          # line fitted to the edge points
                L = (line[-1] - line[0]) @ tang
                ends = np.abs(np.polyval(fit, [0.0, L]))
                sd_end = 2 * np.std(res - np.polyval(fit, s[ok])) / np.sqrt(ok.sum())
                assert ends.max() < 5 * sd_end + 0.02, (fid, k, cam.name, ends, sd_end)
                ERRORS["square_edge"].append(float(ends.max()))
        # dot grid: 25 dark blobs, centroids vs projected true dot centres, pitch
        g = feats["grid"]
        dots_uv = _proj(cam, g["dots_stage"])
        x0, y0, x1, y1 = _roi_of(dots_uv, 20, img.shape)
        sub = img[y0:y1, x0:x1].astype(np.float64)
        dark, bright = np.percentile(sub, [1, 99.5])
        assert bright - dark > 60
        n, lab = cv2.connectedComponents((sub < 0.5 * (dark + bright)).astype(np.uint8))
        cents = np.array([np.argwhere(lab == i).mean(0)[::-1] for i in range(1, n)])
        assert len(cents) == 25, (cam.name, len(cents))
        # darkness-weighted centroid in a disc of 0.45 x the nearest-neighbour distance, re-centred
        nn = np.sort(np.linalg.norm(cents[:, None] - cents[None], axis=2), axis=1)[:, 1]
        gy, gx = np.mgrid[0:sub.shape[0], 0:sub.shape[1]]
        bg = sub[sub > 0.5 * (dark + bright)]
        sig_i = 1.4826 * np.median(np.abs(bg - np.median(bg)))   # pixel noise (bright, upper bound)
        sd_c = np.zeros(25)
        for _ in range(4):
            for i in range(25):
                win = np.hypot(gx - cents[i, 0], gy - cents[i, 1]) < 0.45 * nn[i]
                wgt = np.clip(bright - sub[win], 0, None)
                cents[i] = [(wgt * gx[win]).sum() / wgt.sum(), (wgt * gy[win]).sum() / wgt.sum()]
                r2 = (gx[win] - cents[i, 0]) ** 2 + (gy[win] - cents[i, 1]) ** 2
                sd_c[i] = sig_i * np.sqrt(0.5 * r2.sum()) / wgt.sum()   # per-axis centroid sd
        cents = cents + [x0, y0]
        dist = np.linalg.norm(cents[:, None] - dots_uv[None], axis=2)
        match = dist.argmin(0)
        assert len(set(match.tolist())) == 25
        cerr = dist[match, np.arange(25)]
        # 5 sigma of the centroid noise (2-D) plus 0.03 px for the windowed centroid's own bias
        tol = 5 * np.sqrt(2) * sd_c.max() + 0.03
        assert cerr.max() < tol, (cam.name, cerr.max(), tol)
        ERRORS["dot_centre"].append(float(cerr.max()))
        # pitch: neighbour spacings (rows and columns) measured vs true
        m = cents[match].reshape(5, 5, 2)
        t = dots_uv.reshape(5, 5, 2)
        for ax in (0, 1):
            dm = np.linalg.norm(np.diff(m, axis=ax), axis=2)
            dt = np.linalg.norm(np.diff(t, axis=ax), axis=2)
            assert np.abs(dm - dt).max() < tol, (cam.name, np.abs(dm - dt).max(), tol)
            ERRORS["pitch"].append(float(np.abs(dm - dt).mean()))
    print({k: (round(float(np.median(v)), 4), round(float(np.max(v)), 4)) for k, v in ERRORS.items() if v})


@pytest.mark.parametrize("pose_key", list(POSES))
@pytest.mark.parametrize("setting", list(SETTINGS))
def test_flange_dark_field(cam_cell, pose_key, setting):
    part, truth, imgs = _frames(cam_cell, "flange", pose_key, setting)
    R = truth["R_stage_part"]
    band = truth["band_m"]
    for cam, img in zip(cam_cell.cameras, imgs):
        face = np.median(img)                     # the face and the background are dark
        assert face < 20
        noise = 1.4826 * np.median(np.abs(img[:200, :200] - np.median(img[:200, :200]))) + 0.5
        for f in truth["features"]:
            if f["type"] != "circle":
                continue
            # the bright ring lies on the material side: holes outside the bore, the outer edge inside
            r_mid = f["diameter"] / 2 + (band / 2 if f["hole"] else -band / 2)
            rim_uv = _proj(cam, _rim(f["center_stage"], r_mid, R))
            x0, y0, x1, y1 = _roi_of(rim_uv, 15, img.shape)
            sub = img[y0:y1, x0:x1].astype(np.float64)
            peak = np.percentile(sub, 99.5)
            assert peak > face + 15 * noise, (f["id"], cam.name, peak, face, noise)
            # centre of the projected hole: inside is dark
            if f["hole"]:
                cu = np.round(cv2.fitEllipse(rim_uv.astype(np.float32))[0]).astype(int)
                assert np.median(img[cu[1] - 3:cu[1] + 4, cu[0] - 3:cu[0] + 4]) < face + 5 * noise
            # ring pixels: above the mid level, within 8 px of the projected band centre line
            near = np.zeros(sub.shape, np.uint8)
            cv2.polylines(near, [np.round((rim_uv - [x0, y0]) * 16).astype(np.int32)], True, 1, 17, cv2.LINE_8, 4)
            yy, xx = np.nonzero((sub > 0.5 * (face + peak)) & (near > 0))
            pts = np.column_stack([xx + x0, yy + y0]).astype(np.float32)
            ell = cv2.fitEllipse(pts)
            true_ell = cv2.fitEllipse(rim_uv.astype(np.float32))
            err = np.hypot(*(np.array(ell[0]) - true_ell[0]))
            # thresholded ring pixels (not sub-pixel) -> a looser bound than bright field
            assert err < 0.15, (f["id"], cam.name, err)
            ERRORS["ring_centre"].append(err)
        # aperture band: bright along the projected band centre line, dark inside the aperture
        ap = next(f for f in truth["features"] if f["id"] == "aperture")
        sx, sy = ap["size"] + band
        c, s = np.cos(ap["rotation"]), np.sin(ap["rotation"])
        t = np.linspace(-0.4, 0.4, 40)
        loc = np.vstack([np.column_stack([t * sx, np.full_like(t, sy / 2)]), np.column_stack([t * sx, np.full_like(t, -sy / 2)]),
                         np.column_stack([np.full_like(t, sx / 2), t * sy]), np.column_stack([np.full_like(t, -sx / 2), t * sy])])
        xy = loc @ np.array([[c, s], [-s, c]]) + ap["center_part"]
        uv = _proj(cam, part.to_stage(xy))
        vals = cv2.remap(img.astype(np.float32), uv[:, 0].astype(np.float32).reshape(1, -1),
                         uv[:, 1].astype(np.float32).reshape(1, -1), cv2.INTER_LINEAR).ravel()
        assert np.percentile(vals, 10) > face + 10 * noise, (cam.name, np.percentile(vals, 10))
        cu = np.round(_proj(cam, ap["center_stage"])[0]).astype(int)
        assert np.median(img[cu[1] - 5:cu[1] + 6, cu[0] - 5:cu[0] + 6]) < face + 5 * noise
    print({k: (round(float(np.median(v)), 4), round(float(np.max(v)), 4)) for k, v in ERRORS.items() if v})


def test_truth_and_scene_selection():
    part = scenes.make_part("chrome_targets", (0.001, 0.0, 0.0), (0.0, 0.0), np.pi / 2)
    tr = scenes.part_truth(part)
    sq5 = next(f for f in tr["features"] if f["id"] == "sq5")
    # in-plane rotation by 90 deg maps part (-9, 8) mm to stage (-8, -9) mm, plus the offset
    assert np.allclose(sq5["center_stage"], [0.001 - 0.008, -0.009, 0.0], atol=1e-12)
    assert np.allclose(np.linalg.norm(np.diff(np.vstack([sq5["corners_stage"], sq5["corners_stage"][:1]]), axis=0), axis=1), 0.005)
    grid = next(f for f in tr["features"] if f["id"] == "grid")
    assert grid["dots_stage"].shape == (25, 3) and np.isclose(grid["pitch"], 5e-4)
    assert scenes.make_part("smr") is None
    with pytest.raises(ValueError, match="unknown scene"):
        scenes.make_part("teapot")
    with pytest.raises(ValueError, match="rotation"):
        scenes.PlanarPart("x", "bright_field", np.ones((3, 3)), np.zeros(3), ())



def test_still_pose_reuses_the_part_image_bit_identically():
    """The part image is remembered per (camera, pose, part): the same pose and noise seed give the same frame
    with or without the cache, a pose one encoder count away is rendered anew, and fresh noise differs."""
    from picms_nodes.core import cell, scenes
    from picms_nodes.core.render import _PART_CACHE, render_frame
    truth = cell.cell_from_seed(8)
    part = scenes.chrome_targets((1.6e-4, -1.1e-4, 0.0))
    cam = truth.cameras[1]

    def frame(q, seed):
        return render_frame(truth.camera_pose_at(1, np.asarray(q, float)), cam.true_intrinsics, truth.physics,
                            np.random.default_rng(seed), nest_axis_stage=truth.nest_axis_stage, part=part)

    _PART_CACHE.clear()
    a = frame([0, 0, 0], 5)
    b = frame([0, 0, 0], 5)                       # from the cache
    _PART_CACHE.clear()
    c = frame([6e-6, 0, 0], 5)                    # moved by one 6 um step, same noise draws
    d = frame([0, 0, 0], 6)
    assert np.array_equal(a, b)
    moved = np.abs(a.astype(int) - c.astype(int))
    assert moved.max() > 10 and np.count_nonzero(moved > 3) > 1000     # the edges moved (the noise is the same)
    assert np.count_nonzero(a != d) > 0.5 * a.size                      # fresh noise everywhere
