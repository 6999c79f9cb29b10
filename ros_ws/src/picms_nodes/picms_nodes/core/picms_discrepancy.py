"""Pixel Probe adapter for the sim-to-real discrepancy engine (issue 11, Pixel Probe part).

The cell-agnostic engine lives in ct_calib_nodes.core.discrepancy (numpy/scipy only; picms_nodes
already depends on ct_calib_nodes, so it is imported from there rather than moved). This adapter
turns a Pixel Probe CalibrationResult (its ``design``: target points U in the probe-body frame,
the cameras' normalised disc observations and covariances, and the solved poses) into the
engine's Dataset: residuals in pixels per camera, station and image axis; the Jacobian of the
nominal parameters (three camera poses, six each, and the three stage squareness angles); the
locate axes (station order = time, position on each sensor) and a catalogue of camera-side
physical terms, each a linearised basis d(pixel)/d(theta).

Scope (honest): the terms act on the disc-centre (camera) residuals only. Tracker-side terms
(length scale, SMR centring, angular encoder) need the tracker-link residuals and are not in
this catalogue yet. The refit is the engine's linear joint fit (one Gauss-Newton step from the
nominal estimate), adequate for the small terms here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ct_calib_nodes.core.discrepancy import BIC_THRESHOLD, Candidate, Dataset, analyse

from .calibrate import CalibrationResult, _skew, travel_matrix


@dataclass(frozen=True)
class PicmsTerm:
    id: str
    name: str
    mechanism: str
    per_camera: tuple          # parameter names per camera
    units: tuple
    display_unit: str
    reveal_by: str
    basis: object              # (ctx, j) -> (n_j, 2, p) d pixel / d theta for camera j
    plausible_max: float = np.inf


def _b_k1(c, j):
    x, y = c["n"][j].T
    r2 = x * x + y * y
    return c["f"][j] * np.stack([x * r2, y * r2], 1)[:, :, None]


def _b_k2(c, j):
    x, y = c["n"][j].T
    r4 = (x * x + y * y) ** 2
    return c["f"][j] * np.stack([x * r4, y * r4], 1)[:, :, None]


def _b_tangential(c, j):
    x, y = c["n"][j].T
    r2 = x * x + y * y
    b1 = np.stack([2 * x * y, r2 + 2 * y * y], 1)
    b2 = np.stack([r2 + 2 * x * x, 2 * x * y], 1)
    return c["f"][j] * np.stack([b1, b2], 2)


def _b_pp(c, j):
    # CameraInfo's centre off by e px: the undistorted observation moves by -inv(d distort / d n) e / f,
    # a pure shift (absorbed by the camera rotation) when D = 0, a field-dependent one otherwise
    return -np.linalg.inv(c["jdist"][j])


def _b_focal(c, j):
    return c["f"][j] * c["n"][j][:, :, None]


def _b_aspect(c, j):
    b = np.zeros((len(c["n"][j]), 2, 1))
    b[:, 0, 0] = c["f"][j] * c["n"][j][:, 0]
    return b


def _b_rot_drift(c, j):
    # rotation of camera j growing linearly over the session (rad per session)
    return c["t"][j][:, None, None] * c["jrot"][j]


def _b_pos_drift(c, j):
    return c["t"][j][:, None, None] * c["jpos"][j]


def _b_skew(c, j):
    b = np.zeros((len(c["n"][j]), 2, 1))
    b[:, 0, 0] = c["f"][j] * c["n"][j][:, 1]
    return b


def _distort_n(D, n):
    k1, k2, p1, p2, k3 = D
    x, y = n[:, 0], n[:, 1]
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return np.column_stack([x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                            y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y])


def _distort_jacobian(D, n, h=1e-7):
    """(m, 2, 2) d distorted / d undistorted normalised coordinates under CameraInfo's D."""
    out = np.zeros((len(n), 2, 2))
    for k in range(2):
        e = np.zeros(2)
        e[k] = h
        out[:, :, k] = (_distort_n(D, n + e) - _distort_n(D, n - e)) / (2 * h)
    return out


