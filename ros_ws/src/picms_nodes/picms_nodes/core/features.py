"""Locators for part programs: edge points of straight edges and circle rims, dot centres, and
finding the part near its placement (in-plane rotation unknown).

A Locator (contract with core/targeting.py) maps a settled state and the probe to feature
pixels per camera. Those pixels must be images of ONE 3-D point, or the triangulation that
drives X* onto the feature mixes different points. Definitions used here:

- Edge point: the intersection of the edge with a plane PI fixed in the stage frame (through
  the nominal point, perpendicular to the edge: it contains the edge's in-plane normal and the
  part normal). In every view the edge is fitted along a short strip (1-D sub-pixel model
  across it, straight or with the curvature of the projected nominal rim); the fitted image
  line back-projects to a plane through the camera centre that contains the 3-D edge (tangent)
  line. Those planes (two or three) and PI give the 3-D point by weighted least squares; its
  projections are the pixels returned. Nothing here needs the part plane to be known exactly:
  the point follows from the images and the camera poses, and stays the same point when X*
  moves (PI is fixed). A second pass refits the strips centred on the point's own images.
- Edge models (pixel values against the signed distance s across the edge, toward the
  material): bright field (dark chrome on bright glass): a blurred step, I = hi + (lo - hi)
  Phi(d / sigma); dark field: a blurred band on the material side, I = base + amp (Phi(d /
  sigma) - Phi((d - w) / sigma)); d = s - e - theta u + kappa u^2 / 2 (u along the edge; the
  projected nominal rim is s = -kappa u^2 / 2). The
  edge is e: the 50 % level of the step, or the band's boundary AWAY from the material
  (doc/picms.md, Scenes). Pixels are used where they are (no interpolation along a search
  line): each pixel centre's s, u are computed in the local frame.
- Dot centre: background-normalised absorption (1 - I / bg, bg a plane fitted on a ring
  around the dot) centroid in a window, iterated; the image of the dot centre to ~0.003 px
  (a 250 um dot's conic-centre offset scales with its radius squared).

Part finding (`find_part`): every camera's image is resampled onto the nominal plane (through X*
at the placement reading, normal to stage z); the edges of that map are correlated with the
edges of the nominal layout over the in-plane rotation (all of it when unknown) and
translation; then each feature is matched locally in every camera's map, and the shift
disparity between the three views gives the feature's height (a point dz above the map plane
shifts by -dz (X - C)_xy / (X - C)_z in camera C's map). A plane through the features' 3-D
centres and a 2-D Procrustes fit give the part pose used to plan the points.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.special import ndtr

from .camera import CameraPose, Intrinsics, project


class LocateError(RuntimeError):
    """A feature could not be located (message says where and why)."""


# ----------------------------------------------------------------------------------------
# camera geometry at a stage reading, from the probe (targeting.Probe)

@dataclass(frozen=True)
class View:
    name: str
    pose: CameraPose            # at the settled reading (stage frame)
    intr: Intrinsics            # CameraInfo


def views_at(probe, q) -> dict:
    """Camera poses (stage frame) at encoder reading q (3,) from the calibrated probe.

    The cameras ride with X*: centre = p_stage_centre (relative to X*) + X*(q)."""
    xs = np.asarray(probe.xstar_stage(np.asarray(q, float)), float).reshape(3)
    out = {}
    for name, (R, C, intr) in probe_cameras(probe).items():
        out[name] = View(name, CameraPose(np.asarray(R, float), np.asarray(C, float) + xs), intr)
    return out


def probe_cameras(probe) -> dict:
    """name -> (R_stage_camera, p_stage_centre relative to X*, Intrinsics)."""
    cams = probe.cameras
    info = probe.camera_info
    out = {}
    for name, c in cams.items():
        R = getattr(c, "R_stage_camera", None)
        C = getattr(c, "p_stage_centre", None)
        if R is None and isinstance(c, dict):
            R, C = c["R_stage_camera"], c["p_stage_centre"]
        out[name] = (np.asarray(R, float), np.asarray(C, float), info[name])
    return out


# ----------------------------------------------------------------------------------------
# edges

@dataclass(frozen=True)
class EdgeTarget:
    """An edge point to find, stage frame. PI = plane through `point` with normal `tangent`."""
    point: np.ndarray           # (3,) nominal / current estimate (defines PI)
    tangent: np.ndarray         # (3,) unit, along the edge
    into_material: np.ndarray   # (3,) unit, in-plane, toward the material (chrome / face)
    normal: np.ndarray          # (3,) unit part normal
    lighting: str               # bright_field | dark_field
    center: np.ndarray | None = None   # circle rims: nominal centre (3,)
    radius: float = 0.0                # circle rims: nominal radius (m); 0 = straight
    band_m: float | None = None        # dark field: band width (m) when known (fixed in the fit)


@dataclass
class StripFit:
    ok: bool
    reason: str = ""
    e_px: float = 0.0           # edge offset along n_img from p0
    u_e_px: float = np.inf
    theta: float = 0.0
    sigma_px: float = 0.0
    width_px: float = 0.0       # dark field band width
    rms_dn: float = 0.0
    contrast_dn: float = 0.0
    n_pixels: int = 0
    p0: np.ndarray = field(default_factory=lambda: np.zeros(2))
    n_img: np.ndarray = field(default_factory=lambda: np.zeros(2))
    t_img: np.ndarray = field(default_factory=lambda: np.zeros(2))
    kappa: float = 0.0
    px_per_m: float = 0.0


def _img_dirs(view: View, P, d3, eps=2e-5):
    """Image point of P and the unit image direction (and px per m) of a small step along d3."""
    pts = np.vstack([P, P + eps * d3, P - eps * d3])
    uv = project(view.pose, view.intr, pts)
    d = (uv[1] - uv[2]) / 2
    L = float(np.hypot(*d))
    return uv[0], d / L, L / eps


def fit_strip(img, view: View, target: EdgeTarget, P, *, search_px=10.0, half_len_px=5.0,
              band_m=None) -> StripFit:
    """Sub-pixel edge across a strip centred on the image of P (3,), see module doc.
    band_m: dark-field band width (m), fixed in the fit when given (else fitted)."""
    p0, n_img, px_per_m = _img_dirs(view, P, target.into_material)
    t_img = np.array([-n_img[1], n_img[0]])
    kappa = 0.0
    if target.radius > 0 and target.center is not None:
        # curvature of the projected rim at P, in (u, s): fit s = -kappa u^2 / 2 to rim images
        rad = float(np.linalg.norm(P - target.center))            # the rim through P itself
        r_hat = (P - target.center) / max(rad, 1e-12)
        t_hat = target.tangent - (target.tangent @ r_hat) * r_hat
        t_hat /= np.linalg.norm(t_hat)
        da = np.array([-2.0, -1.0, 0.0, 1.0, 2.0]) * (4.0 / (rad * _img_dirs(view, P, t_hat)[2] + 1e-9))
        rim = target.center + rad * (np.cos(da)[:, None] * r_hat + np.sin(da)[:, None] * t_hat)
        uv = project(view.pose, view.intr, rim) - p0
        uu, ss = uv @ t_img, uv @ n_img
        coef = np.polyfit(uu, ss, 2)                                # s = c2 u^2 + c1 u + c0
        kappa = float(-2 * coef[0])
    h, w = img.shape
    R = search_px + half_len_px + 2
    x0, x1 = int(max(math.floor(p0[0] - R), 0)), int(min(math.ceil(p0[0] + R) + 1, w))
    y0, y1 = int(max(math.floor(p0[1] - R), 0)), int(min(math.ceil(p0[1] + R) + 1, h))
    if x1 - x0 < 4 or y1 - y0 < 4:
        return StripFit(False, f"{view.name}: edge image at ({p0[0]:.0f}, {p0[1]:.0f}) px is outside the frame")
    yy, xx = np.mgrid[y0:y1, x0:x1]
    dx, dy = xx - p0[0], yy - p0[1]
    s = (dx * n_img[0] + dy * n_img[1]).ravel()
    u = (dx * t_img[0] + dy * t_img[1]).ravel()
    I = img[y0:y1, x0:x1].astype(np.float64).ravel()
    m = (np.abs(u) <= half_len_px) & (np.abs(s) <= search_px)
    s, u, I = s[m], u[m], I[m]
    sc = s + kappa * u * u / 2                                   # straightened
    bins = np.arange(-search_px, search_px + 1.0)
    idx = np.clip(np.rint(sc).astype(int) + int(search_px), 0, len(bins) - 1)
    cnt = np.bincount(idx, minlength=len(bins))
    prof = np.bincount(idx, I, minlength=len(bins)) / np.maximum(cnt, 1)
    good = cnt > 0
    if good.sum() < 6:
        return StripFit(False, f"{view.name}: too few pixels in the strip")
    bright = target.lighting == "bright_field"
    lo, hi = float(prof[good].min()), float(prof[good].max())
    noise = max(1.0, float(np.std(np.diff(prof[good]))) / 2)
    if hi - lo < 6 * noise / math.sqrt(max(half_len_px, 1)) or hi - lo < 5:
        return StripFit(False, f"{view.name}: no edge within {search_px:.0f} px (contrast {hi - lo:.1f} DN)")
    if bright:
        mid = 0.5 * (lo + hi)
        # bright (glass) on the -s side, dark (chrome) on +s: crossings from above to below mid
        cand = [k for k in range(len(bins) - 1) if good[k] and good[k + 1] and prof[k] >= mid > prof[k + 1]]
        if not cand:
            return StripFit(False, f"{view.name}: no bright-to-dark crossing toward the material")
        k = min(cand, key=lambda k: abs(bins[k] + 0.5))
        f = (prof[k] - mid) / (prof[k] - prof[k + 1])
        s_c = bins[k] + f
        win = (sc > s_c - 6) & (sc < s_c + 6)
    else:
        # the band: local maxima of the profile; take the one nearest 0 that is clearly bright
        thr = lo + 0.5 * (hi - lo)
        cand = [k for k in range(1, len(bins) - 1) if good[k] and prof[k] >= thr
                and prof[k] >= prof[k - 1] and prof[k] >= prof[k + 1]]
        if not cand:
            return StripFit(False, f"{view.name}: no bright edge band")
        k = min(cand, key=lambda k: abs(bins[k]))
        s_c = bins[k] - 1.0
        win = (sc > s_c - 6) & (sc < s_c + 8)
    # saturated pixels (the frame's full scale) only say "at least this bright": left out of the
    # fit, so a clipped back-light does not pull the fitted step's mid-level (and the edge) down
    sat = np.iinfo(img.dtype).max if np.issubdtype(img.dtype, np.integer) else np.inf
    clipped = bool(np.any(I[win] >= sat))
    win &= I < sat
    s, u, I = s[win], u[win], I[win]
    if len(I) < 12:
        return StripFit(False, f"{view.name}: too few unsaturated pixels near the edge")

    def model(x):
        d = s - x[0] - x[1] * u + kappa * u * u / 2
        if bright:
            return x[4] + (x[3] - x[4]) * ndtr(d / x[2])
        wb = x[5] if band_m is None else w_fix
        return x[3] + x[4] * (ndtr(d / x[2]) - ndtr((d - wb) / x[2]))

    # level bounds in DN of an 8-bit frame, scaled up for mono16 (or any frame brighter than 8 bits:
    # the bounds must contain the levels, else every fit of a mono16 frame fails)
    g = max(1.0, hi / 250.0) * (3.0 if clipped else 1.0)   # clipped: the true level is above full scale
    if bright:
        x0_ = np.array([s_c, 0.0, 1.5, lo, hi])
        lb = [s_c - 6, -0.5, 0.25, -50 * g, -50 * g]
        ub = [s_c + 6, 0.5, 10.0, 300 * g, 300 * g]
    elif band_m is None:
        x0_ = np.array([s_c, 0.0, 1.5, lo, hi - lo, 2.5])
        lb = [s_c - 6, -0.5, 0.25, -50 * g, 0.0, 0.2]
        ub = [s_c + 6, 0.5, 10.0, 300 * g, 400 * g, 20.0]
    else:
        w_fix = band_m * px_per_m
        x0_ = np.array([s_c, 0.0, 1.5, lo, hi - lo])
        lb = [s_c - 6, -0.5, 0.25, -50 * g, 0.0]
        ub = [s_c + 6, 0.5, 10.0, 300 * g, 1000 * g]
    try:
        sol = least_squares(lambda x: model(x) - I, x0_, bounds=(lb, ub), x_scale="jac")
        if clipped:
            # dropping the saturated pixels by their observed value keeps those that noise pushed
            # below full scale (a bias toward dark near the top): keep by the fitted model's value
            # instead (3 sd below full scale), which the noise does not select, and refit
            keep = model(sol.x) < sat - 3.0 * float(np.sqrt(np.mean(sol.fun ** 2)))
            if keep.sum() < 12:
                return StripFit(False, f"{view.name}: too few pixels below saturation near the edge")
            s, u, I = s[keep], u[keep], I[keep]
            sol = least_squares(lambda x: model(x) - I, sol.x, bounds=(lb, ub), x_scale="jac")
    except (ValueError, np.linalg.LinAlgError) as e:
        return StripFit(False, f"{view.name}: edge fit failed ({e})")
    dof = max(len(I) - len(x0_), 1)
    s2 = float(np.sum(sol.fun ** 2) / dof)
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * s2
    except np.linalg.LinAlgError:
        return StripFit(False, f"{view.name}: edge fit singular")
    x = sol.x
    contrast = abs(x[3] - x[4]) if bright else x[4]
    # a blurred curved edge's 50 % contour lies sigma^2 kappa / 2 toward its centre of curvature
    e = float(x[0]) + x[2] ** 2 * kappa / 2
    fit = StripFit(True, "", e, float(np.sqrt(max(cov[0, 0], 0))), float(x[1]), float(x[2]),
                    0.0 if bright else (float(x[5]) if band_m is None else w_fix), math.sqrt(s2), float(contrast), len(I),
                    p0, n_img, t_img, kappa)
    fit.px_per_m = px_per_m
    return fit


@dataclass
class EdgePoint:
    X: np.ndarray               # (3,) stage frame
    cov: np.ndarray             # (3, 3)
    pixels: dict                # camera -> (c, r): images of X
    strips: dict                # camera -> StripFit (last pass)
    cameras_used: list
    problems: list
    band_m: float | None = None


def _edge_plane(view: View, fit: StripFit):
    """Plane (unit normal n, point C) through the camera centre and the fitted image line."""
    a = fit.p0 + fit.e_px * fit.n_img
    b = a + 3.0 * (fit.t_img + fit.theta * fit.n_img)
    xn = view.intr.undistort(np.vstack([a, b]))
    r = np.column_stack([xn, np.ones(2)])
    nc = np.cross(r[0], r[1])
    n = view.pose.R_stage_camera @ nc
    return n / np.linalg.norm(n), view.pose.p_stage_centre


def locate_edge_point(images: dict, views: dict, target: EdgeTarget, *, passes=2, search_px=10.0,
                      half_len_px=5.0) -> EdgePoint:
    """The 3-D edge point on PI (see module doc) from every camera that sees the edge (>= 2)."""
    P = np.asarray(target.point, float)
    m = target.into_material / np.linalg.norm(target.into_material)
    N = target.normal / np.linalg.norm(target.normal)
    N = N - (N @ m) * m
    N /= np.linalg.norm(N)
    B = np.column_stack([m, N])
    problems: list = []
    band_m = target.band_m
    dark = target.lighting == "dark_field"
    if dark and band_m is None:
        passes = max(passes, 2)
    for k in range(passes):
        fits, rows, rhs, wts = {}, [], [], []
        for name, view in views.items():
            if name not in images:
                continue
            fit = fit_strip(images[name], view, target, P, search_px=search_px if k == 0 else 4.0,
                            half_len_px=half_len_px, band_m=band_m)
            if not fit.ok:
                problems.append(fit.reason)
                continue
            fits[name] = fit
            n, C = _edge_plane(view, fit)
            depth = float(np.linalg.norm(P - C))
            sig = max(fit.u_e_px, 1e-3) * depth / view.intr.f_px
            # n . (P + B ab - C) = 0
            rows.append(n @ B / sig)
            rhs.append(-(n @ (P - C)) / sig)
            wts.append(sig)
        if len(rows) < 2:
            raise LocateError(f"edge seen in {len(rows)} camera(s), 2 needed: " + "; ".join(problems[-3:]))
        A, y = np.array(rows), np.array(rhs)
        ab, *_ = np.linalg.lstsq(A, y, rcond=None)
        covab = np.linalg.inv(A.T @ A)
        P = P + B @ ab
        if dark and band_m is None:
            # band width (m) from this pass's free fits, weighted by their edge uncertainty; the
            # next pass fixes it (a free width is ill-conditioned when the blur exceeds it)
            w = [(f.width_px / f.px_per_m, 1.0 / max(f.u_e_px, 0.02) ** 2) for f in fits.values() if f.u_e_px < 1.0]
            if w:
                band_m = float(np.average([a for a, _ in w], weights=[b for _, b in w]))
    cov = B @ covab @ B.T
    pixels = {name: tuple(project(v.pose, v.intr, P)[0]) for name, v in views.items() if name in fits}
    return EdgePoint(P, cov, pixels, fits, sorted(fits), problems, band_m)


def estimate_band_width(images: dict, views: dict, targets: list) -> tuple[float, float, int]:
    """Dark field: the edge band's width (m) from free fits on every target's strip in every
    view (weighted by 1 / u_e^2, ill-conditioned fits left out): (width, standard error, n).
    One feature's targets share one band (a chamfer); the edge fits then fix it."""
    vals, wts = [], []
    for t in targets:
        for name, view in views.items():
            if name in images:
                f = fit_strip(images[name], view, t, np.asarray(t.point, float))
                if f.ok and f.u_e_px < 0.5 and f.width_px > 0.3:
                    vals.append(f.width_px / f.px_per_m)
                    wts.append(1.0 / max(f.u_e_px, 0.02) ** 2)
    if len(vals) < 3:
        raise LocateError(f"dark-field band width: only {len(vals)} well-conditioned edge fits")
    v, w = np.array(vals), np.array(wts)
    med = float(np.median(v))
    keep = np.abs(v - med) < 4 * 1.4826 * np.median(np.abs(v - med)) + 1e-7
    v, w = v[keep], w[keep]
    mean = float(np.average(v, weights=w))
    se = float(np.sqrt(np.average((v - mean) ** 2, weights=w) / max(len(v) - 1, 1)))
    return mean, se, int(len(v))


