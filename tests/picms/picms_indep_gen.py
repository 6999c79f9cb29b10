"""Independent generator of a Pixel Probe measurement record (measurement.json + crops.npz).

Written from /work/shared/INTERFACES.md (PiCMS: camera optical frames, plumb_bob CameraInfo,
stage frame with X* at encoder reading 0, picms_calibration.yaml keys, part_program.yaml) and
the documented measurement.json extras (points with their encoder reading `q`, the edge
`target` and 57 x 57 px crops per camera). It uses none of picms_nodes' renderer, cell,
scenes or instruments: its own pinhole + plumb_bob projection (undistortion by its own
fixed-point iteration), its own ray casting onto a tilted part plane, supersampled coverage,
Gaussian PSF, pixel integration, shot + read noise and 8-bit quantisation.

What it cannot produce independently: the point targets and encoder readings come from a
measurement run (part finding + drive_to). They are emulated: each target is planned from a
nominal part pose that is off the true one by tens of um and a few mrad (as part finding
would be), and the encoder reading is the stage step nearest the true edge point on the
target's plane PI (as drive_to ends within one step).
"""
from __future__ import annotations

import json
import math
import pathlib

import numpy as np
import yaml
from scipy.ndimage import gaussian_filter

CROP_HALF = 28
STEP = 6.0e-6


def _rot(axis, a):
    c, s = math.cos(a), math.sin(a)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


class Cam:
    """Pinhole + plumb_bob, pose in the stage frame relative to X* (cameras ride with X*)."""

    def __init__(self, K, D, w, h, R_sc, C):
        self.K, self.D, self.w, self.h = np.asarray(K, float), np.asarray(D, float), w, h
        self.R, self.C = np.asarray(R_sc, float), np.asarray(C, float)

    def _dist(self, x, y):
        k1, k2, p1, p2, k3 = self.D
        r2 = x * x + y * y
        f = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
        return x * f + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * f + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y

    def project(self, P, xstar):
        v = (np.atleast_2d(P) - (self.C + xstar)) @ self.R     # camera coordinates
        xd, yd = self._dist(v[:, 0] / v[:, 2], v[:, 1] / v[:, 2])
        return np.column_stack([self.K[0, 0] * xd + self.K[0, 2], self.K[1, 1] * yd + self.K[1, 2]])

    def rays(self, u, v):
        """Unit ray directions (stage frame) of pixel positions u, v (arrays)."""
        xd, yd = (u - self.K[0, 2]) / self.K[0, 0], (v - self.K[1, 2]) / self.K[1, 1]
        x, y = xd.copy(), yd.copy()
        for _ in range(30):                   # x = xd - (dist(x) - x)
            dx, dy = self._dist(x, y)
            x, y = x - (dx - xd), y - (dy - yd)
        d = np.stack([x, y, np.ones_like(x)], -1) @ self.R.T
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


def make_cameras(rng, lens="mild"):
    """Three cameras 120 deg apart, ~35 deg from the vertical, ~180 mm from X* (the paper's layout)."""
    cams = {}
    for j in range(3):
        az = math.radians(90 + 120 * j + rng.uniform(-5, 5))
        tilt = math.radians(35 + rng.uniform(-3, 3))
        dist = 0.18 + rng.uniform(-0.01, 0.01)
        C = dist * np.array([math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az), math.cos(tilt)])
        z = -C / np.linalg.norm(C)
        y = np.cross(z, [math.cos(az + 1.3), math.sin(az + 1.3), 0.0])
        y /= np.linalg.norm(y)
        x = np.cross(y, z)
        R = np.column_stack([x, y, z]) @ _rot("z", rng.uniform(-0.02, 0.02))   # roll about the axis
        f = 7250.0 * (1 + rng.uniform(-0.03, 0.03))
        fy = f if lens == "mild" else f * (1 + rng.uniform(-0.01, 0.01))     # "strong": non-square pixels
        K = [[f, 0, 640 + rng.uniform(-8, 8)], [0, fy, 512 + rng.uniform(-8, 8)], [0, 0, 1]]
        D = [rng.uniform(-0.08, 0.08), 0.0, 0.0, 0.0, 0.0] if lens == "mild" else \
            [rng.uniform(-0.3, 0.3), rng.uniform(-0.5, 0.5), rng.uniform(-2e-3, 2e-3), rng.uniform(-2e-3, 2e-3), 0.1]
        cams[f"camera_{j + 1}"] = Cam(K, D, 1280, 1024, R, C)
    return cams