CATALOGUE = (
    PicmsTerm("lens_radial_k1", "lens radial distortion (k1) missing from CameraInfo",
              "the lens bends rays radially by k1 r^2 of the normalised radius; CameraInfo D says 0",
              ("k1",), ("1",), "1 (rms over cameras)",
              "a disc pattern spanning the field (wider stage travel), or a lab distortion calibration",
              _b_k1, 5.0),
    PicmsTerm("lens_radial_k2", "lens radial distortion (k2, 4th order)",
              "fourth-order radial term k2 r^4 of the lens distortion",
              ("k2",), ("1",), "1 (rms over cameras)", "features near the edge of the field", _b_k2, 500.0),
    PicmsTerm("lens_tangential", "lens decentring (tangential) distortion",
              "lens elements decentred: p1, p2 plumb_bob terms", ("p1", "p2"), ("1", "1"),
              "1 (rms over cameras)", "features over the whole field", _b_tangential, 0.05),
    PicmsTerm("principal_point_error", "principal-point error in CameraInfo",
              "cx, cy of the camera matrix are off: every image point shifts by the same pixels",
              ("dcx", "dcy"), ("px", "px"), "px (rms)",
              "a camera intrinsic calibration; in this cell it is absorbed by the camera rotation",
              _b_pp, 200.0),
    PicmsTerm("focal_length_error", "focal-length (image scale) error",
              "the camera's focal length differs from CameraInfo: image coordinates scale about the centre",
              ("df_rel",), ("1",), "1 (rms over cameras)",
              "a change of working distance or a scale bar in the field", _b_focal, 0.1),
    PicmsTerm("pixel_aspect_error", "pixel aspect-ratio error",
              "fx and fy differ from CameraInfo by different amounts", ("dfx_rel",), ("1",),
              "1 (rms over cameras)", "features spread horizontally across the field", _b_aspect, 0.05),
    PicmsTerm("sensor_skew", "sensor axis skew", "sensor columns not perpendicular to rows",
              ("skew",), ("1",), "1 (rms over cameras)", "features spread vertically across the field",
              _b_skew, 0.05),
    PicmsTerm("camera_rotation_drift", "camera pose thermal drift (rotation)",
              "the camera mount rotates steadily as it warms during the session",
              ("wx", "wy", "wz"), ("rad", "rad", "rad"), "urad over the session (rms over cameras)",
              "a longer session, or repeat stations at its start and end", _b_rot_drift, 1e-2),
    PicmsTerm("camera_position_drift", "camera pose thermal drift (position)",
              "the camera centre moves steadily as the mount expands during the session",
              ("vx", "vy", "vz"), ("m", "m", "m"), "um over the session (rms over cameras)",
              "a longer session, or repeat stations at its start and end", _b_pos_drift, 1e-3),
)
MIN_STATIONS = 15
CATALOGUE_BY_ID = {t.id: t for t in CATALOGUE}
DISPLAY = {"lens_radial_k1": 1.0, "lens_radial_k2": 1.0, "lens_tangential": 1.0, "principal_point_error": 1.0,
           "focal_length_error": 1.0, "pixel_aspect_error": 1.0, "sensor_skew": 1.0,
           "camera_rotation_drift": 1e6, "camera_position_drift": 1e6}