# ----------------------------------------------------------------------------------------
# dots

@dataclass
class DotFix:
    pixels: dict                # camera -> (c, r) centroid
    u_px: dict                  # camera -> standard uncertainty (px)
    problems: list


def dot_centroid(img, p0, r_px, *, dark=True, iterations=6):
    """Centroid (c, r) of a dot of radius r_px near p0 and its standard uncertainty (px).

    Weights: absorption 1 - I / bg (dark dots) in a disc of radius r_px + 2.5 px about the
    current centre (iterated, so the window ends up centred on the dot and truncates its blur
    tails symmetrically); bg is the local background level (75th percentile of a window two
    dot diameters wide: the glass covers most of it). Weights are not clipped (clipping noise at
    zero would pull the centroid to the window centre)."""
    h, w = img.shape
    Rw = r_px + 2.5
    c = np.asarray(p0, float).copy()
    Rb = 4 * r_px + 4
    x0, x1 = int(max(math.floor(c[0] - Rb), 0)), int(min(math.ceil(c[0] + Rb) + 1, w))
    y0, y1 = int(max(math.floor(c[1] - Rb), 0)), int(min(math.ceil(c[1] + Rb) + 1, h))
    if x1 - x0 < 2 * Rb or y1 - y0 < 2 * Rb:
        raise LocateError(f"dot at ({c[0]:.0f}, {c[1]:.0f}) px is cut by the frame edge")
    I = img[y0:y1, x0:x1].astype(np.float64)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    bg = float(np.percentile(I, 75)) if dark else float(np.percentile(I, 25))
    if dark and bg <= 5:
        raise LocateError("dot: background too dark")
    wgt = (1.0 - I / bg) if dark else (I / bg - 1.0)
    for _ in range(iterations):
        rr = np.hypot(xx - c[0], yy - c[1])
        inside = rr <= Rw
        W = wgt[inside]
        sw = W.sum()
        if not sw > 0.3 * math.pi * r_px * r_px * 0.3:
            raise LocateError(f"dot near ({c[0]:.0f}, {c[1]:.0f}) px not found (absorption {sw:.1f} px)")
        new = np.array([(W * xx[inside]).sum() / sw, (W * yy[inside]).sum() / sw])
        step = np.hypot(*(new - c))
        c = new
        if step < 1e-4:
            break
    # uncertainty: the weights' noise (scatter of the background pixels) through the centroid sums
    bgpix = wgt[(rr > Rw + 2 * r_px) & (np.abs(wgt) < 0.3)]
    sd_w = float(np.std(bgpix)) if bgpix.size > 20 else 0.02
    u = sd_w * math.sqrt(np.sum((xx[inside] - c[0]) ** 2)) / sw
    return c, u


