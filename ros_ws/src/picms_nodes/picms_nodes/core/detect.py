"""Pixel Probe centroid x_j*: the image of the SMR* centre in one camera (paper section 2.3.2).

As in the paper: a semi-annular region of interest around the disc whose start and stop angles
exclude the nest (found from the image: rays along which the outer end of the annulus stays
dark are the nest), sub-pixel dark-to-light edges along radial lines every 2 deg, circle and
ellipse fits. Unlike the paper (which assumes scaled orthographic projection) the point
returned is the PROJECTED SPHERE CENTRE, not the silhouette ellipse's centre: the edge points
are undistorted with the CameraInfo intrinsics into viewing rays, and a right circular cone
(axis n, half angle alpha) is fitted to them; the sphere centre lies on the cone axis, so its
image is the axis direction mapped back through the lens. Under true perspective the ellipse
centre lies further out from the principal point than that image (0.1-0.5 px a few
millimetres off axis here, measured in the tests); `ellipse_centre_px` reports it. Targeting must
use the same point (the image of a 3-D point), which is what the cone axis gives.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .camera import Intrinsics


class DetectionError(ValueError):
    """The image does not show a usable SMR disc; the message names why."""


@dataclass(frozen=True)
class DiscDetection:
    centre_px: np.ndarray          # (2,) image of the sphere centre (cone axis), raw pixels
    cov_px: np.ndarray             # (2, 2) its covariance, px^2
    axis_normalised: np.ndarray    # (2,) cone axis in normalised undistorted coordinates
    cov_normalised: np.ndarray     # (2, 2)
    half_angle_rad: float
    ellipse_centre_px: np.ndarray  # (2,) centre of the fitted silhouette ellipse (perspective-biased)
    radius_px: float
    edges_px: np.ndarray           # (M, 2) edge points used
    excluded_deg: tuple            # (start, stop) of the excluded (nest) sector, deg, image angle
    rms_px: float                  # rms of the cone-fit residuals


def _levels(img):
    small = cv2.resize(img, (max(img.shape[1] // 8, 1), max(img.shape[0] // 8, 1)), interpolation=cv2.INTER_AREA)
    lo, hi = np.percentile(small, [1.0, 95.0])
    return small, float(lo), float(hi)


def _coarse(img):
    small, lo, hi = _levels(img)
    if hi - lo < 0.25 * max(hi, 1e-9):
        raise DetectionError(f"no disc: the image has no dark region (levels {lo:.1f} to {hi:.1f})")
    mask = (small < 0.5 * (lo + hi)).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n < 2:
        raise DetectionError("no disc: nothing darker than the background")
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    blob = (lab == k).astype(np.uint8)
    blob = np.pad(blob, 1)   # the image edge counts as outside: a cut disc is found small
    dist = cv2.distanceTransform(blob, cv2.DIST_L2, 5)
    r = float(dist.max())
    iy, ix = np.unravel_index(int(np.argmax(dist)), dist.shape)
    cx, cy = (ix - 1 + 0.5) * 8 - 0.5, (iy - 1 + 0.5) * 8 - 0.5
    R = r * 8
    if R < 20:
        raise DetectionError(f"no disc: largest dark region is {R:.0f} px in radius")
    return cx, cy, R, lo, hi


def _edges(img, cx, cy, r_in, r_out, step_deg, dr, min_contrast):
    ang = np.deg2rad(np.arange(0.0, 360.0, step_deg))
    rr = np.arange(r_in, r_out, dr)
    X = (cx + np.cos(ang)[:, None] * rr[None, :]).astype(np.float32)
    Y = (cy + np.sin(ang)[:, None] * rr[None, :]).astype(np.float32)
    h, w = img.shape
    inside = (X >= 0) & (X <= w - 1) & (Y >= 0) & (Y <= h - 1)
    prof = cv2.remap(img, X, Y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    n = rr.size
    k = max(n // 8, 3)
    dark = np.median(prof[:, :k], axis=1)
    bright = np.median(prof[:, -k:], axis=1)
    ok = (bright - dark > min_contrast) & inside.all(axis=1)
    edge_r = np.full(ang.size, np.nan)
    blur = np.full(ang.size, np.nan)
    for i in np.flatnonzero(ok):
        p = prof[i]
        mid = 0.5 * (dark[i] + bright[i])
        up = np.flatnonzero((p[:-1] < mid) & (p[1:] >= mid))
        if up.size == 0:
            ok[i] = False
            continue
        if up.size > 1:   # several crossings (noise): the steepest one
            g = p[np.minimum(up + 3, n - 1)] - p[np.maximum(up - 2, 0)]
            up = up[[int(np.argmax(g))]]
        j = int(up[0])
        edge_r[i] = rr[j] + dr * (mid - p[j]) / (p[j + 1] - p[j])
        # edge blur (Gaussian sd, px) from the slope over +-1 px at the crossing: contrast / (slope sqrt(2 pi))
        h = max(int(round(1.0 / dr)), 1)
        slope = (p[min(j + 1 + h, n - 1)] - p[max(j - h, 0)]) / (dr * (min(j + 1 + h, n - 1) - max(j - h, 0)))
        if slope > 0:
            blur[i] = (bright[i] - dark[i]) / (slope * np.sqrt(2 * np.pi))
    return ang, edge_r, ok, inside, blur


def _circle_fit(pts):
    A = np.column_stack([2 * pts, np.ones(len(pts))])
    b = (pts ** 2).sum(1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    c = sol[:2]
    return c, float(np.sqrt(sol[2] + c @ c))


def _cone_residual(params, rays):
    a, b, alpha = params
    n = np.array([a, b, 1.0]) / np.sqrt(a * a + b * b + 1.0)
    cr = np.cross(rays, n)
    return np.arctan2(np.linalg.norm(cr, axis=1), rays @ n) - alpha


def fit_cone(rays: np.ndarray, init) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton fit of a right circular cone through the origin to unit rays (M, 3).

    Returns params [a, b, alpha] (axis through (a, b, 1), half angle), their covariance
    (scale from the residuals), and the residuals (rad).
    """
    p = np.asarray(init, float).copy()
    for _ in range(20):
        r = _cone_residual(p, rays)
        J = np.empty((r.size, 3))
        for k in range(3):
            h = 1e-7 if k < 2 else 1e-9
            d = np.zeros(3)
            d[k] = h
            J[:, k] = (_cone_residual(p + d, rays) - _cone_residual(p - d, rays)) / (2 * h)
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        p += step
        if np.all(np.abs(step) < 1e-13):
            break
    r = _cone_residual(p, rays)
    dof = max(r.size - 3, 1)
    s2 = float(r @ r) / dof
    cov = s2 * np.linalg.inv(J.T @ J)
    return p, cov, r


