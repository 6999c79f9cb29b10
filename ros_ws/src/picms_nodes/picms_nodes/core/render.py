"""Rendered camera frames of the back-lit SMR* in its nest (true perspective, true distortion).

Every pixel of a region of interest is ray-cast: the pixel is undistorted with the TRUE lens
model into a viewing ray, and the ray is tested against the sphere (the silhouette is the cone
of rays tangent to the sphere, so the dark region is an ellipse whose centre is not the image
of the sphere centre off axis) and against the nest post (a cylinder below the sphere along the
nest axis; it hides part of the disc rim, as the conical nest does in the paper's Fig. 7).
Anti-aliasing uses the signed angular distance to each silhouette (box-filtered edge), then a
Gaussian blur for the lens PSF and the defocus of the sphere's depth, vignetting, shot and read
noise, and 8-bit output. Motion blur of frames taken mid-move is not modelled.

A thin wire ending in a tip (< 50 um) can be added (`Wire`), drawn the same way.

A planar part (`scenes.PlanarPart`: chrome-on-glass targets in bright field, a flange face in
dark field) is drawn by `_part_signal`: every pixel near an edge is undistorted with the TRUE
lens, its ray intersected with the part plane, and the signed distance to the edges (part
metres) turned into pixels by the local plane-to-pixel Jacobian (area-filtered edge, whose 50 %
level is the true edge; exact pixel-area coverage of the local straight edge, so that edges at
any angle are unbiased). Defocus varies over a tilted or oblique plane: the blur sd is
computed per 16 px tile from its depth and applied as a spatially varying Gaussian
(interpolation between blurs at geometrically spaced sd levels).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .camera import CameraPose, Intrinsics
from .cell import SMR_DIAMETER, Physics
from .scenes import PlanarPart

NEST_POST_RADIUS_FRACTION = 0.4    # post radius / sphere radius
NEST_POST_LENGTH_M = 0.025
_VIGNETTE_CACHE: dict = {}


@dataclass(frozen=True)
class Wire:
    """A straight wire of `radius_m` ending in a hemispherical tip centred at `tip_stage`."""
    tip_stage: np.ndarray
    direction_stage: np.ndarray      # from the tip along the wire
    radius_m: float = 20e-6
    length_m: float = 0.02


def _vignette(intr: Intrinsics, strength: float) -> np.ndarray:
    key = (intr.width, intr.height, round(float(intr.K[0, 2]), 3), round(float(intr.K[1, 2]), 3), strength)
    v = _VIGNETTE_CACHE.get(key)
    if v is None:
        if len(_VIGNETTE_CACHE) > 6:
            _VIGNETTE_CACHE.clear()
        yy, xx = np.mgrid[0:intr.height, 0:intr.width].astype(np.float32)
        r2 = (xx - intr.K[0, 2]) ** 2 + (yy - intr.K[1, 2]) ** 2
        r2max = max(intr.K[0, 2], intr.width - intr.K[0, 2]) ** 2 + max(intr.K[1, 2], intr.height - intr.K[1, 2]) ** 2
        v = (1.0 - strength * r2 / r2max).astype(np.float32)
        _VIGNETTE_CACHE[key] = v
    return v


def _roi(intr, pose, points, pad_px):
    from .camera import project
    uv = project(pose, intr, points)
    x0 = int(np.floor(uv[:, 0].min() - pad_px))
    x1 = int(np.ceil(uv[:, 0].max() + pad_px))
    y0 = int(np.floor(uv[:, 1].min() - pad_px))
    y1 = int(np.ceil(uv[:, 1].max() + pad_px))
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1, intr.width), min(y1, intr.height)
    return x0, y0, max(x1 - x0, 0), max(y1 - y0, 0)


def defocus_sigma_px(physics: Physics, depth_m: float, focus_m: float) -> float:
    """Gaussian sd (px) of the blur circle of a point at depth_m with focus at focus_m (thin lens)."""
    f = physics.focal_m
    diam = f * f / (physics.f_number * (focus_m - f)) * abs(depth_m - focus_m) / depth_m
    return diam / physics.pixel_m / 2.5


_TILE = 16


def _edge_coverage(intr: Intrinsics, x0: int, y0: int, w: int, h: int, sd_fn) -> np.ndarray:
    """Coverage (h, w) float32 of an opaque object whose signed pixel distance is sd_fn(xn, yn).

    sd_fn takes 1-D normalised undistorted coordinates and returns the signed distance to the
    silhouette in pixels (negative inside). It is evaluated exactly only in 16 px tiles near
    the silhouette (found from the tile centres); other tiles are 0 or 1.
    """
    ty, tx = (h + _TILE - 1) // _TILE, (w + _TILE - 1) // _TILE
    cx = x0 + _TILE * np.arange(tx) + (_TILE - 1) / 2
    cy = y0 + _TILE * np.arange(ty) + (_TILE - 1) / 2
    gx, gy = np.meshgrid(cx, cy)
    n = intr.undistort(np.column_stack([gx.ravel(), gy.ravel()]))
    sdc = sd_fn(n[:, 0], n[:, 1]).reshape(ty, tx)
    full = np.repeat(np.repeat((sdc < 0).astype(np.float32), _TILE, 0), _TILE, 1)
    edge = np.argwhere(np.abs(sdc) < _TILE * 0.75 + 2)
    if edge.size:
        oy, ox = np.mgrid[0:_TILE, 0:_TILE]
        px = (x0 + edge[:, 1, None, None] * _TILE + ox[None]).ravel().astype(np.float64)
        py = (y0 + edge[:, 0, None, None] * _TILE + oy[None]).ravel().astype(np.float64)
        nn = intr.undistort(np.column_stack([px, py]))
        cov = np.clip(0.5 - sd_fn(nn[:, 0], nn[:, 1]), 0.0, 1.0).astype(np.float32)
        full[(py - y0).astype(int), (px - x0).astype(int)] = cov
    return full[:h, :w]


_BASE_CACHE: dict = {}


def _base(intr: Intrinsics, physics: Physics):
    """(clean background + 0.5, noise sd) for a camera and physics, cached."""
    key = (intr.width, intr.height, float(intr.K[0, 2]), float(intr.K[1, 2]), physics.vignetting,
           physics.bright_level, physics.full_well_dn, physics.read_noise_dn)
    v = _BASE_CACHE.get(key)
    if v is None:
        if len(_BASE_CACHE) > 6:
            _BASE_CACHE.clear()
        clean = _vignette(intr, physics.vignetting) * np.float32(physics.bright_level)
        sd = np.sqrt(clean / np.float32(physics.full_well_dn) + np.float32(physics.read_noise_dn ** 2))
        v = (clean, clean + np.float32(0.5), sd)
        _BASE_CACHE[key] = v
    return v


def render_frame(pose: CameraPose, intr: Intrinsics, physics: Physics, rng, *,
                 sphere_stage=None, nest_axis_stage=(0.0, 0.0, -1.0), wire: Wire | None = None,
                 focus_m: float | None = None, sphere_diameter_m: float = SMR_DIAMETER,
                 part: PlanarPart | None = None) -> np.ndarray:
    """One mono8 frame (height, width) uint8 of the scene seen from `pose` with TRUE `intr`.

    sphere_stage : (3,) or None. The SMR centre in the stage frame (None: no sphere or nest).
    focus_m : focus distance from the perspective centre (default: the working distance).
    part : a planar part (chrome targets, flange face) fixed in the stage frame, or None.
    """
    R_sc, C = pose.R_stage_camera, pose.p_stage_centre
    focus = physics.working_distance_m if focus_m is None else focus_m
    f_px = intr.f_px
    cover = []     # (x0, y0, coverage array, blur sd)

    def line_sd(t_cam, a_cam, radius, length, clip_u):
        def fn(xn, yn):
            inv = 1.0 / np.sqrt(xn * xn + yn * yn + 1.0)
            dx, dy, dz = xn * inv, yn * inv, inv
            b = dx * a_cam[0] + dy * a_cam[1] + dz * a_cam[2]
            dd = dx * t_cam[0] + dy * t_cam[1] + dz * t_cam[2]
            ea = t_cam @ a_cam
            den = np.maximum(1.0 - b * b, 1e-12)
            u = (b * dd - ea) / den
            if clip_u:
                u = np.clip(u, 0.0, length)
            qx, qy, qz = t_cam[0] + u * a_cam[0], t_cam[1] + u * a_cam[1], t_cam[2] + u * a_cam[2]
            tr = qx * dx + qy * dy + qz * dz
            dist = np.sqrt((tr * dx - qx) ** 2 + (tr * dy - qy) ** 2 + (tr * dz - qz) ** 2)
            scale = f_px / np.maximum(tr, 1e-6)
            sd = (dist - radius) * scale
            if not clip_u:   # finite cylinder: flat ends
                sd = np.maximum(sd, np.maximum(-u, u - length) * scale)
            return sd
        return fn

    if sphere_stage is not None:
        s = np.asarray(sphere_stage, float)
        Rs = sphere_diameter_m / 2
        axis = np.asarray(nest_axis_stage, float)
        axis = axis / np.linalg.norm(axis)
        r_post = NEST_POST_RADIUS_FRACTION * Rs
        top = s + axis * np.sqrt(Rs * Rs - r_post * r_post)
        bottom = s + axis * NEST_POST_LENGTH_M
        c_cam = (s - C) @ R_sc
        if c_cam[2] <= Rs:
            raise ValueError("sphere behind or around the camera")
        depth = float(np.linalg.norm(c_cam))
        blur = float(np.hypot(physics.psf_sigma_px, defocus_sigma_px(physics, depth, focus)))
        cu = c_cam / depth
        alpha = np.arcsin(Rs / depth)

        def sphere_sd(xn, yn):
            inv = 1.0 / np.sqrt(xn * xn + yn * yn + 1.0)
            cx = (yn * cu[2] - cu[1]) * inv
            cy = (cu[0] - xn * cu[2]) * inv
            cz = (xn * cu[1] - yn * cu[0]) * inv
            ang = np.arcsin(np.minimum(np.sqrt(cx * cx + cy * cy + cz * cz), 1.0))
            front = (xn * cu[0] + yn * cu[1] + cu[2]) > 0
            return np.where(front, (ang - alpha) * f_px, 1e3)

        corners = np.array([[i, k, m] for i in (-1, 1) for k in (-1, 1) for m in (-1, 1)], float)
        x0, y0, w, h = _roi(intr, pose, s + 1.05 * Rs * corners, 4 * blur + 4)
        if w > 0 and h > 0:
            cover.append((x0, y0, _edge_coverage(intr, x0, y0, w, h, sphere_sd), blur))
        ends = [p + r_post * 1.5 * np.array(d) for p in (top, bottom) for d in [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0)]]
        x0, y0, w, h = _roi(intr, pose, np.array(ends), 4 * blur + 4)
        if w > 0 and h > 0:
            fn = line_sd((top - C) @ R_sc, axis @ R_sc, r_post, float(np.linalg.norm(bottom - top)), False)
            cover.append((x0, y0, _edge_coverage(intr, x0, y0, w, h, fn), blur))
    if wire is not None:
        tip = np.asarray(wire.tip_stage, float)
        wd = np.asarray(wire.direction_stage, float)
        wd = wd / np.linalg.norm(wd)
        end = tip + wd * wire.length_m
        depth = float(np.linalg.norm((tip - C) @ R_sc))
        blur = float(np.hypot(physics.psf_sigma_px, defocus_sigma_px(physics, depth, focus)))
        x0, y0, w, h = _roi(intr, pose, np.array([tip, end]), 4 * blur + 6)
        if w > 0 and h > 0:
            fn = line_sd((tip - C) @ R_sc, wd @ R_sc, wire.radius_m, wire.length_m, True)
            cover.append((x0, y0, _edge_coverage(intr, x0, y0, w, h, fn), blur))
    if part is not None:
        return _render_with_part(pose, intr, physics, rng, part, focus, cover)
    clean, clean_half, sd = _base(intr, physics)
    img = rng.standard_normal(clean.shape, dtype=np.float32)
    img *= sd
    img += clean_half
    if cover:
        # union of the opaque objects (max of coverages) in one box, one blur, own noise level
        bx0 = min(c[0] for c in cover)
        by0 = min(c[1] for c in cover)
        bx1 = max(c[0] + c[2].shape[1] for c in cover)
        by1 = max(c[1] + c[2].shape[0] for c in cover)
        tot = np.zeros((by1 - by0, bx1 - bx0), np.float32)
        for x0, y0, cov, _ in cover:
            h, w = cov.shape
            sub = tot[y0 - by0:y0 - by0 + h, x0 - bx0:x0 - bx0 + w]
            np.maximum(sub, cov, out=sub)
        blur = max(c[3] for c in cover)
        cb = cv2.GaussianBlur(tot, (0, 0), blur, borderType=cv2.BORDER_REPLICATE)
        contrast = np.float32(1.0 - physics.dark_level / physics.bright_level)
        roi_clean = clean[by0:by1, bx0:bx1] * (1.0 - contrast * cb)
        roi_sd = np.sqrt(roi_clean / np.float32(physics.full_well_dn) + np.float32(physics.read_noise_dn ** 2))
        img[by0:by1, bx0:bx1] = roi_clean + 0.5 + roi_sd * rng.standard_normal(roi_clean.shape, dtype=np.float32)
    np.clip(img, 0, 255.49, out=img)
    return img.astype(np.uint8)


def _plane_geometry(pose: CameraPose, part: PlanarPart):
    R_sc, C = pose.R_stage_camera, pose.p_stage_centre
    o_c = (part.p_stage_part - C) @ R_sc            # part origin in the camera frame
    A_c = R_sc.T @ part.R_stage_part                 # part axes in the camera frame (columns)
    return o_c, A_c


def _ray_plane(n, o_c, A_c):
    """Part-plane (x, y) and range (m) of the rays through normalised points n (N, 2)."""
    nc = A_c[:, 2]
    den = n[:, 0] * nc[0] + n[:, 1] * nc[1] + nc[2]
    t = (nc @ o_c) / np.where(np.abs(den) < 1e-12, 1e-12, den)
    px, py, pz = n[:, 0] * t - o_c[0], n[:, 1] * t - o_c[1], t - o_c[2]
    x = px * A_c[0, 0] + py * A_c[1, 0] + pz * A_c[2, 0]
    y = px * A_c[0, 1] + py * A_c[1, 1] + pz * A_c[2, 1]
    rng_m = t * np.sqrt(n[:, 0] ** 2 + n[:, 1] ** 2 + 1.0)
    return x, y, rng_m, t


def _area_coverage(d_px, a, b):
    """Exact area of a unit pixel on the inside (d < 0) of a straight edge at signed distance
    d_px from its centre, edge normal (a, b) = |components| (unit): the CDF of the sum of two
    uniform variables of widths a and b (the pixel square projected on the normal)."""
    a, b = np.maximum(a, b), np.maximum(np.minimum(a, b), 1e-9)
    t = -d_px
    h = 0.5 * (a + b)
    lo = np.clip(t + h, 0.0, b)                    # quadratic start
    hi = np.clip(h - t, 0.0, b)                    # quadratic end
    mid = np.clip(t, -0.5 * (a - b), 0.5 * (a - b))
    cov = np.where(t < -0.5 * (a - b), lo * lo / (2 * a * b),
                   np.where(t > 0.5 * (a - b), 1.0 - hi * hi / (2 * a * b), (mid + 0.5 * a) / a))
    return cov


def _signal(part: PlanarPart, d_px, w_px, a=1.0, b=0.0):
    """Exact pixel-area coverage of the signal region (chrome, or the material's edge band)."""
    cov = _area_coverage(d_px, a, b)
    if part.lighting == "dark_field":
        cov = cov - _area_coverage(d_px + w_px, a, b)
    return cov


_PART_CACHE: dict = {}


def _part_signal_cached(intr: Intrinsics, pose: CameraPose, part: PlanarPart, physics: Physics, focus: float):
    """_part_signal, remembered for the last few (camera, pose, part): a still stage gives the same noise-free
    part image frame after frame (the encoders are quantised), so only the noise is drawn anew. The camera
    simulator's frames then cost ~0.15 s instead of ~0.6-1 s each (three 5 MP cameras)."""
    key = (id(intr), id(part), id(physics), float(focus), np.asarray(pose.R_stage_camera, np.float64).tobytes(),
           np.asarray(pose.p_stage_centre, np.float64).tobytes())
    hit = _PART_CACHE.get(key)
    # the objects are kept with the entry, so their ids cannot be reused while it lives (all are frozen)
    if hit is not None and hit[0][0] is intr and hit[0][1] is part and hit[0][2] is physics:
        return hit[1]
    v = _part_signal(intr, pose, part, physics, focus)
    while len(_PART_CACHE) >= 6:                 # one per camera of a three-camera cell, and a margin
        _PART_CACHE.pop(next(iter(_PART_CACHE)))
    _PART_CACHE[key] = ((intr, part, physics), v)
    return v


def _part_signal(intr: Intrinsics, pose: CameraPose, part: PlanarPart, physics: Physics, focus: float):
    """(x0, y0, blurred signal (h, w) float32) of a planar part, or None when it is out of view."""
    o_c, A_c = _plane_geometry(pose, part)
    if abs(A_c[:, 2] @ o_c) < 1e-6:
        raise ValueError(f"part {part.name!r}: the camera sees the plane edge-on or sits in it")
    pts = part.to_stage(part.bound_points_part())
    if np.any(((pts - pose.p_stage_centre) @ pose.R_stage_camera)[:, 2] <= 0):
        raise ValueError(f"part {part.name!r}: partly behind the camera")
    ranges = np.linalg.norm(pts - pose.p_stage_centre, axis=1)
    pad = 4 * max(np.hypot(physics.psf_sigma_px, defocus_sigma_px(physics, r, focus)) for r in ranges) + 4
    x0, y0, w, h = _roi(intr, pose, pts, pad)
    if w <= 0 or h <= 0:
        return None
    # tile centres: plane coordinates, Jacobian (part m per px), range, signed distance in px
    ty, tx = (h + _TILE - 1) // _TILE, (w + _TILE - 1) // _TILE
    cx = x0 + _TILE * np.arange(tx) + (_TILE - 1) / 2
    cy = y0 + _TILE * np.arange(ty) + (_TILE - 1) / 2
    gx, gy = (g.ravel() for g in np.meshgrid(cx, cy))
    quad = [intr.undistort(np.column_stack([gx + du, gy + dv])) for du, dv in ((0, 0), (-.5, 0), (.5, 0), (0, -.5), (0, .5))]
    xc, yc, rc, tc = _ray_plane(quad[0], o_c, A_c)
    if np.any(tc <= 0):
        raise ValueError(f"part {part.name!r}: rays in view miss the plane (horizon in view)")
    xl, yl = _ray_plane(quad[1], o_c, A_c)[:2]
    xr, yr = _ray_plane(quad[2], o_c, A_c)[:2]
    xu, yu = _ray_plane(quad[3], o_c, A_c)[:2]
    xd, yd = _ray_plane(quad[4], o_c, A_c)[:2]
    Ju = np.column_stack([xr - xl, yr - yl])          # part m per pixel column
    Jv = np.column_stack([xd - xu, yd - yu])          # part m per pixel row

    def dist_px(x, y, ju, jv):
        # central differences (forward ones bias curved edges by the direction of the step)
        d = part.sdf(x, y)
        gu = part.sdf(x + ju[..., 0] / 2, y + ju[..., 1] / 2) - part.sdf(x - ju[..., 0] / 2, y - ju[..., 1] / 2)
        gv = part.sdf(x + jv[..., 0] / 2, y + jv[..., 1] / 2) - part.sdf(x - jv[..., 0] / 2, y - jv[..., 1] / 2)
        g = np.maximum(np.hypot(gu, gv), 1e-12)       # part m per px along the distance gradient
        return d / g, part.band_m / g, np.abs(gu) / g, np.abs(gv) / g

    # tile classification: the sdf's gradient has kinks (between dots, along diagonals), so
    # bound the pixel distance with the Jacobian's singular values instead of differencing
    sv = np.linalg.svd(np.stack([Ju, Jv], axis=2), compute_uv=False)     # (N, 2), m per px
    dm = part.sdf(xc, yc)
    dc, wc = dm / sv[:, 0], part.band_m / sv[:, 1]
    sig = _signal(part, dc, wc).reshape(ty, tx).astype(np.float32)
    lim = _TILE * 0.75 + 2
    near = (np.abs(dc) < lim) | ((part.lighting == "dark_field") & (dc > -wc - lim) & (dc < lim))
    full = np.repeat(np.repeat(sig, _TILE, 0), _TILE, 1)
    edge = np.flatnonzero(near)
    if edge.size:
        ey, ex = np.divmod(edge, tx)
        oy, ox = np.mgrid[0:_TILE, 0:_TILE]
        px = (x0 + ex[:, None, None] * _TILE + ox[None]).astype(np.float64)
        py = (y0 + ey[:, None, None] * _TILE + oy[None]).astype(np.float64)
        nn = intr.undistort(np.column_stack([px.ravel(), py.ravel()]))
        x, y = _ray_plane(nn, o_c, A_c)[:2]
        rep = _TILE * _TILE
        d, wpx, ga, gb = dist_px(x, y, np.repeat(Ju[edge], rep, 0), np.repeat(Jv[edge], rep, 0))
        full[(py.ravel() - y0).astype(int), (px.ravel() - x0).astype(int)] = _signal(part, d, wpx, ga, gb)
    full = full[:h, :w]
    # defocus by depth, per tile, as a spatially varying Gaussian
    blur_t = np.hypot(physics.psf_sigma_px, [defocus_sigma_px(physics, r, focus) for r in rc]).reshape(ty, tx)
    smin, smax = float(blur_t.min()), float(blur_t.max())
    if smax / smin < 1.03:
        return x0, y0, cv2.GaussianBlur(full, (0, 0), 0.5 * (smin + smax), borderType=cv2.BORDER_REPLICATE)
    n_lev = int(np.ceil(np.log(smax / smin) / np.log(1.25))) + 1
    levels = smin * (smax / smin) ** np.linspace(0, 1, n_lev)
    smap = cv2.resize(blur_t.astype(np.float32), (tx * _TILE, ty * _TILE), interpolation=cv2.INTER_LINEAR)[:h, :w]
    pos = np.interp(smap, levels, np.arange(n_lev)).astype(np.float32)
    out = np.zeros((h, w), np.float32)
    for k, s in enumerate(levels):
        wk = np.maximum(0.0, 1.0 - np.abs(pos - k))
        if np.any(wk > 0):
            out += wk * cv2.GaussianBlur(full, (0, 0), float(s), borderType=cv2.BORDER_REPLICATE)
    return x0, y0, out


def _render_with_part(pose, intr, physics, rng, part: PlanarPart, focus, cover):
    """Frame with a planar part (and any opaque objects in `cover` in front of it). The cached
    background (back-light, or the dark face) and its noise cover the frame; the box holding
    the part's edges and the objects is recomputed with its own levels and noise."""
    from dataclasses import replace
    if part.lighting == "bright_field":
        lo, hi = physics.dark_level, physics.bright_level
        clean, clean_half, sd = _base(intr, physics)
    else:
        lo, hi = part.face_level, part.band_level
        clean, clean_half, sd = _base(intr, replace(physics, bright_level=part.face_level))
    img = rng.standard_normal(clean.shape, dtype=np.float32)
    img *= sd
    img += clean_half
    boxes = []
    ps = _part_signal_cached(intr, pose, part, physics, focus)
    if ps is not None:
        boxes.append((ps[0], ps[1], ps[0] + ps[2].shape[1], ps[1] + ps[2].shape[0]))
    boxes += [(x0, y0, x0 + cov.shape[1], y0 + cov.shape[0]) for x0, y0, cov, _ in cover]
    if boxes:
        bx0, by0 = min(b[0] for b in boxes), min(b[1] for b in boxes)
        bx1, by1 = max(b[2] for b in boxes), max(b[3] for b in boxes)
        vig = _vignette(intr, physics.vignetting)[by0:by1, bx0:bx1]
        box = clean[by0:by1, bx0:bx1].copy()
        if ps is not None:
            x0, y0, sig = ps
            h, w = sig.shape
            if part.lighting == "bright_field":
                sig = 1.0 - sig                               # transmitted: chrome blocks
            box[y0 - by0:y0 - by0 + h, x0 - bx0:x0 - bx0 + w] = (
                vig[y0 - by0:y0 - by0 + h, x0 - bx0:x0 - bx0 + w] * (np.float32(lo) + np.float32(hi - lo) * sig))
        for x0, y0, cov, blur in cover:
            h, w = cov.shape
            cb = cv2.GaussianBlur(cov, (0, 0), blur, borderType=cv2.BORDER_REPLICATE)
            sub = box[y0 - by0:y0 - by0 + h, x0 - bx0:x0 - bx0 + w]
            sub += (np.float32(physics.dark_level) * vig[y0 - by0:y0 - by0 + h, x0 - bx0:x0 - bx0 + w] - sub) * cb
        bsd = np.sqrt(box / np.float32(physics.full_well_dn) + np.float32(physics.read_noise_dn ** 2))
        img[by0:by1, bx0:bx1] = box + 0.5 + bsd * rng.standard_normal(box.shape, dtype=np.float32)
    np.clip(img, 0, 255.49, out=img)
    return img.astype(np.uint8)
