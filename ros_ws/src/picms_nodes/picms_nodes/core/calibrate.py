"""Pixel Probe calibration (paper section 2.3) and extrinsic calibration (Appendix A).

Input is only what INTERFACES.md gives: frames, CameraInfo intrinsics, stage joint_states,
tracker readings with their own stamps, picms_cell.yaml. Steps:

1. Settled periods from joint_states (`settled_windows`): frames and tracker readings taken
   while the stage moves or rings are not used.
2. Per station and camera: the disc centre (cone axis, `detect.detect_disc`) averaged over the
   station's frames; per station and SMR: the mean tracker reading. The tracker's per-axis
   noise is estimated from the pooled within-station scatter of all readings.
3. Link (section 2.3.3): at the reference station (the first), X* = the SMR* centre; the
   constellation frame (origin at the constellation centroid, principal axes) holds X* and the
   SMR centres. At every station a weighted rigid fit (Kabsch) maps the reference
   constellation onto the station's, which gives X* in the tracker frame there, and the SMR*
   (fixed in the nest) in probe-body coordinates: U_i = R_i^T (S* - t_i) - S*.
4. Stage axes: X*(station) = p0 + M q (generalised least squares over stations); the columns
   of M are the travels seen by the tracker; the stage frame and the squareness follow.
5. Cameras (Appendix A.2): the three poses from U_i and the image observations, by one joint
   Gauss-Newton / generalised least squares whose covariance holds the pixel noise AND the
   tracker noise of U (shared by the cameras, hence joint); started from OpenCV solvePnP
   (iterative) per camera, whose own answer is kept for comparison.

All covariances are propagated linearly (numerical Jacobians where the map is small); the
cross-correlations that enter through shared inputs (reference constellation, S*) are kept.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .camera import Intrinsics, matrix_to_rotvec, rotvec_to_matrix
from .detect import DetectionError, DiscDetection


#: camera fit chi2/dof at or above which a calibration is POOR_FIT: published so, stored so in the history,
#: and written to the calibration file plant software reads neither by the node nor by the offline tool
POOR_FIT_CHI2 = 4.0


def is_poor_fit(res) -> bool:
    """True when the calibration's own camera fit says its model does not explain the data."""
    return float(res.chi2_dof) >= POOR_FIT_CHI2


class CalibrationError(ValueError):
    """The data cannot give a calibration; the message names the cause."""


# ---------------------------------------------------------------- settled periods
@dataclass(frozen=True)
class Window:
    start_ns: int
    end_ns: int
    q: np.ndarray           # (3,) mean encoder reading, m


def settled_windows(stamps_ns, positions, *, tol_m: float = 5e-7, hold_s: float = 0.3,
                    min_s: float = 0.6) -> list[Window]:
    """Periods where every encoder stays within `tol_m` of its running value.

    A window opens `hold_s` after the readings stopped changing and must last `min_s`
    (including the hold). stamps_ns (N,), positions (N, 3), any order (sorted here).
    """
    t = np.asarray(stamps_ns, dtype=np.int64)
    q = np.asarray(positions, dtype=np.float64)
    if t.ndim != 1 or q.shape != (t.size, 3):
        raise ValueError(f"joint_states: stamps (N,) and positions (N, 3) expected, got {t.shape}, {q.shape}")
    if t.size < 3:
        return []
    o = np.argsort(t, kind="stable")
    t, q = t[o], q[o]
    out = []
    i0 = 0
    n = t.size
    for i in range(1, n + 1):
        if i < n and np.all(np.abs(q[i] - q[i0]) <= tol_m):
            continue
        # run i0 .. i-1 is still
        t0, t1 = t[i0], t[i - 1]
        if (t1 - t0) * 1e-9 >= min_s:
            out.append(Window(int(t0 + hold_s * 1e9), int(t1), q[i0:i].mean(0)))
        i0 = i
    return out


def in_window(stamp_ns: int, windows: list[Window]) -> int:
    """Index of the window holding stamp_ns, or -1."""
    for k, w in enumerate(windows):
        if w.start_ns <= stamp_ns <= w.end_ns:
            return k
    return -1