PROGRAM = {
    "units": "SI", "part": "indep_targets", "lighting": "bright_field",
    "placement": {"origin_at_stage": [0.0, 0.0, 0.0], "tolerance": 0.0005, "rotation_about_normal": None},
    "features": [
        {"id": "sq5", "type": "square", "center": [-0.006, 0.005], "side": 0.005, "points_per_side": 4},
        {"id": "sq3", "type": "square", "center": [0.005, 0.005], "side": 0.003, "points_per_side": 3,
         "rotation": 0.3},
        {"id": "c5", "type": "circle", "center": [-0.006, -0.006], "diameter": 0.005, "points": 10},
        {"id": "c2", "type": "circle", "center": [0.005, -0.005], "diameter": 0.002, "points": 8},
        {"id": "face", "type": "plane"},
    ],
}


def _plan_edges(feat):
    """(xy, into_material, tangent, radius) in the part frame for one feature (own plan)."""
    c = np.asarray(feat["center"], float)
    rot = feat.get("rotation", 0.0)
    ex, ey = np.array([math.cos(rot), math.sin(rot)]), np.array([-math.sin(rot), math.cos(rot)])
    out = []
    if feat["type"] == "square":
        h, n = feat["side"] / 2, feat["points_per_side"]
        for on, al in ((ex, ey), (ey, -ex), (-ex, -ey), (-ey, ex)):
            for t in np.linspace(-0.35, 0.35, n):
                out.append((c + on * h + al * (2 * h * t), -on, al, 0.0))
    else:
        r = feat["diameter"] / 2
        for k in range(feat["points"]):
            a = rot + 2 * math.pi * k / feat["points"]
            u = np.array([math.cos(a), math.sin(a)])
            out.append((c + r * u, -u, np.array([-u[1], u[0]]), r))
    return out


def true_sizes(true_scale):
    """True sizes of the part as made (nominal x scale: the part is not the drawing)."""
    return {f["id"]: (f.get("side") or f.get("diameter")) * true_scale
            for f in PROGRAM["features"] if f["type"] != "plane"}


def _inside(feat, xy, scale):
    """Mask of part-frame points xy (..., 2) inside the TRUE feature (scaled about its centre)."""
    c = np.asarray(feat["center"], float)
    d = xy - c
    if feat["type"] == "circle":
        return np.hypot(d[..., 0], d[..., 1]) <= feat["diameter"] * scale / 2
    rot = feat.get("rotation", 0.0)
    a = d[..., 0] * math.cos(rot) + d[..., 1] * math.sin(rot)
    b = -d[..., 0] * math.sin(rot) + d[..., 1] * math.cos(rot)
    h = feat["side"] * scale / 2
    return (np.abs(a) <= h) & (np.abs(b) <= h)


def render_crop(cam, xstar, R_sp, p_sp, feats, scale, centre_px, rng, *, blur_px, bg, dark, read_sd, ss=5, bits=8):
    """57 x 57 px uint8 (uint16 when bits=16) crop around centre_px: bright back-light, dark chrome features."""
    x0 = int(round(centre_px[0])) - CROP_HALF
    y0 = int(round(centre_px[1])) - CROP_HALF
    n = 2 * CROP_HALF + 1
    pad = int(math.ceil(4 * blur_px)) + 1
    m = n + 2 * pad
    sub = (np.arange(m * ss) + 0.5) / ss - 0.5 - pad          # pixel centre at integer + 0
    u, v = np.meshgrid(x0 + sub, y0 + sub)
    d = cam.rays(u, v)
    C = cam.C + xstar
    nrm = R_sp[:, 2]
    t = ((p_sp - C) @ nrm) / (d @ nrm)
    X = C + t[..., None] * d
    xy = (X - p_sp) @ R_sp[:, :2]
    cov = np.zeros(u.shape)
    for f in feats:
        cov = np.maximum(cov, _inside(f, xy, scale))
    img = bg - (bg - dark) * cov
    img = gaussian_filter(img, blur_px * ss, mode="nearest")
    img = img.reshape(m, ss, m, ss).mean(axis=(1, 3))[pad:pad + n, pad:pad + n]
    img = rng.poisson(img * 4.0) / 4.0 + rng.normal(0, read_sd, img.shape)   # gain 4 e-/DN
    if bits == 16:
        return np.clip(np.round(img * 256), 0, 65535).astype(np.uint16), (x0, y0)
    return np.clip(np.round(img), 0, 255).astype(np.uint8), (x0, y0)