def build(result: CalibrationResult, camera_info: dict, n_folds: int = 5):
    """Dataset, candidates and context arrays from a calibration. Raises ValueError on an unusable one."""
    d = result.design
    if not d or "obs" not in d:
        raise ValueError("calibration carries no pose-fit design (U, obs): nothing to analyse")
    U, obs, cov = np.asarray(d["U"]), np.asarray(d["obs"]), np.asarray(d["obs_cov"])
    cams = list(d["cameras"])
    sq = np.asarray(d["sq"], float)
    A = travel_matrix(sq)
    dq = -U @ np.linalg.inv(A).T                  # U = -(dq A^T)
    N = U.shape[0]
    dA = []
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1e-7
        dA.append(-(dq @ ((travel_matrix(sq + e) - travel_matrix(sq - e)) / 2e-7).T))   # (N, 3)
    if N < MIN_STATIONS:
        raise ValueError(f"{N} settled stations: too few for a discrepancy verdict (the noise floor and the "
                         f"held-out folds need >= {MIN_STATIONS}; 6 pose parameters per camera leave too few "
                         "degrees of freedom); record the grid acquisition (grid_pattern(), 33 stations)")
    n_pose = 6 * len(cams)
    p0 = n_pose + 3
    rows_r, rows_j, sig, comp, grp, cam_of, st_of = [], [], [], [], [], [], []
    ctx = {"jdist": [], "n": [], "f": [], "t": [], "jrot": [], "jpos": [], "idx": []}
    tnorm = np.linspace(-0.5, 0.5, N) if N > 1 else np.zeros(1)
    row = 0
    for j, c in enumerate(cams):
        cr = result.cameras[c]
        R, C = np.asarray(cr.R_stage_camera), np.asarray(cr.p_stage_centre)
        f = float(camera_info[c].f_px)
        ok = np.where(np.isfinite(obs[j, :, 0]))[0]
        pc = (U[ok] - C) @ R
        n = pc[:, :2] / pc[:, 2:3]
        jr, jp = np.zeros((len(ok), 2, 3)), np.zeros((len(ok), 2, 3))
        for m, i in enumerate(ok):
            x, y, z = pc[m]
            P = np.array([[1 / z, 0, -x / z ** 2], [0, 1 / z, -y / z ** 2]])
            jr[m] = f * P @ _skew(pc[m])
            jp[m] = -f * P @ R.T
            Jrow = np.zeros((2, p0))
            Jrow[:, 6 * j:6 * j + 3] = jr[m]
            Jrow[:, 6 * j + 3:6 * j + 6] = jp[m]
            for k in range(3):
                Jrow[:, n_pose + k] = f * P @ R.T @ dA[k][i]
            r = f * (obs[j, i] - n[m])
            s = f * np.sqrt(np.diag(cov[j, i]))
            for a in range(2):
                rows_r.append(r[a])
                rows_j.append(Jrow[a])
                sig.append(s[a])
                comp.append(a)
                grp.append(i)
                cam_of.append(j)
                st_of.append(i)
        ctx["n"].append(n)
        ctx["jdist"].append(_distort_jacobian(np.asarray(camera_info[c].D, float), n))
        ctx["f"].append(f)
        ctx["t"].append(tnorm[ok])
        ctx["jrot"].append(jr)
        ctx["jpos"].append(jp)
        ctx["idx"].append(np.arange(row, row + 2 * len(ok)).reshape(-1, 2))
        row += 2 * len(ok)
    residual = np.array(rows_r)
    nn = residual.size
    if nn < 2 * p0:
        raise ValueError(f"{nn} residuals for {p0} nominal parameters: too few stations to analyse")
    cam_of, st_of, comp = np.array(cam_of), np.array(st_of), np.array(comp)
    # neighbours: same camera and axis, consecutive stations
    pairs = []
    for j in range(len(cams)):
        for a in range(2):
            ii = np.where((cam_of == j) & (comp == a))[0]
            pairs += list(zip(ii[:-1], ii[1:]))
    fold = (st_of * n_folds) // max(N, 1)
    # locate axes: time (station order) per camera, sensor field per camera
    emp_t = np.zeros((nn, 3 * len(cams) * 2))
    emp_f = np.zeros((nn, 5 * len(cams) * 2))
    for j in range(len(cams)):
        n = ctx["n"][j]
        nx = n / max(np.abs(n).max(), 1e-12)
        t = ctx["t"][j]
        for a in range(2):
            rr = ctx["idx"][j][:, a]
            for k, v in enumerate((t, t ** 2, t ** 3)):
                emp_t[rr, (j * 2 + a) * 3 + k] = v
            for k, v in enumerate((nx[:, 0] ** 2, nx[:, 0] * nx[:, 1], nx[:, 1] ** 2,
                                   nx[:, 0] * (nx ** 2).sum(1), nx[:, 1] * (nx ** 2).sum(1))):
                emp_f[rr, (j * 2 + a) * 5 + k] = v
    ds = Dataset(residual=residual, jac=np.array(rows_j),
                 nominal_names=tuple(f"{c}.{p}" for c in cams for p in ("rx", "ry", "rz", "cx", "cy", "cz"))
                 + ("squareness_xy", "squareness_xz", "squareness_yz"),
                 sigma=np.array(sig), component=comp, group=np.array(grp), neighbours=np.array(pairs, int),
                 fold=fold, empirical={"station order (time)": emp_t, "sensor field": emp_f}, unit="px")
    cands = []
    for t in CATALOGUE:
        p = len(t.per_camera)
        B = np.zeros((nn, p * len(cams)))
        for j in range(len(cams)):
            b = t.basis(ctx, j)                      # (m, 2, p)
            for a in range(2):
                B[ctx["idx"][j][:, a], j * p:(j + 1) * p] = b[:, a, :]
        scale = np.full(p * len(cams), DISPLAY[t.id])
        nc = len(cams)
        mag = (lambda th, s=DISPLAY[t.id], nc=nc: float(np.sqrt(np.sum((np.asarray(th) * s) ** 2) / nc)))
        cands.append(Candidate(id=t.id, name=t.name, mechanism=t.mechanism,
                               param_names=tuple(f"{c}.{q}" for c in cams for q in t.per_camera),
                               param_units=tuple(u for _ in cams for u in t.units), basis=B,
                               magnitude_unit=t.display_unit, display_scale=scale, reveal_by=t.reveal_by,
                               magnitude=mag, plausible_max=t.plausible_max * DISPLAY[t.id]))
    return ds, cands, {"cameras": cams, "n_stations": N, "cam_of": cam_of, "station_of": st_of, "comp": comp}