# ---------------------------------------------------------------- rigid fit
def kabsch(A, B, w=None):
    """R, t minimising sum w |R a + t - b|^2; A, B (n, 3), w (n,)."""
    A = np.asarray(A, float)
    B = np.asarray(B, float)
    w = np.ones(len(A)) if w is None else np.asarray(w, float)
    w = w / w.sum()
    ca, cb = w @ A, w @ B
    H = (A - ca).T @ ((B - cb) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1, 1, d]) @ U.T
    return R, cb - R @ ca


def _num_jac(f, x, h):
    y0 = f(x)
    J = np.empty((y0.size, x.size))
    for k in range(x.size):
        d = np.zeros_like(x)
        d[k] = h
        J[:, k] = (f(x + d) - f(x - d)) / (2 * h)
    return y0, J


def constellation_frame(points):
    """(R_tracker_const, origin) of the constellation frame: centroid, principal axes, right-handed.

    points (n, 3). Raises CalibrationError for fewer than 3 points or collinear points.
    """
    P = np.asarray(points, float)
    if P.shape[0] < 3:
        raise CalibrationError(f"fewer than 3 constellation SMRs measured ({P.shape[0]}): the probe frame is undefined")
    c = P.mean(0)
    U, s, Vt = np.linalg.svd(P - c)
    if s[1] < 1e-3 * np.sqrt(P.shape[0]):
        raise CalibrationError(f"constellation SMRs are collinear (spread across the line {s[1] / np.sqrt(P.shape[0]) * 1e3:.3f} mm): the probe frame is undefined")
    R = Vt.T.copy()
    # deterministic signs: x toward the first SMR, z right-handed
    if (P[0] - c) @ R[:, 0] < 0:
        R[:, 0] *= -1
    if (P[1] - c) @ R[:, 1] < 0:
        R[:, 1] *= -1
    R[:, 2] = np.cross(R[:, 0], R[:, 1])
    return R, c


# ---------------------------------------------------------------- results
@dataclass(frozen=True)
class CameraResult:
    name: str
    R_stage_camera: np.ndarray
    p_stage_centre: np.ndarray
    u_rotation_rad: np.ndarray
    u_p_stage_centre: np.ndarray
    reprojection_rms_px: float
    pnp_R_stage_camera: np.ndarray     # OpenCV solvePnP (iterative) answer on the same data
    pnp_p_stage_centre: np.ndarray


@dataclass(frozen=True)
class CalibrationResult:
    success: bool
    message: str
    pixels: dict                 # camera -> (2,) x_j*
    u_pixels: dict               # camera -> (2,)
    p_tracker: np.ndarray        # X* in the tracker frame at stage_reading
    cov_p_tracker: np.ndarray
    stage_reading: np.ndarray
    p_constellation: np.ndarray
    cov_p_constellation: np.ndarray
    constellation: dict          # name -> (3,) in the constellation frame
    cameras: dict                # name -> CameraResult
    R_tracker_stage: np.ndarray
    p_tracker_stage: np.ndarray  # X* at encoder reading 0, tracker frame
    travel_matrix: np.ndarray    # M (3, 3): tracker displacement per encoder metre, tracker frame
    squareness_rad: dict
    u_squareness_rad: dict
    scale_ppm: np.ndarray        # |M e_k| - 1 per axis (tracker vs encoder length), ppm
    u_scale_ppm: np.ndarray
    tracker_sigma_m: float       # estimated per-axis reading noise
    rigid_fit_rms_m: float       # rms residual of the constellation rigid fits
    chi2_dof: float              # camera GLS chi^2 / dof
    n_stations: int
    notes: tuple = ()
    camera_cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # joint (18 + 3) incl. squareness
    design: dict = field(default_factory=dict)   # the pose fit's inputs: U (N, 3), obs (J, N, 2), obs_cov, cameras


# ---------------------------------------------------------------- station data
@dataclass
class Station:
    window: Window
    detections: dict = field(default_factory=dict)   # camera -> list[DiscDetection]
    readings: dict = field(default_factory=dict)     # smr -> list[(3,)]


def tracker_shortfall(counts: dict, cell: dict) -> list:
    """What a station's tracker readings (``counts``: SMR name -> number of readings) lack for the
    calibration to use the station: at least one reading of the probe SMR and two of each of at least
    3 constellation SMRs (the probe frame). Empty when the station is usable."""
    tr = cell.get("tracker", {})
    star = tr.get("probe_smr", "smr_star")
    n_const = sum(counts.get(c, 0) >= 2 for c in tr.get("constellation", []))
    out = []
    if n_const < 3:
        out.append(f"{n_const} constellation SMR(s) read twice (3 needed)")
    if counts.get(star, 0) < 1:
        out.append(f"no reading of the probe SMR {star}")
    return out