def generate(out_dir, seed, *, blur_px=None, only=None, ss=5, bits=8, lens="mild", bg=None):
    """Write measurement.json + measurement.crops.npz; return (path, truth dict).

    only: feature ids to keep (default all); ss: supersampling per pixel axis; bits: 8 (mono8)
    or 16 (mono16 crops, same light level x 256)."""
    rng = np.random.default_rng(seed)
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cams = make_cameras(rng, lens)
    blur = blur_px if blur_px is not None else rng.uniform(0.7, 1.3)
    bg_, dark, read_sd = rng.uniform(180, 230), rng.uniform(20, 50), rng.uniform(1.0, 2.5)
    bg = bg_ if bg is None else bg        # bg > 255: the back-light saturates the 8-bit frame
    # true part: tilted, rotated, offset; made 200 ppm off nominal (a true size is not the drawing)
    tilt = rng.normal(0, 0.02, 2)
    R_sp = _rot("z", rng.uniform(-0.05, 0.05)) @ _rot("y", tilt[1]) @ _rot("x", tilt[0])
    p_sp = np.array([rng.uniform(-2e-4, 2e-4), rng.uniform(-2e-4, 2e-4), rng.uniform(-1e-4, 1e-4)])
    scale = 1 + rng.uniform(-2e-4, 2e-4)
    # the pose a part finding would have given (targets are planned from it)
    R_nom = R_sp @ _rot("z", rng.normal(0, 2e-3)) @ _rot("x", rng.normal(0, 1e-3))
    p_nom = p_sp + rng.normal(0, 20e-6, 3)
    prog = dict(PROGRAM, features=[f for f in PROGRAM["features"] if only is None or f["id"] in only
                                   or f["type"] == "plane"])
    feats = [f for f in prog["features"] if f["type"] != "plane"]
    points, crops = [], {}
    for f in feats:
        for k, (xy, into, tang, r) in enumerate(_plan_edges(f)):
            P = p_nom + R_nom[:, :2] @ xy
            T = R_nom[:, :2] @ tang
            M = R_nom[:, :2] @ into
            Nn = R_nom[:, 2]
            target = {"kind": "edge", "point": P.tolist(), "tangent": T.tolist(), "into_material": M.tolist(),
                      "normal": Nn.tolist(), "lighting": "bright_field",
                      "center": (p_nom + R_nom[:, :2] @ np.asarray(f["center"])).tolist() if r else None,
                      "radius": r, "band_m": None}
            # true edge point on PI (plane through P, normal T): march along M from P on the true part
            Ptrue = _true_edge_on_plane(f, scale, R_sp, p_sp, P, T, M)
            q = np.round(Ptrue / STEP) * STEP                   # rigid, square stage: X*(q) = q
            rec = {"feature": f["id"], "kind": "edge", "index": k, "ok": True, "reason": "",
                   "p_stage": q.tolist(), "cov_stage": (np.eye(3) * 1e-12).tolist(),
                   "p_tracker": None, "cov_tracker": None, "q": q.tolist(), "pixels": {},
                   "iterations": 1, "moves": 1, "elapsed_s": 0.0, "offsets_um": [], "target": target}
            pi = len(points)
            for c, cam in cams.items():
                px = cam.project(Ptrue, q)[0]
                rec["pixels"][c] = px.tolist()
                a, xy0 = render_crop(cam, q, R_sp, p_sp, feats, scale, px, rng, blur_px=blur, bg=bg, dark=dark,
                                     read_sd=read_sd, ss=ss, bits=bits)
                crops[f"p{pi}_{c}"] = a
                crops[f"p{pi}_{c}_xy"] = np.array(xy0)
            points.append(rec)
    calib = {"units": "SI",
             "probe_point": {"pixels": {c: cam.project(np.zeros(3), np.zeros(3))[0].tolist() for c, cam in cams.items()},
                             "u_pixels": {c: [0.05, 0.05] for c in cams},
                             "p_tracker": [1.0, 0.5, 0.2], "stage_reading": [0.0, 0.0, 0.0],
                             "cov_p_tracker": (np.eye(3) * 1e-10).tolist(),
                             "p_constellation": [0.0, 0.0, -0.05],
                             "constellation": {f"smr_{i}": [0.05 * math.cos(i), 0.05 * math.sin(i), 0.0] for i in range(1, 6)}},
             "cameras": {c: {"R_stage_camera": cam.R.tolist(), "p_stage_centre": cam.C.tolist(),
                             "u_rotation_rad": [1e-5] * 3, "u_p_stage_centre": [1e-6] * 3, "reprojection_rms_px": 0.05}
                         for c, cam in cams.items()},
             "stage": {"R_tracker_stage": np.eye(3).tolist(), "squareness_rad": {"xy": 0.0, "xz": 0.0, "yz": 0.0},
                       "u_squareness_rad": {"xy": 1e-6, "xz": 1e-6, "yz": 1e-6}}}
    doc = {"part": PROGRAM["part"], "mode": "stage", "frame": "stage",
           "points": points, "program_yaml": yaml.safe_dump(prog, sort_keys=False),
           "part_finding": {"R_stage_part": R_nom.tolist(), "p_stage_part": p_nom.tolist()},
           "probe": {"calibration": calib, "camera_info": {
               c: {"K": cam.K.tolist(), "D": cam.D.tolist(), "width": cam.w, "height": cam.h} for c, cam in cams.items()}}}
    path = out / "measurement.json"
    path.write_text(json.dumps(doc))
    np.savez_compressed(out / "measurement.crops.npz", **crops)
    truth = {"sizes": {k: v for k, v in true_sizes(scale).items() if only is None or k in only}, "normal": R_sp[:, 2].tolist(), "blur_px": blur,
             "centres_stage": {f["id"]: (p_sp + R_sp[:, :2] @ np.asarray(f["center"])).tolist() for f in feats}}
    return path, truth