def locate_dot(images: dict, views: dict, centre_stage, diameter_m, *, dark=True) -> DotFix:
    pixels, us, problems = {}, {}, []
    for name, view in views.items():
        if name not in images:
            continue
        p0, _, px_per_m = _img_dirs(view, np.asarray(centre_stage, float), np.array([1.0, 0.0, 0.0]))
        try:
            c, u = dot_centroid(images[name], p0, 0.5 * diameter_m * px_per_m, dark=dark)
        except LocateError as e:
            problems.append(f"{name}: {e}")
            continue
        if np.hypot(*(c - p0)) > 0.5 * diameter_m * px_per_m + 6:
            problems.append(f"{name}: dot centroid {np.hypot(*(c - p0)):.1f} px from where expected")
            continue
        pixels[name], us[name] = (float(c[0]), float(c[1])), float(u)
    return DotFix(pixels, us, problems)


# ----------------------------------------------------------------------------------------
# part finding

@dataclass
class PartPose:
    R_stage_part: np.ndarray
    p_stage_part: np.ndarray
    rotation_rad: float               # in-plane rotation found (from stage +x to part +x)
    score: float                      # correlation peak (0..1)
    feature_heights: dict             # feature id -> height above the map plane (m)
    feature_centres_stage: dict       # feature id -> (3,)
    message: str = ""