def assign(windows, frames_detected, tracker):
    """Stations from windows, detections [(stamp_ns, camera, DiscDetection)], readings [(stamp_ns, name, p)]."""
    st = [Station(w) for w in windows]
    for stamp, cam, det in frames_detected:
        k = in_window(stamp, windows)
        if k >= 0:
            st[k].detections.setdefault(cam, []).append(det)
    for stamp, name, p in tracker:
        k = in_window(stamp, windows)
        if k >= 0:
            st[k].readings.setdefault(name, []).append(np.asarray(p, float))
    return st


def _mean_detection(dets: list[DiscDetection]):
    covs = np.array([d.cov_normalised for d in dets])
    W = np.linalg.inv(covs).sum(0)
    cov = np.linalg.inv(W)
    m = cov @ np.einsum("kij,kj->i", np.linalg.inv(covs), np.array([d.axis_normalised for d in dets]))
    return m, cov


def _project_n(R, C, U):
    pc = (U - C) @ R
    return pc[:, :2] / pc[:, 2:3], pc


def _skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def travel_matrix(sq) -> np.ndarray:
    """Unit travel directions (columns) in the stage frame from squareness [xy, xz, yz] (rad).

    Each angle is the included angle of the pair of travels minus 90 deg (INTERFACES.md).
    x is the stage x axis; y lies in the stage xy plane (the frame's definition).
    """
    sxy, sxz, syz = sq
    ax = np.array([1.0, 0.0, 0.0])
    ay = np.array([-np.sin(sxy), np.cos(sxy), 0.0])
    azx = -np.sin(sxz)
    azy = (-np.sin(syz) - ay[0] * azx) / ay[1]
    az = np.array([azx, azy, np.sqrt(max(1.0 - azx * azx - azy * azy, 0.0))])
    return np.column_stack([ax, ay, az])


def solve_cameras(U_fn, n_extra, extra0, cov_U, obs, obs_cov, init, prior=None, max_iter: int = 30):
    """Joint Gauss-Newton / GLS of the camera poses (and shared extra parameters).

    U_fn(extra) -> (N, 3): the target point in the probe-body frame at each station.
    cov_U (3N, 3N): covariance of U (its noise is shared by the cameras: joint weighting).
    obs (J, N, 2) normalised observations (NaN = missing); obs_cov (J, N, 2, 2).
    init: list of (R_frame_camera, C). prior: (value (k,), cov (k, k)) on the extras or None.
    Parameters per camera: small rotation in the camera frame (R <- R exp([d]x)), centre C.
    Returns (poses, extra, cov (6J + k, 6J + k), residuals (J, N, 2), chi2, dof).
    """
    J_, N = obs.shape[:2]
    poses = [(np.array(R, float), np.array(C, float)) for R, C in init]
    extra = np.array(extra0, float)
    mask = np.isfinite(obs[..., 0])
    rows = [(j, i) for i in range(N) for j in range(J_) if mask[j, i]]
    m = len(rows)
    npar = 6 * J_ + n_extra
    converged = False
    for it in range(max_iter):
        U = U_fn(extra)
        if n_extra:
            _, dU = _num_jac(lambda e: U_fn(e).ravel(), extra, 1e-8)
        r = np.zeros(2 * m)
        Jp = np.zeros((2 * m, npar))
        Ju = np.zeros((2 * m, 3 * N))
        S = np.zeros((2 * m, 2 * m))
        for k, (j, i) in enumerate(rows):
            R, C = poses[j]
            n, pc = _project_n(R, C, U[i:i + 1])
            x, y, z = pc[0]
            P = np.array([[1 / z, 0, -x / z ** 2], [0, 1 / z, -y / z ** 2]])
            r[2 * k:2 * k + 2] = obs[j, i] - n[0]
            Jp[2 * k:2 * k + 2, 6 * j:6 * j + 3] = P @ _skew(pc[0])
            Jp[2 * k:2 * k + 2, 6 * j + 3:6 * j + 6] = -P @ R.T
            Ju[2 * k:2 * k + 2, 3 * i:3 * i + 3] = P @ R.T
            S[2 * k:2 * k + 2, 2 * k:2 * k + 2] = obs_cov[j, i]
        if n_extra:
            Jp[:, 6 * J_:] = Ju @ dU
        S = S + Ju @ cov_U @ Ju.T
        L = np.linalg.cholesky(S)
        Jw = np.linalg.solve(L, Jp)
        rw = np.linalg.solve(L, r)
        if prior is not None:
            pv, pc_ = prior
            Lp = np.linalg.cholesky(np.linalg.inv(pc_))
            Jpr = np.zeros((n_extra, npar))
            Jpr[:, 6 * J_:] = Lp.T
            Jw = np.vstack([Jw, Jpr])
            rw = np.concatenate([rw, Lp.T @ (pv - extra)])
        N_ = Jw.T @ Jw
        try:
            d = np.linalg.solve(N_, Jw.T @ rw)
        except np.linalg.LinAlgError:
            raise CalibrationError("camera pose fit is singular: the stations do not determine the poses") from None
        for j in range(J_):
            R, C = poses[j]
            poses[j] = (R @ rotvec_to_matrix(d[6 * j:6 * j + 3]), C + d[6 * j + 3:6 * j + 6])
        extra = extra + d[6 * J_:]
        if np.max(np.abs(d)) < 1e-12:
            converged = True
            break
    if not converged and np.max(np.abs(d)) > 1e-9:
        raise CalibrationError(f"camera pose fit did not converge in {max_iter} iterations (last step {np.max(np.abs(d)):.1e})")
    cov = np.linalg.inv(N_)
    res = np.full((J_, N, 2), np.nan)
    for k, (j, i) in enumerate(rows):
        res[j, i] = r[2 * k:2 * k + 2]
    chi2 = float(rw @ rw)
    return poses, extra, cov, res, chi2, 2 * m - 6 * J_