def run(result: CalibrationResult, camera_info: dict, *, progress=None, max_terms: int = 3) -> dict:
    """The Pixel Probe analysis; the discrepancy.json dict (same keys as CT) plus ``_arrays``."""
    say = progress or (lambda _m: None)
    ds, cands, ext = build(result, camera_info)
    say(f"{ds.residual.size} disc-centre residuals ({len(ext['cameras'])} cameras, {ext['n_stations']} stations); "
        f"{len(cands)} catalogue terms")
    res = analyse(ds, cands, max_terms=max_terms, progress=say)
    by_id = {c.id: c for c in cands}
    findings = []
    for f in res["findings"]:
        c = by_id[f["term"]]
        th, ct = np.asarray(f["theta"]), np.asarray(f["theta_cov"])
        u = np.sqrt(np.maximum(np.diag(ct), 0))
        mag = c.mag(th)
        g = np.zeros_like(th)
        if mag > 0:
            g = (th * c.display_scale ** 2) / (len(ext["cameras"]) * mag)
        mag_u = float(np.sqrt(max(g @ ct @ g, 0.0)))
        sep = {c.reveal_by} | {by_id[d].reveal_by for d in f["degenerate_with"]}
        findings.append({
            "term": c.id, "name": c.name, "mechanism": c.mechanism,
            "significance_sigma": f["significance_sigma"], "delta_bic": f["delta_bic"], "cv_gain": f["cv_gain"],
            "magnitude": mag, "magnitude_u": mag_u, "magnitude_unit": c.magnitude_unit,
            "parameters": [{"name": n, "value": float(v), "u": float(uu), "unit": un}
                           for n, v, uu, un in zip(c.param_names, th, u, c.param_units)],
            "degenerate_with": list(f["degenerate_with"]),
            "correlated_with_calibrated": f["correlated_nominal"],
            "separate_by": sorted(sep) if (f["degenerate_with"] or f["correlated_nominal"]) else [],
        })
    limits = {}
    for c in cands:
        lim = res["limits"][c.id]
        if lim["absorbed_fraction"] > 0.999 or not np.isfinite(lim["limit"]):
            limits[c.id] = {"limit": None, "unit": c.magnitude_unit, "reveal_by": c.reveal_by,
                            "cannot_see": "absorbed by the calibrated camera poses in this acquisition"}
        else:
            # the engine's limit is on the parameter vector's smallest-eigen direction (display units);
            # our magnitude is an rms over cameras
            limits[c.id] = {"limit": lim["limit"] / np.sqrt(len(ext["cameras"])), "unit": c.magnitude_unit,
                            "reveal_by": c.reveal_by, "absorbed_fraction": lim["absorbed_fraction"]}
    unexplained = [{"axis": e["axis"], "significance_sigma": e["significance_sigma"], "delta_bic": e["delta_bic"],
                    "amplitude_rms_px": e["amplitude_rms"], "amplitude_max_px": e["amplitude_max"],
                    "absorbed_by": f"empirical:{e['axis']}"} for e in res["unexplained"]]
    adequate = not findings and not unexplained
    fl = res["floor"]
    floor_d = fl.to_dict("px")
    floor_d["stated_sigma_median_px"] = fl.sigma_median
    sd = fl.factor * fl.sigma_median

    def fmt(v, unit):
        return "not observable" if v is None or not np.isfinite(v) else f"{v:.3g} {unit.split(' ')[0]}"
    if adequate:
        verdict = (f"No significant discrepancy: the nominal model explains the {ds.residual.size // 2} disc centres "
                   f"down to the noise floor ({sd[0]:.3g} / {sd[1]:.3g} px in u / v); e.g. no lens k1 above "
                   f"{fmt(limits['lens_radial_k1']['limit'], '1')} and no camera rotation drift above "
                   f"{fmt(limits['camera_rotation_drift']['limit'], 'urad')} urad over the session.")
    elif findings:
        f0 = findings[0]
        alt = (f" (or, indistinguishable here, {', '.join(by_id[d].name for d in f0['degenerate_with'])})"
               if f0["degenerate_with"] else "")
        verdict = (f"The nominal model leaves out {f0['name']}{alt}: {f0['magnitude']:.3g} {f0['magnitude_unit']} "
                   f"at {f0['significance_sigma']:.1f} sigma; with it the held-out residual falls from "
                   f"{res['before']['held_out_rms']:.4g} to {res['after']['held_out_rms']:.4g} px "
                   f"(noise floor {sd[0]:.3g} px).")
        if len(findings) > 1:
            verdict += " Also: " + "; ".join(f"{f['name']} ({f['magnitude']:.3g} {f['magnitude_unit']})"
                                             for f in findings[1:]) + "."
        if unexplained:
            verdict += f" Structure along {unexplained[0]['axis']} remains unexplained."
    else:
        e = unexplained[0]
        verdict = (f"Structure beyond the noise floor along {e['axis']} ({e['significance_sigma']:.1f} sigma, "
                   f"{e['amplitude_rms_px']:.3g} px rms) that no catalogue term explains; absorbed only by an "
                   f"empirical term, physics unknown.")
    xr = np.hstack([ds.jac] + [by_id[i].basis for i in res["chosen"]])
    r_after = ds.residual - xr @ res["beta"]
    return {
        "verdict": verdict, "adequate": bool(adequate), "noise_floor": floor_d,
        "fit_before": res["before"], "fit_after": res["after"], "findings": findings, "unexplained": unexplained,
        "located": [dict(e) for e in res["located"]], "detection_limits": limits,
        "catalogue": [{"id": t.id, "name": t.name, "mechanism": t.mechanism,
                       "parameters": list(t.per_camera), "units": list(t.units), "per": "camera",
                       "magnitude_unit": t.display_unit, "reveal_by": t.reveal_by} for t in CATALOGUE],
        "n_observations": int(ds.residual.size // 2), "n_stations": ext["n_stations"],
        "bic_threshold": BIC_THRESHOLD,
        "_arrays": {"residual_before": ds.residual, "residual_after": r_after, "station": ext["station_of"],
                    "camera": ext["cam_of"], "comp": ext["comp"]},
    }


def grid_pattern(n_xy: int = 4, n_z: int = 2, half_xy_m: float = 0.006, half_z_m: float = 0.004) -> np.ndarray:
    """A denser discrepancy acquisition: an n_xy x n_xy x n_z grid of stage positions, in serpentine order
    (consecutive stations are spatial neighbours, so their residual differences cancel smooth structure)."""
    xs = np.linspace(-half_xy_m, half_xy_m, n_xy)
    zs = np.linspace(-half_z_m, half_z_m, n_z) if n_z > 1 else np.zeros(1)
    pts = [np.zeros(3)]
    for kz, z in enumerate(zs):
        for ky, y in enumerate(xs if kz % 2 == 0 else xs[::-1]):
            row = xs if (ky + kz * n_xy) % 2 == 0 else xs[::-1]
            for x in row:
                pts.append(np.array([x, y, z]))
    return np.array(pts)