def _layout_edges(features, res, half, angle, blur_px, offset=(0.0, 0.0)):
    """Edge map of the nominal layout rotated by `angle` (sum of every feature's own edges, so
    holes inside an outer edge count too), on a grid of `res` m over +-half."""
    n = int(round(2 * half / res)) + 1
    g = (np.arange(n) - (n - 1) / 2) * res
    X, Y = np.meshgrid(g, g)
    c, s = math.cos(-angle), math.sin(-angle)
    x = c * (X - offset[0]) - s * (Y - offset[1])
    y = s * (X - offset[0]) + c * (Y - offset[1])
    out = np.zeros(X.shape, np.float32)
    for f in features:
        out += _edges(_feature_mask(f, x, y), blur_px)
    return out


def _feature_mask(f, x, y):
    cx, cy = f.center
    ca, sa = math.cos(f.rotation), math.sin(f.rotation)
    u = ca * (x - cx) + sa * (y - cy)
    v = -sa * (x - cx) + ca * (y - cy)
    if f.type == "circle":
        return (np.hypot(u, v) <= f.size[0] / 2).astype(float)
    if f.type in ("square", "rectangle"):
        hx, hy = f.half_sizes
        return ((np.abs(u) <= hx) & (np.abs(v) <= hy)).astype(float)
    if f.type == "dot_grid":
        m = np.zeros_like(x)
        for xy in f.dots_part():
            m = np.maximum(m, (np.hypot(x - xy[0], y - xy[1]) <= f.dot_diameter / 2).astype(float))
        return m
    return np.zeros_like(x)