def solvepnp_pose(U, n):
    """OpenCV solvePnP on normalised points; returns (R_frame_camera, C).

    Started by SOLVEPNP_SQPNP (global, any N >= 3; the DLT start of the iterative method is
    unreliable with 6-7 points of a 12 mm pattern seen from 180 mm), then refined by
    SOLVEPNP_ITERATIVE (Levenberg-Marquardt on the unweighted reprojection error).
    """
    obj = np.ascontiguousarray(U, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(n, dtype=np.float64).reshape(-1, 1, 2)
    if len(obj) < 4:
        raise CalibrationError(f"pose needs at least 4 stations seen by the camera, got {len(obj)}")
    if not (np.all(np.isfinite(obj)) and np.all(np.isfinite(img))):
        raise CalibrationError("pose: station positions or image points are not finite")
    try:     # degenerate input (stations on a line, readings far off) trips OpenCV's own assertions
        ok, rvec, tvec = cv2.solvePnP(obj, img, np.eye(3), None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            raise CalibrationError("solvePnP (SQPnP start) failed")
        ok, rvec, tvec = cv2.solvePnP(obj, img, np.eye(3), None, rvec, tvec, useExtrinsicGuess=True,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
    except cv2.error as exc:
        why = str(exc).strip().splitlines()[-1][:160]
        raise CalibrationError(f"camera pose not solvable from the {len(obj)} stations seen (degenerate stage "
                               f"positions or image points): OpenCV: {why}") from None
    if not ok:
        raise CalibrationError("solvePnP (iterative) failed")
    Rcw = cv2.Rodrigues(rvec)[0]
    return Rcw.T, -Rcw.T @ tvec.ravel()


def calibrate(stations: list[Station], camera_info: dict, cell: dict) -> CalibrationResult:
    """The calibration from assembled stations (see module doc). Raises CalibrationError."""
    notes = []
    tr = cell.get("tracker", {})
    const_names = list(tr.get("constellation", []))
    star = tr.get("probe_smr", "smr_star")
    cams = sorted(camera_info)
    if not stations:
        raise CalibrationError("the stage never settled: no period without motion in joint_states")
    if len(cams) < 2:
        raise CalibrationError(f"CameraInfo missing: intrinsics for {cams} only (need the cameras' K and D)")
    # usable stations: SMR*, >= 3 constellation SMRs
    good = [s for s in stations if not tracker_shortfall({k: len(v) for k, v in s.readings.items()}, cell)]
    if not good:
        have = sorted({k for s in stations for k in s.readings})
        n_c = max((sum(len(s.readings.get(c, [])) >= 2 for c in const_names) for s in stations), default=0)
        if n_c < 3:
            raise CalibrationError(f"fewer than 3 constellation SMRs measured at any settled station ({n_c}; "
                                   f"readings seen: {have}): the probe frame is undefined")
        raise CalibrationError(f"no settled station with a reading of the probe SMR {star!r} "
                               f"(readings seen: {have})")
    ref = good[0]
    if ref is not stations[0]:
        # X* is where the SMR* sat at the reference station: a first station without the tracker's
        # readings moves it to this station's reading (self-consistent, but not the X* intended)
        notes.append(f"the first settled station (reading {np.round(stations[0].window.q * 1e3, 3).tolist()} mm) "
                     "lacks the probe SMR or >= 3 constellation SMRs: X* is defined at the reading "
                     f"{np.round(ref.window.q * 1e3, 3).tolist()} mm instead")
    if not all(c in ref.detections for c in cams):
        missing = [c for c in cams if c not in ref.detections]
        raise CalibrationError(f"no usable disc image at the reference station from {missing}")
    names = [c for c in const_names if all(len(s.readings.get(c, [])) >= 2 for s in good)]
    if len(names) < 3:
        raise CalibrationError(f"fewer than 3 constellation SMRs measured at every station ({names})")
    # tracker noise from pooled within-station scatter
    ss, dof = 0.0, 0
    for s in good:
        for k, v in s.readings.items():
            a = np.array(v)
            if len(a) >= 2:
                ss += float(((a - a.mean(0)) ** 2).sum())
                dof += 3 * (len(a) - 1)
    sigma = np.sqrt(ss / dof)
    N = len(good)
    nc = len(names)
    means = np.array([[np.mean(s.readings[c], axis=0) for c in names] for s in good])   # (N, nc, 3)
    counts = np.array([[len(s.readings[c]) for c in names] for s in good])
    star_all = np.concatenate([np.array(s.readings[star]) for s in good if star in s.readings])
    S_star = star_all.mean(0)
    var_in = np.concatenate([np.repeat(sigma ** 2 / counts.ravel(), 3), np.full(3, sigma ** 2 / len(star_all))])
    constellation_frame(means[0])      # raises for collinear points

    def derived(x):
        mm = x[:-3].reshape(N, nc, 3)
        Sx = x[-3:]
        U, X, W = [], [], []
        for i in range(N):
            R, t = kabsch(mm[0], mm[i])
            U.append(R.T @ (Sx - t) - Sx)
            X.append(R @ Sx + t)
            W.append(matrix_to_rotvec(R))
        return np.concatenate([np.ravel(U), np.ravel(X), np.ravel(W)])

    x0 = np.concatenate([means.ravel(), S_star])
    y, Jd = _num_jac(derived, x0, 1e-6)
    cov_y = (Jd * var_in) @ Jd.T
    U_T = y[:3 * N].reshape(N, 3)
    X_T = y[3 * N:6 * N].reshape(N, 3)
    cov_U = cov_y[:3 * N, :3 * N]
    cov_X = cov_y[3 * N:6 * N, 3 * N:6 * N]
    W_T = y[6 * N:].reshape(N, 3)           # constellation rotation (tracker frame) since the reference
    cov_W = cov_y[6 * N:, 6 * N:]
    res = []
    for i in range(N):
        R, t = kabsch(means[0], means[i])
        res.append(means[0] @ R.T + t - means[i])
    rigid_rms = float(np.sqrt(np.mean(np.square(res))))
    # stage: X_T,i = p0 + M q_i (GLS)
    q = np.array([s.window.q for s in good])
    if np.linalg.matrix_rank(q - q.mean(0), tol=1e-4) < 3:
        raise CalibrationError("the stations do not span the three stage axes: travels unobservable")
    A = np.zeros((3 * N, 12))
    for i in range(N):
        for a in range(3):
            A[3 * i + a, a] = 1.0
            A[3 * i + a, 3 + 3 * a:6 + 3 * a] = q[i]
    Wx = np.linalg.inv(cov_X + 1e-30 * np.eye(3 * N))
    Ncx = A.T @ Wx @ A
    cov_b = np.linalg.inv(Ncx)
    b = cov_b @ A.T @ Wx @ X_T.ravel()
    p0, M = b[:3], b[3:].reshape(3, 3)

    def stage_fn(bv):
        Mv = bv[3:].reshape(3, 3)
        x = Mv[:, 0] / np.linalg.norm(Mv[:, 0])
        z = np.cross(Mv[:, 0], Mv[:, 1])
        z /= np.linalg.norm(z)
        yv = np.cross(z, x)
        R = np.column_stack([x, yv, z])
        ang = []
        for i, k in ((0, 1), (0, 2), (1, 2)):
            c = Mv[:, i] @ Mv[:, k] / np.linalg.norm(Mv[:, i]) / np.linalg.norm(Mv[:, k])
            ang.append(np.arccos(np.clip(c, -1, 1)) - np.pi / 2)
        sc = (np.linalg.norm(Mv, axis=0) - 1.0) * 1e6
        return R, np.array(ang), sc

    R_ts, ang, sc = stage_fn(b)
    _, Jang = _num_jac(lambda bv: np.concatenate([stage_fn(bv)[1], stage_fn(bv)[2],
                                                  matrix_to_rotvec(R_ts.T @ stage_fn(bv)[0])]), b, 1e-7)
    cov_der = Jang @ cov_b @ Jang.T
    u_ang = np.sqrt(np.diag(cov_der)[:3])
    u_sc = np.sqrt(np.diag(cov_der)[3:6])
    cov_rts = cov_der[6:9, 6:9]         # small rotation of the stage frame, in its own axes
    # cameras
    obs = np.full((len(cams), N, 2), np.nan)
    obs_cov = np.tile(np.eye(2), (len(cams), N, 1, 1))
    # one frame's silhouette edge points (raw px) per camera and station: the discrepancy engine's lens
    # terms model how a distortion missing from CameraInfo moves the cone fitted to them (not just a point)
    edges = [[None] * N for _ in cams]
    for j, c in enumerate(cams):
        for i, s in enumerate(good):
            dets = s.detections.get(c)
            if dets:
                m, cv = _mean_detection(dets)
                obs[j, i], obs_cov[j, i] = m, cv
                e = getattr(dets[0], "edges_px", None)
                edges[j][i] = None if e is None else np.asarray(e, float)
    for j, c in enumerate(cams):
        if np.isfinite(obs[j, :, 0]).sum() < 6:
            raise CalibrationError(f"{c}: disc seen at {int(np.isfinite(obs[j, :, 0]).sum())} settled stations; "
                                   "the pose needs at least 6")
    # Target points in the probe-body frame, stage axes: the SMR* is fixed, so relative to
    # X* it sits at -(travel between the reference and station i) = -A(squareness) (q_i - q_ref).
    # The encoders give the travel (steps are exact to the encoder resolution); the squareness
    # angles are shared unknowns, constrained by the tracker's estimate (prior) and by the
    # images; the tracker-linked alternative (U from the rigid fits) is kept for comparison.
    dq = q - q[0]
    enc_var = (1e-7) ** 2 / 12 + (float(cell.get("stage", {}).get("encoder_noise", 0.0)) ** 2)
    cov_Uq = np.eye(3 * N) * enc_var

    def U_fn(e):
        return -(dq @ travel_matrix(e).T)

    pnp = []
    for j in range(len(cams)):
        ok = np.isfinite(obs[j, :, 0])
        pnp.append(solvepnp_pose(U_fn(ang)[ok], obs[j, ok]))
    prior = (ang, cov_der[:3, :3])
    poses, sq_est, cov_cam, resid, chi2, dof = solve_cameras(U_fn, 3, ang, cov_Uq, obs, obs_cov, pnp, prior)
    cov_sq = cov_cam[-3:, -3:]
    # OpenCV solvePnP (iterative, unweighted reprojection error) per camera on the same final
    # target points, for comparison with the joint GLS
    pnp = []
    for j in range(len(cams)):
        ok = np.isfinite(obs[j, :, 0])
        pnp.append(solvepnp_pose(U_fn(sq_est)[ok], obs[j, ok]))
    cam_results = {}
    for j, c in enumerate(cams):
        Rs, Cs = poses[j]
        cr = cov_cam[6 * j:6 * j + 3, 6 * j:6 * j + 3]
        cc = cov_cam[6 * j + 3:6 * j + 6, 6 * j + 3:6 * j + 6]
        cov_rot = Rs @ cr @ Rs.T
        f = camera_info[c].f_px
        rr = resid[j][np.isfinite(resid[j, :, 0])]
        cam_results[c] = CameraResult(c, Rs, Cs, np.sqrt(np.diag(cov_rot)), np.sqrt(np.diag(cc)),
                                      float(np.sqrt(np.mean(rr ** 2)) * f), pnp[j][0], pnp[j][1])
    ang = sq_est
    u_ang = np.sqrt(np.diag(cov_sq))
    # x_j*: the reference station's disc centre in raw pixels
    pixels, u_pixels = {}, {}
    for j, c in enumerate(cams):
        intr: Intrinsics = camera_info[c]
        n0, cv0 = obs[j, 0], obs_cov[j, 0]
        px = intr.distort(n0.reshape(1, 2))[0]
        Jn = np.empty((2, 2))
        for k in range(2):
            d = np.zeros(2)
            d[k] = 1e-7
            Jn[:, k] = (intr.distort((n0 + d).reshape(1, 2))[0] - intr.distort((n0 - d).reshape(1, 2))[0]) / 2e-7
        pixels[c] = px
        u_pixels[c] = np.sqrt(np.diag(Jn @ cv0 @ Jn.T))
    # X* in the constellation frame (reference station)
    def to_const(x):
        mm = x[:-3].reshape(nc, 3)
        R, o = constellation_frame(mm)
        return np.concatenate([R.T @ (x[-3:] - o), ((mm - o) @ R).ravel()])
    xin = np.concatenate([means[0].ravel(), S_star])
    yc, Jc = _num_jac(to_const, xin, 1e-6)
    vin = np.concatenate([np.repeat(sigma ** 2 / counts[0], 3), np.full(3, sigma ** 2 / len(star_all))])
    cov_pc = (Jc[:3] * vin) @ Jc[:3].T
    if chi2 / max(dof, 1) > 4.0:
        notes.append(f"camera fit chi2/dof = {chi2 / dof:.2f}: residuals exceed the stated uncertainties "
                     "(lens distortion not in CameraInfo? stage not translating rigidly?)")
    if np.any(np.abs(sc) > 5 * np.maximum(u_sc, 1.0)):
        notes.append(f"tracker and encoder lengths disagree by {np.round(sc, 1).tolist()} ppm "
                     f"(u {np.round(u_sc, 1).tolist()}): tracker scale or encoder scale error")
    msg = "calibrated" + ("; " + "; ".join(notes) if notes else "")
    return CalibrationResult(
        success=True, message=msg, pixels=pixels, u_pixels=u_pixels, p_tracker=S_star,
        cov_p_tracker=np.eye(3) * sigma ** 2 / len(star_all), stage_reading=ref.window.q.copy(),
        p_constellation=yc[:3], cov_p_constellation=cov_pc,
        constellation={n: yc[3 + 3 * k:6 + 3 * k] for k, n in enumerate(names)}, cameras=cam_results,
        R_tracker_stage=R_ts, p_tracker_stage=p0, travel_matrix=M,
        squareness_rad=dict(zip(("xy", "xz", "yz"), ang.tolist())),
        u_squareness_rad=dict(zip(("xy", "xz", "yz"), u_ang.tolist())), scale_ppm=sc, u_scale_ppm=u_sc,
        tracker_sigma_m=float(sigma), rigid_fit_rms_m=rigid_rms, chi2_dof=float(chi2 / max(dof, 1)),
        n_stations=N, notes=tuple(notes), camera_cov=cov_cam,
        design={"U": U_fn(sq_est), "obs": obs, "obs_cov": obs_cov, "cov_U": cov_Uq, "cameras": cams,
                "sq": sq_est, "sq_prior": prior,
                # the tracker link, for the discrepancy engine: X* per station (tracker frame), the
                # constellation's rotation since the reference, the encoder readings and station times
                "X_T": X_T, "cov_X": cov_X, "W_T": W_T, "cov_W": cov_W, "q": q,
                "t_ns": np.array([s.window.start_ns for s in good], np.int64), "edges_px": edges})