def _true_edge_on_plane(f, scale, R_sp, p_sp, P, T, M):
    """The true (made) edge's point on the plane through P with normal T, nearest P: bisection
    along the in-plane direction M (made orthogonal to T) within the true part plane."""
    nrm = R_sp[:, 2]
    m = M - (M @ T) * T
    m = m - (m @ nrm) * nrm          # stays in the true plane (approximately on PI: T nearly in-plane)
    m /= np.linalg.norm(m)
    # project P onto the true plane along the true normal, keeping it on PI (T . nrm ~ 0)
    w = nrm - (nrm @ T) * T
    P0 = P - ((P - p_sp) @ nrm) / (w @ nrm) * w

    def inside(s):
        xy = ((P0 + s * m) - p_sp) @ R_sp[:, :2]
        return bool(_inside(f, xy[None, :], scale)[0])
    a, b = -3e-4, 3e-4                # inside(a) False (outside the material), inside(b) True
    if inside(a) or not inside(b):
        raise RuntimeError("edge not bracketed within 0.3 mm of the target")
    for _ in range(60):
        mid = (a + b) / 2
        if inside(mid):
            b = mid
        else:
            a = mid
    return P0 + (a + b) / 2 * m


def check(out_dir, seed, **kw):
    """Generate, re-locate + fit with picms_measure_offline (in-process), compare with truth."""
    from picms_nodes import measure_offline
    path, truth = generate(out_dir, seed, **kw)
    out = pathlib.Path(out_dir) / "reloc.json"
    rc = measure_offline.main([str(path), "--out", str(out), "--relocate", "--history", "none"])
    if rc != 0:
        return {"seed": seed, "rc": rc}
    d = json.loads(out.read_text())
    feats = {f["id"]: {"err_um": (f["size"] - truth["sizes"][f["id"]]) * 1e6, "u_um": f["u_size"] * 1e6,
                       "chi2_dof": f["chi2_dof"], "n": f["n_points"]} for f in d["features"] if "size" in f}
    n = np.asarray(d["plane"]["normal"])
    ang = float(np.arccos(min(1.0, abs(n @ np.asarray(truth["normal"])))))
    return {"seed": seed, "rc": rc, "blur_px": truth["blur_px"], "features": feats, "normal_err_urad": ang * 1e6,
            "n_points": len(d["points"]), "problems": d["problems"]}


if __name__ == "__main__":
    import argparse
    import tempfile
    ap = argparse.ArgumentParser(description="independent Pixel Probe records through picms_measure_offline")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4])
    ap.add_argument("--blur", type=float, default=None, help="PSF sigma px (default: random 0.7-1.3)")
    ap.add_argument("--bits", type=int, default=8, choices=(8, 16))
    ap.add_argument("--lens", default="mild", choices=("mild", "strong"))
    ap.add_argument("--bg", type=float, default=None, help="back-light level DN (> 255 saturates)")
    a = ap.parse_args()
    res = []
    with tempfile.TemporaryDirectory() as tmp:
        for s in a.seeds:
            r = check(pathlib.Path(tmp) / f"s{s}", s, blur_px=a.blur, bits=a.bits, lens=a.lens, bg=a.bg)
            res.append(r)
            print(json.dumps(r), flush=True)
    z = [f["err_um"] / f["u_um"] for r in res for f in r.get("features", {}).values()]
    print(json.dumps({"n_sizes": len(z), "z_rms": float(np.sqrt(np.mean(np.square(z)))),
                      "max_abs_err_um": max(abs(f["err_um"]) for r in res for f in r.get("features", {}).values()),
                      "normal_err_urad": [round(r.get("normal_err_urad", -1), 1) for r in res]}))