def _edges(a, blur_px):
    b = cv2.GaussianBlur(a.astype(np.float32), (0, 0), blur_px)
    gx = cv2.Sobel(b, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(b, cv2.CV_32F, 0, 1)
    return np.hypot(gx, gy)


def _rectify(img, view: View, origin, res, half):
    """Image resampled onto the horizontal plane through origin (3,): grid +-half, step res."""
    n = int(round(2 * half / res)) + 1
    g = (np.arange(n) - (n - 1) / 2) * res
    X, Y = np.meshgrid(g, g)
    pts = np.column_stack([X.ravel() + origin[0], Y.ravel() + origin[1], np.full(X.size, origin[2])])
    uv = project(view.pose, view.intr, pts).astype(np.float32)
    mx, my = uv[:, 0].reshape(n, n), uv[:, 1].reshape(n, n)
    out = cv2.remap(img.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=-1)
    valid = (mx >= 0) & (mx < img.shape[1] - 1) & (my >= 0) & (my < img.shape[0] - 1)
    return out, valid


def _ncc_peak(img, tpl):
    """Normalised cross-correlation (cv2.TM_CCORR_NORMED of zero-mean edges) peak with a
    sub-pixel parabola: (dx, dy) of the template's centre from the image's centre, score."""
    r = cv2.matchTemplate(img, tpl, cv2.TM_CCOEFF_NORMED)
    _, mx, _, loc = cv2.minMaxLoc(r)
    x, y = loc
    sub = [0.0, 0.0]
    for k, (a, b, c) in enumerate(((r[y, x - 1] if x > 0 else mx, mx, r[y, x + 1] if x + 1 < r.shape[1] else mx),
                                   (r[y - 1, x] if y > 0 else mx, mx, r[y + 1, x] if y + 1 < r.shape[0] else mx))):
        den = a - 2 * b + c
        sub[k] = 0.5 * (a - c) / den if den < 0 else 0.0
    cx = x + sub[0] - (r.shape[1] - 1) / 2
    cy = y + sub[1] - (r.shape[0] - 1) / 2
    return cx, cy, float(mx)


def find_part(images: dict, views: dict, program, origin_stage, *, res=80e-6, fine_res=25e-6) -> PartPose:
    """Part pose near the placement (see module doc). origin_stage (3,): X* at the placement
    reading (the nominal part origin). Uses the program's nominal features only."""
    feats = [f for f in program.features if f.type != "plane"]
    extent = max(np.hypot(*f.center) + f.radius_bound() for f in feats)
    tol = program.tolerance
    half_t = extent + 4 * res
    half_i = half_t + tol + 8 * res
    o = np.asarray(origin_stage, float)
    known = program.rotation_about_normal
    if known is None:
        schedule = [(4 * res, np.deg2rad(np.arange(0.0, 360.0, 3.0))), (res, np.deg2rad(np.linspace(-3, 3, 7))),
                    (res, np.deg2rad(np.linspace(-0.75, 0.75, 7)))]
    else:
        schedule = [(res, known + np.deg2rad(np.linspace(-3, 3, 7))), (res, np.deg2rad(np.linspace(-1, 1, 9)))]
    maps_at, base_at = {}, {}

    def score_angles(r, angles):
        if r not in maps_at:
            mp = {}
            for name, v in views.items():
                if name in images:
                    m, valid = _rectify(images[name], v, o, r, half_i)
                    if valid.mean() > 0.95:
                        mp[name] = _edges(m, 2.0 if r > res else 1.0)
            if not mp:
                raise LocateError("part finding: the part area is not fully in view of any camera")
            maps_at[r] = mp
            base_at[r] = _layout_edges(feats, r, half_t, 0.0, 2.0 if r > res else 1.0)
        base = base_at[r]
        ctr = ((base.shape[1] - 1) / 2, (base.shape[0] - 1) / 2)
        out = []
        for a in angles:
            M = cv2.getRotationMatrix2D(ctr, -math.degrees(a), 1.0)   # rows are +y: negative angle
            tpl = cv2.warpAffine(base, M, (base.shape[1], base.shape[0]), flags=cv2.INTER_LINEAR)
            sc = [_ncc_peak(e, tpl) for e in maps_at[r].values()]
            out.append((float(np.mean([x[2] for x in sc])), float(a), float(np.median([x[0] for x in sc])),
                        float(np.median([x[1] for x in sc]))))
        return out

    # coarse pass; the three best separated local maxima are refined (a partial program of a
    # plate can look alike at more than one rotation at the coarse scale)
    r0, a0 = schedule[0]
    coarse = score_angles(r0, a0)
    order = sorted(range(len(coarse)), key=lambda i: -coarse[i][0])
    seeds = []
    for i in order:
        if all(abs(math.remainder(coarse[i][1] - coarse[j][1], 2 * math.pi)) > math.radians(10) for j in seeds):
            seeds.append(i)
        if len(seeds) == (5 if len(a0) > 10 else 1):
            break
    best = (-2.0, 0.0, 0.0, 0.0)
    for i in seeds:
        cand = coarse[i]
        for r, angles in schedule[1:]:
            cand = max(score_angles(r, cand[1] + angles))
        if cand[0] > best[0]:
            best = cand
    res = schedule[-1][0]
    # a layout symmetric under a rotation (the flange: 180 deg) cannot be told apart in the
    # images: take the equivalent rotation nearest the placement's (or 0), so ids are stable
    base = _layout_edges(feats, schedule[-1][0], half_t, 0.0, 1.0)
    ctr = ((base.shape[1] - 1) / 2, (base.shape[0] - 1) / 2)
    ref = 0.0 if known is None else known
    sym = [0.0]
    for n in (2, 3, 4, 6):
        a = 2 * math.pi / n
        rot = cv2.warpAffine(base, cv2.getRotationMatrix2D(ctr, -math.degrees(a), 1.0), base.shape[::-1])
        if float(np.sum(rot * base) / np.sqrt(np.sum(rot * rot) * np.sum(base * base))) > 0.97:
            sym += [k * a for k in range(1, n)]
    if len(sym) > 1:
        cands = [best[1] + a for a in sym]
        pick = min(cands, key=lambda a: abs(math.remainder(a - ref, 2 * math.pi)))
        best = (best[0], pick, best[2], best[3])
    score, ang, dx, dy = best
    if score < 0.2:
        raise LocateError(f"part finding: the nominal layout does not match the images (score {score:.2f})")
    off = np.array([dx, dy]) * res
    # per feature: fine local match in each camera's map -> (dx, dy, dz)
    heights, centres = {}, {}
    c_a, s_a = math.cos(ang), math.sin(ang)
    R2 = np.array([[c_a, -s_a], [s_a, c_a]])
    for f in feats:
        cen = R2 @ np.asarray(f.center) + off
        ft = _replace_center(f, (0.0, 0.0), f.rotation)
        half_f = f.radius_bound() + 10 * fine_res
        tpl = _layout_edges([ft], fine_res, half_f, ang, 1.5)
        rows, rhs = [], []
        for name, v in views.items():
            if name not in images:
                continue
            oc = np.array([o[0] + cen[0], o[1] + cen[1], o[2]])
            m, valid = _rectify(images[name], v, oc, fine_res, half_f + 0.3e-3)
            if valid.mean() < 0.98:
                continue
            dx_f, dy_f, s = _ncc_peak(_edges(m, 1.5), tpl)
            if s < 0.3:
                continue
            d = oc - v.pose.p_stage_centre
            g = -d[:2] / d[2]
            rows += [[1, 0, g[0]], [0, 1, g[1]]]
            rhs += [dx_f * fine_res, dy_f * fine_res]
        if len(rows) >= 4:
            sol, *_ = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)
            centres[f.id] = np.array([o[0] + cen[0] + sol[0], o[1] + cen[1] + sol[1], o[2] + sol[2]])
            heights[f.id] = float(sol[2])
    # pose: plane through the feature centres (>= 3) and 2-D Procrustes in it
    ids = list(centres)
    # a dot grid repeats: its local match can be off by a pitch in one view (a wrong height);
    # leave grids out of the pose when two other features were placed
    solid = [i for i in ids if feats_by_id(feats)[i].type != "dot_grid"]
    if len(solid) >= 2:
        ids = solid
    nominal = np.array([feats_by_id(feats)[i].center for i in ids]) if ids else np.zeros((0, 2))
    meas = np.array([centres[i] for i in ids]) if ids else np.zeros((0, 3))
    normal = np.array([0.0, 0.0, 1.0])
    if len(ids) >= 2:
        # heights z = a x + b y + c; minimum-norm tilt when the centres are (nearly) collinear
        # (only the tilt along their line is then known)
        cm = meas.mean(0)
        A = np.column_stack([(meas[:, :2] - cm[:2]) / 0.01, np.ones(len(ids))])
        sol, *_ = np.linalg.lstsq(A, meas[:, 2] - cm[2], rcond=0.15)
        normal = np.array([-sol[0] / 0.01, -sol[1] / 0.01, 1.0])
        normal /= np.linalg.norm(normal)
    if len(ids) >= 2:
        a = nominal - nominal.mean(0)
        e1 = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(normal, e1)
        b3 = meas - meas.mean(0)
        b = np.column_stack([b3 @ e1, b3 @ e2])
        H = a.T @ b
        ang = float(np.arctan2(H[0, 1] - H[1, 0], H[0, 0] + H[1, 1]))
        ca, sa = math.cos(ang), math.sin(ang)
        ex = ca * e1 + sa * e2
        R = np.column_stack([ex, np.cross(normal, ex), normal])
        p = meas.mean(0) - R[:, :2] @ nominal.mean(0)
    else:
        R = np.array([[c_a, -s_a, 0.0], [s_a, c_a, 0.0], [0.0, 0.0, 1.0]])
        p = o + np.array([off[0], off[1], 0.0])
        if ids:
            p = centres[ids[0]] - R[:, :2] @ nominal[0]
    return PartPose(R, p, float(ang), score, heights, centres,
                    f"rotation {math.degrees(ang):.2f} deg, score {score:.2f}, {len(ids)} features placed")


def feats_by_id(feats):
    return {f.id: f for f in feats}


def _replace_center(f, center, rotation):
    from dataclasses import replace
    return replace(f, center=tuple(center), rotation=rotation)