def detect_disc(image, intr: Intrinsics, *, step_deg: float = 2.0, nest_margin_deg: float = 8.0) -> DiscDetection:
    """Find x_j*, the image of the SMR* centre, in one back-lit frame (see module doc).

    image : ndarray of shape (H, W), mono8 or mono16 (any numeric type).
    intr : the camera's CameraInfo intrinsics (K, D) used to undistort the edge points.
    Raises DetectionError naming the cause (no disc, disc cut by the image edge, too few edges).
    """
    img = np.asarray(image)
    if img.ndim != 2 or img.size == 0:
        raise DetectionError(f"image must be a 2-D mono array, got shape {img.shape}")
    if (img.shape[1], img.shape[0]) != (intr.width, intr.height):
        raise DetectionError(f"image is {img.shape[1]}x{img.shape[0]} but CameraInfo says {intr.width}x{intr.height}")
    img = img.astype(np.float32)
    cx, cy, R, lo, hi = _coarse(img)
    h, w = img.shape
    margin = 0.15 * R + 10
    if cx - R - margin < 0 or cy - R - margin < 0 or cx + R + margin > w - 1 or cy + R + margin > h - 1:
        raise DetectionError(f"disc cut by the image edge (centre ~({cx:.0f}, {cy:.0f}) px, radius ~{R:.0f} px)")
    contrast = hi - lo
    # pass 1: wide annulus from the coarse centre, circle fit
    ang, er, ok, _, _ = _edges(img, cx, cy, 0.75 * R, 1.3 * R, step_deg, 0.5, 0.5 * contrast)
    if ok.sum() < 20:
        raise DetectionError(f"too few disc edges found ({int(ok.sum())} rays)")
    pts = np.column_stack([cx + np.cos(ang[ok]) * er[ok], cy + np.sin(ang[ok]) * er[ok]])
    (cx, cy), R = _circle_fit(pts)
    # pass 2: narrow annulus; rays whose outer end stays dark are the nest: exclude them and a margin.
    # Run twice: pass 1's circle takes in part of the nest's outline and sits px off the disc's centre, towards
    # the nest; an annulus that far off-centre puts one end of each profile on the blurred edge, whose level
    # estimate (hence the mid-level crossing) is then biased, the more the wider the blur (0.23 px of centre
    # with a 4.3 px defocus blur, measured). The second pass is centred on the first pass's own circle and
    # reaches 4 blur sd beyond the edge on both sides.
    half_in, half_out = 12.0, 14.0
    for it in range(2):
        ang, er, ok, inside, blur = _edges(img, cx, cy, R - half_in, R + half_out, step_deg, 0.25, 0.5 * contrast)
        blocked = ~ok
        if blocked.any():
            m = int(np.ceil(nest_margin_deg / step_deg))
            near = np.zeros_like(blocked)
            for s in range(-m, m + 1):
                near |= np.roll(blocked, s)
            ok &= ~near
        if ok.sum() < 30:
            raise DetectionError(f"too few disc edges found ({int(ok.sum())} of {ang.size} rays usable)")
        if it == 0:
            (cx, cy), R = _circle_fit(np.column_stack([cx + np.cos(ang[ok]) * er[ok], cy + np.sin(ang[ok]) * er[ok]]))
            sd = float(np.nanmedian(blur[ok])) if np.isfinite(blur[ok]).any() else 1.0
            half_in, half_out = max(12.0, 4.0 * sd + 4.0), max(14.0, 4.0 * sd + 6.0)
    # the excluded sector (largest run of unusable rays), for the record
    bad = np.flatnonzero(~ok)
    excl = (float(np.rad2deg(ang[bad[0]])), float(np.rad2deg(ang[bad[-1]]))) if bad.size else (0.0, 0.0)
    pts = np.column_stack([cx + np.cos(ang[ok]) * er[ok], cy + np.sin(ang[ok]) * er[ok]])
    # reject gross outliers against a circle fit (robust scale)
    c, r0 = _circle_fit(pts)
    d = np.linalg.norm(pts - c, axis=1) - r0
    mad = 1.4826 * np.median(np.abs(d - np.median(d))) + 1e-3
    keep = np.abs(d - np.median(d)) < max(6 * mad, 1.0)
    pts = pts[keep]
    xn = intr.undistort(pts)
    rays = np.column_stack([xn, np.ones(len(xn))])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    c_n = intr.undistort(c.reshape(1, 2))[0]
    p, cov, res = fit_cone(rays, [c_n[0], c_n[1], r0 / intr.f_px])
    centre = intr.distort(p[:2].reshape(1, 2))[0]
    J = np.empty((2, 2))
    for k in range(2):
        dd = np.zeros(2)
        dd[k] = 1e-7
        J[:, k] = (intr.distort((p[:2] + dd).reshape(1, 2))[0] - intr.distort((p[:2] - dd).reshape(1, 2))[0]) / 2e-7
    cov_px = J @ cov[:2, :2] @ J.T
    (ex, ey), _, _ = cv2.fitEllipse(pts.astype(np.float32))
    return DiscDetection(centre, cov_px, p[:2].copy(), cov[:2, :2].copy(), float(p[2]),
                         np.array([ex, ey]), float(r0), pts, excl, float(np.sqrt(np.mean(res ** 2)) * intr.f_px))
