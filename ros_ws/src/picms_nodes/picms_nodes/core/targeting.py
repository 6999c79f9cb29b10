"""Pixel Probe targeting (Gordon and Borenstein 2019, sections 2.4 to 3): triangulate a feature
seen by the cameras, drive the invisible stylus X* onto it, record the point.

Geometry. The cameras and the constellation ride on the stage (pure translation), so in the
frame that moves with the probe body (stage axes, origin X*(q)) the camera poses are constant:
`R_stage_camera`, `p_stage_centre` of picms_calibration.yaml. A feature at stage point P seen
at encoder reading q is, in that frame, at P - X*(q), where X*(q) = A q and A (columns: the unit
travel directions in the stage frame) follows from the calibrated squareness.

Triangulation (eqs 13-16): each camera j gives two rows of the homogeneous system
    x_j (p_j3 . X) - p_j1 . X = 0,   y_j (p_j3 . X) - p_j2 . X = 0
on normalised, undistorted coordinates (x_j, y_j) with P_j = [R_j^T | -R_j^T C_j]; the row
pairs are scaled by the pixel weight f_j / sigma_j and the solution is the right singular
vector of the smallest singular value. A Gauss-Newton refinement on the pixel residuals
follows (the DLT's algebraic error is not the pixel error). The offset the stage must move is
measured against the images x_j* of X* itself: offset = T(feature pixels) - T(x_j*), so the
constant part of any camera-pose error cancels (the feature is on X* when its pixels are x_j*).

drive_to iterates: locate the feature in the settled images, triangulate, command q + A^-1
offset through the calibrated axes, wait for settled readings, re-image. A move that rounds
to no step on any axis is not commanded (the resolution limit): the final point is then
X*(q) + the small remaining triangulated offset, with the offset's own uncertainty.

Points: stage mode (tracker-free, relative): p_stage = A q + offset; tracker mode: X* in the
tracker frame from the settled constellation readings (rigid fit of the constellation frame)
plus R_tracker_stage offset.
"""
from __future__ import annotations

import pathlib
import time
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np

from .calibrate import kabsch, travel_matrix
from .cellio import CellIO, Settled


class TargetingError(ValueError):
    """Targeting cannot proceed; the message names the cause."""


# ---------------------------------------------------------------- probe
@dataclass
class Probe:
    """What targeting needs from picms_calibration.yaml and the CameraInfo intrinsics."""
    camera_names: list
    intrinsics: dict                 # camera -> Intrinsics
    R_stage_camera: dict             # camera -> (3, 3)
    p_stage_centre: dict             # camera -> (3,), relative to X*
    u_rotation_rad: dict             # camera -> (3,)
    u_p_stage_centre: dict           # camera -> (3,)
    xstar_px: dict                   # camera -> (2,) image of X* (raw pixels)
    u_xstar_px: dict                 # camera -> (2,)
    squareness: np.ndarray           # (3,) [xy, xz, yz] rad
    u_squareness: np.ndarray         # (3,)
    p_constellation: np.ndarray      # X* in the constellation frame
    cov_p_constellation: np.ndarray
    constellation: dict              # SMR name -> (3,) in the constellation frame
    R_tracker_stage: np.ndarray
    tracker_sigma_m: float = 1.0e-5  # per-axis sd of one tracker reading (quality.tracker_sigma_m)
    A: np.ndarray = field(default=None)
    _xstar_body: np.ndarray = field(default=None, repr=False)
    _xstar_cov: np.ndarray = field(default=None, repr=False)

    def __post_init__(self):
        self.squareness = np.asarray(self.squareness, float).reshape(3)
        self.u_squareness = np.asarray(self.u_squareness, float).reshape(3)
        if self.A is None:
            self.A = travel_matrix(self.squareness)
        self.A_inv = np.linalg.inv(self.A)
        missing = [c for c in self.camera_names if c not in self.intrinsics]
        if missing:
            raise TargetingError(f"no CameraInfo intrinsics for {missing}")
        if len(self.camera_names) < 2:
            raise TargetingError(f"at least two calibrated cameras are needed, got {self.camera_names}")
        px = {c: np.asarray(self.xstar_px[c], float) for c in self.camera_names}
        upx = {c: np.asarray(self.u_xstar_px[c], float) for c in self.camera_names}
        tri = _triangulate_body(self, px, {c: np.diag(np.maximum(upx[c], 1e-4) ** 2) for c in self.camera_names})
        self._xstar_body, self._xstar_cov = tri[0], tri[1]

    @property
    def xstar_body(self) -> np.ndarray:
        """X* triangulated from its calibrated images x_j* in the camera body's stage-aligned frame
        (the frame every triangulation here uses; offsets are taken from it)."""
        return np.asarray(self._xstar_body, float)

    # -------------------------------------------------------------- construction
    @classmethod
    def from_calibration_yaml(cls, path_or_dict, camera_info: dict) -> "Probe":
        """From picms_calibration.yaml (a path, its dict, or a calibrate.CalibrationResult) and the
        CameraInfo intrinsics {camera: camera.Intrinsics}. Raises TargetingError naming a missing key."""
        d = path_or_dict
        if isinstance(d, (str, pathlib.Path)):
            import yaml
            try:
                d = yaml.safe_load(pathlib.Path(d).read_text())
            except (OSError, ValueError) as exc:
                raise TargetingError(f"cannot read picms_calibration.yaml at {path_or_dict}: {exc}") from exc
        elif not isinstance(d, dict):
            from ..io.files import calibration_dict
            d = calibration_dict(d)
        try:
            pp, cams, st = d["probe_point"], d["cameras"], d["stage"]
            names = sorted(c for c in cams if c in camera_info)
            if len(names) < 2:
                raise TargetingError(f"calibrated cameras {sorted(cams)} with CameraInfo {sorted(camera_info)}: "
                                     "fewer than two usable")
            sq = st.get("squareness_rad") or {}
            usq = st.get("u_squareness_rad") or {}
            q = d.get("quality") or {}
            return cls(
                camera_names=names,
                intrinsics={c: camera_info[c] for c in names},
                R_stage_camera={c: np.asarray(cams[c]["R_stage_camera"], float) for c in names},
                p_stage_centre={c: np.asarray(cams[c]["p_stage_centre"], float) for c in names},
                u_rotation_rad={c: np.asarray(cams[c].get("u_rotation_rad", [0, 0, 0]), float) for c in names},
                u_p_stage_centre={c: np.asarray(cams[c].get("u_p_stage_centre", [0, 0, 0]), float) for c in names},
                xstar_px={c: np.asarray(pp["pixels"][c], float) for c in names},
                u_xstar_px={c: np.asarray((pp.get("u_pixels") or {}).get(c, [0.05, 0.05]), float) for c in names},
                squareness=np.array([sq.get("xy", 0.0), sq.get("xz", 0.0), sq.get("yz", 0.0)], float),
                u_squareness=np.array([usq.get("xy", 0.0), usq.get("xz", 0.0), usq.get("yz", 0.0)], float),
                p_constellation=np.asarray(pp["p_constellation"], float),
                cov_p_constellation=np.asarray(pp.get("cov_p_constellation", np.zeros((3, 3))), float),
                constellation={k: np.asarray(v, float) for k, v in (pp.get("constellation") or {}).items()},
                R_tracker_stage=np.asarray(st["R_tracker_stage"], float),
                tracker_sigma_m=float(q.get("tracker_sigma_m", 1.0e-5)),
            )
        except KeyError as exc:
            raise TargetingError(f"picms_calibration.yaml: missing key {exc}") from exc

    # -------------------------------------------------------------- geometry
    def xstar_stage(self, q) -> np.ndarray:
        """X* in the stage frame (3,) at encoder reading q (calibrated axes)."""
        return self.A @ np.asarray(q, float).reshape(3)

    def cov_xstar_stage(self, q) -> np.ndarray:
        """Covariance (3, 3) of A q from the squareness uncertainties."""
        q = np.asarray(q, float).reshape(3)
        J = np.empty((3, 3))
        for k in range(3):
            d = np.zeros(3)
            d[k] = 1e-6
            J[:, k] = (travel_matrix(self.squareness + d) @ q - travel_matrix(self.squareness - d) @ q) / 2e-6
        return (J * self.u_squareness ** 2) @ J.T

    def move_for(self, offset_stage) -> np.ndarray:
        """Encoder increment (3,) that moves X* by offset_stage (stage frame)."""
        return self.A_inv @ np.asarray(offset_stage, float).reshape(3)

    def pixels_of_offset(self, offset_stage, cameras=None) -> dict:
        """Raw pixels {camera: (2,)} of a point at offset_stage from X* (body frame)."""
        X = self._xstar_body + np.asarray(offset_stage, float).reshape(3)
        out = {}
        for c in cameras or self.camera_names:
            pc = self.R_stage_camera[c].T @ (X - self.p_stage_centre[c])
            if pc[2] <= 0:
                raise TargetingError(f"{c}: point behind the camera")
            out[c] = self.intrinsics[c].distort((pc[:2] / pc[2]).reshape(1, 2))[0]
        return out

    def mm_per_px(self, camera: str) -> float:
        """Object-space size (m) of one pixel at X* for a camera."""
        return float(np.linalg.norm(self.p_stage_centre[camera] - self._xstar_body) / self.intrinsics[camera].f_px)


# ---------------------------------------------------------------- triangulation
@dataclass
class Triangulation:
    offset_stage: np.ndarray         # feature minus X* (stage axes), m
    cov: np.ndarray                  # (3, 3) of offset_stage (pixel noise of feature and x_j*)
    reproj_px: dict                  # camera -> (2,) residual of the refined point, px
    point_body: np.ndarray           # refined point in the body frame (poses' frame)
    dlt_point_body: np.ndarray       # the DLT's (before refinement)
    cameras: list
    q: np.ndarray | None = None

    @property
    def rms_px(self) -> float:
        r = np.array(list(self.reproj_px.values()))
        return float(np.sqrt(np.mean(r ** 2))) if r.size else 0.0


def _parse_pixels(pixels: dict, probe: Probe):
    """{camera: (c, r[, sigma_px])} -> ({camera: (2,)}, {camera: (2, 2) cov px^2})."""
    px, cov = {}, {}
    for c, v in pixels.items():
        if c not in probe.intrinsics:
            raise TargetingError(f"pixels given for {c!r}, which is not a calibrated camera ({probe.camera_names})")
        a = np.asarray(v, float).ravel()
        if a.size not in (2, 3) or not np.all(np.isfinite(a)):
            raise TargetingError(f"{c}: pixel must be finite (c, r) or (c, r, sigma_px), got {v!r}")
        px[c] = a[:2]
        s = a[2] if a.size == 3 else 0.1
        cov[c] = np.eye(2) * max(s, 1e-4) ** 2
    return px, cov


def _dlt(probe: Probe, n: dict, w: dict) -> np.ndarray:
    rows = []
    for c, xy in n.items():
        R, C = probe.R_stage_camera[c], probe.p_stage_centre[c]
        P = np.hstack([R.T, (-R.T @ C).reshape(3, 1)])
        rows.append(w[c] * (xy[0] * P[2] - P[0]))
        rows.append(w[c] * (xy[1] * P[2] - P[1]))
    M = np.array(rows)
    # condition: translate/scale the homogeneous coordinate so the point sits near unit size
    _, s, Vt = np.linalg.svd(M)
    X = Vt[-1]
    if abs(X[3]) < 1e-15:
        raise TargetingError("triangulation: rays are parallel (point at infinity)")
    return X[:3] / X[3]


def _proj_px(probe: Probe, c: str, X: np.ndarray) -> np.ndarray:
    pc = probe.R_stage_camera[c].T @ (X - probe.p_stage_centre[c])
    return probe.intrinsics[c].distort((pc[:2] / pc[2]).reshape(1, 2))[0]


def _distortion_jacobian(intr, n) -> np.ndarray:
    """d(pixel)/d(normalised undistorted coordinate) (2, 2) at n (2,)."""
    h = 1e-7
    pts = np.array([n + [h, 0], n - [h, 0], n + [0, h], n - [0, h]])
    u = intr.distort(pts)
    return np.column_stack([(u[0] - u[1]) / (2 * h), (u[2] - u[3]) / (2 * h)])


def _triangulate_body(probe: Probe, px: dict, cov: dict, refine: bool = True):
    """(X (3,), cov (3, 3), residuals {c: (2,)}, X_dlt) in the body frame from raw pixels.

    The pixels are undistorted once; the pixel covariance is carried into normalised
    coordinates through the local distortion Jacobian, so the refinement (Gauss-Newton on
    the weighted normalised residuals, analytic Jacobian) needs no further distortion calls.
    """
    if len(px) < 2:
        raise TargetingError(f"triangulation needs the feature in at least two cameras, got {sorted(px)}")
    cams = list(px)
    n = {c: probe.intrinsics[c].undistort(px[c].reshape(1, 2))[0] for c in cams}
    Jd = {c: _distortion_jacobian(probe.intrinsics[c], n[c]) for c in cams}
    Wn = {}
    for c in cams:
        Jinv = np.linalg.inv(Jd[c])
        Wn[c] = np.linalg.inv(Jinv @ cov[c] @ Jinv.T)       # weight of normalised residuals
    w = {c: np.sqrt(np.trace(Wn[c]) / 2) for c in cams}      # row scaling of the DLT
    X0 = _dlt(probe, n, w)
    X = X0.copy()
    Rt = {c: probe.R_stage_camera[c].T for c in cams}
    Cc = {c: probe.p_stage_centre[c] for c in cams}
    for _ in range(8):
        H = np.zeros((3, 3))
        g = np.zeros(3)
        for c in cams:
            pc = Rt[c] @ (X - Cc[c])
            if pc[2] <= 0:
                raise TargetingError(f"triangulation: point behind {c}")
            m = pc[:2] / pc[2]
            J = (np.array([[1.0, 0.0, -m[0]], [0.0, 1.0, -m[1]]]) / pc[2]) @ Rt[c]
            H += J.T @ Wn[c] @ J
            g += J.T @ Wn[c] @ (n[c] - m)
        if not refine:
            break
        step = np.linalg.solve(H, g)
        X = X + step
        if np.linalg.norm(step) < 1e-13:
            break
    res = {}
    for c in cams:
        pc = Rt[c] @ (X - Cc[c])
        res[c] = Jd[c] @ (n[c] - pc[:2] / pc[2])
    return X, np.linalg.inv(H), res, X0


def triangulate(probe: Probe, pixels: dict, q=None, *, refine: bool = True) -> Triangulation:
    """N-view DLT (eqs 13-16) + Gauss-Newton of a feature's raw pixels {camera: (c, r[, sigma])}.

    offset_stage = T(feature) - T(x_j*): the feature relative to X* in stage axes. cov holds
    the feature's pixel noise (sigma per camera, default 0.1 px) and that of x_j* (u_pixels).
    """
    px, cov = _parse_pixels(pixels, probe)
    X, C, res, X0 = _triangulate_body(probe, px, cov, refine)
    return Triangulation(offset_stage=X - probe._xstar_body, cov=C + probe._xstar_cov, reproj_px=res,
                         point_body=X, dlt_point_body=X0, cameras=sorted(px),
                         q=None if q is None else np.asarray(q, float))


def triangulate_many(probe: Probe, pixels: dict, sigma_px: float | dict = 0.1, *, refine: bool = True):
    """Vectorised triangulate for many points: pixels {camera: (N, 2)} raw pixels of the same N
    points in every camera given (>= 2). Same method (pixel-weighted N-view DLT by batched SVD,
    then Gauss-Newton); returns (offset_stage (N, 3), cov (N, 3, 3), reproj_px {camera: (N, 2)})."""
    cams = list(pixels)
    if len(cams) < 2:
        raise TargetingError(f"triangulation needs at least two cameras, got {cams}")
    px = {c: np.asarray(pixels[c], float).reshape(-1, 2) for c in cams}
    N = px[cams[0]].shape[0]
    if any(v.shape[0] != N for v in px.values()) or not all(np.all(np.isfinite(v)) for v in px.values()):
        raise TargetingError("triangulate_many: every camera needs the same number of finite pixels")
    sig = {c: float(sigma_px[c] if isinstance(sigma_px, dict) else sigma_px) for c in cams}
    n, Wn = {}, {}
    h = 1e-7
    for c in cams:
        intr = probe.intrinsics[c]
        n[c] = intr.undistort(px[c])
        J = np.stack([(intr.distort(n[c] + [h, 0]) - intr.distort(n[c] - [h, 0])) / (2 * h),
                      (intr.distort(n[c] + [0, h]) - intr.distort(n[c] - [0, h])) / (2 * h)], axis=2)  # (N, 2, 2)
        Wn[c] = np.einsum("nki,nkj->nij", J, J) / sig[c] ** 2          # J^T Sigma^-1 J, Sigma = sig^2 I
    rows = []
    for c in cams:
        R, C = probe.R_stage_camera[c], probe.p_stage_centre[c]
        P = np.hstack([R.T, (-R.T @ C).reshape(3, 1)])
        w = np.sqrt(np.trace(Wn[c], axis1=1, axis2=2) / 2)[:, None]
        rows.append(w * (n[c][:, :1] * P[2] - P[0]))
        rows.append(w * (n[c][:, 1:] * P[2] - P[1]))
    M = np.stack(rows, axis=1)                                            # (N, 2J, 4)
    Vt = np.linalg.svd(M)[2]
    X = Vt[:, -1, :3] / Vt[:, -1, 3:4]
    for _ in range(6 if refine else 1):
        H = np.zeros((N, 3, 3))
        g = np.zeros((N, 3))
        for c in cams:
            Rt = probe.R_stage_camera[c].T
            pc = (X - probe.p_stage_centre[c]) @ Rt.T
            m = pc[:, :2] / pc[:, 2:3]
            A = np.zeros((N, 2, 3))
            A[:, 0, 0] = A[:, 1, 1] = 1.0
            A[:, :, 2] = -m
            J = (A / pc[:, 2, None, None]) @ Rt                           # (N, 2, 3)
            JW = np.einsum("nki,nkj->nij", J, Wn[c])                      # J^T W
            H += JW @ J
            g += np.einsum("nij,nj->ni", JW, n[c] - m)
        if not refine:
            break
        X = X + np.linalg.solve(H, g[..., None])[..., 0]
    res = {}
    for c in cams:
        pc = (X - probe.p_stage_centre[c]) @ probe.R_stage_camera[c]
        res[c] = probe.intrinsics[c].distort(pc[:, :2] / pc[:, 2:3]) - px[c]
    return X - probe._xstar_body, np.linalg.inv(H) + probe._xstar_cov, res


# ---------------------------------------------------------------- points in stage / tracker frame
def point_in_tracker(probe: Probe, settled: Settled, offset_stage, cov_offset):
    """(p_tracker (3,), cov (3, 3)) of X*(q) + offset via the settled constellation readings,
    or (None, None) when fewer than 3 calibrated constellation SMRs were read."""
    names = [n for n in probe.constellation if n in settled.tracker and settled.tracker_n.get(n, 0) > 0]
    if len(names) < 3:
        return None, None
    Pc = np.array([probe.constellation[n] for n in names])
    nn = np.array([settled.tracker_n[n] for n in names], float)

    def f(flat):
        R, t = kabsch(Pc, flat.reshape(-1, 3), nn)
        return R @ probe.p_constellation + t

    flat = np.array([settled.tracker[n] for n in names]).ravel()
    x = f(flat)
    J = np.empty((3, flat.size))
    for k in range(flat.size):
        d = np.zeros(flat.size)
        d[k] = 1e-6
        J[:, k] = (f(flat + d) - f(flat - d)) / 2e-6
    var = np.repeat(probe.tracker_sigma_m ** 2 / nn, 3)
    R, _ = kabsch(Pc, flat.reshape(-1, 3), nn)
    cov = (J * var) @ J.T + R @ probe.cov_p_constellation @ R.T
    Rts = probe.R_tracker_stage
    off = np.asarray(offset_stage, float)
    return x + Rts @ off, cov + Rts @ np.asarray(cov_offset) @ Rts.T


# ---------------------------------------------------------------- drive_to
@dataclass
class TargetResult:
    ok: bool
    reason: str
    q: np.ndarray                    # final encoder reading
    offset_stage: np.ndarray         # remaining feature - X* at the end (m)
    p_stage: np.ndarray              # the measured point in the stage frame (tracker-free mode)
    cov_stage: np.ndarray
    p_tracker: np.ndarray | None     # the point in the tracker frame via the constellation (tracker mode)
    cov_tracker: np.ndarray | None
    iterations: list                 # per iteration: q, offset (m), |offset|, n cameras used
    pixels: dict                     # final feature pixels per camera
    settled: Settled                 # the last settled state (images kept for offline refits)
    elapsed_s: float = 0.0           # wall time of drive_to (extra)
    n_moves: int = 0                 # moves commanded (extra)


Locator = Callable[[Settled, Probe], dict]


def drive_to(cell: CellIO, probe: Probe, locate: Locator, *, tol_m=None, max_iter: int = 6,
             start: Settled | None = None, progress=None, max_reproj_px: float = 3.0) -> TargetResult:
    """Drive X* onto the feature `locate` finds; record the point (see module doc).

    tol_m: stop when |offset| <= tol_m (default: the stage resolution). Independently, a move
    that rounds to zero steps on every axis is not commanded: the loop stops at the resolution
    limit with ok=True. max_iter bounds the moves. A triangulation whose reprojection residual
    exceeds max_reproj_px in some camera (the cameras found different features) ends the run
    with ok=False. progress(iteration_dict) is called per
    iteration (feedback). A locator error ends the run with ok=False and the reason.
    """
    t0 = time.perf_counter()
    res = float(cell.resolution_m)
    tol = res if tol_m is None else float(tol_m)
    s = start if start is not None else cell.current()
    iters: list = []
    n_moves = 0
    reason = ""
    ok = False
    tri = tri_prev = None
    s_tri, px_tri = s, {}
    while True:
        try:
            px = locate(s, probe)
            tri = triangulate(probe, px, q=s.q)
        except (TargetingError, ValueError) as exc:
            reason = f"iteration {len(iters)}: feature not located: {exc}"
            tri = tri_prev
            break
        worst = max(tri.reproj_px, key=lambda c: np.linalg.norm(tri.reproj_px[c]))
        if np.linalg.norm(tri.reproj_px[worst]) > max_reproj_px:
            reason = (f"iteration {len(iters)}: the cameras do not see the same point: reprojection residual "
                      f"{np.linalg.norm(tri.reproj_px[worst]):.2f} px in {worst} > {max_reproj_px} px")
            tri = tri_prev
            break
        tri_prev, s_tri, px_tri = tri, s, px
        off = tri.offset_stage
        it = {"iteration": len(iters), "q": s.q.copy(), "offset": off.copy(), "offset_norm": float(np.linalg.norm(off)),
              "n_cameras": len(tri.cameras), "reproj_rms_px": tri.rms_px}
        dq = probe.move_for(off)
        q_now_steps = np.round(s.q / res)
        q_cmd_steps = np.round((s.q + dq) / res)
        it["move_steps"] = (q_cmd_steps - q_now_steps).astype(int).tolist()
        iters.append(it)
        if progress is not None:
            progress(it)
        if it["offset_norm"] <= tol:
            ok, reason = True, f"converged: |offset| {it['offset_norm'] * 1e6:.2f} um <= tol {tol * 1e6:.2f} um"
            break
        if np.all(q_cmd_steps == q_now_steps):
            ok, reason = True, (f"resolution limit: the remaining offset {it['offset_norm'] * 1e6:.2f} um "
                                f"rounds to no stage step ({res * 1e6:.2f} um)")
            break
        if n_moves >= max_iter:
            reason = f"not converged after {max_iter} moves: |offset| {it['offset_norm'] * 1e6:.2f} um"
            break
        try:
            s = cell.move_and_settle(q_cmd_steps * res)
        except TimeoutError as exc:
            reason = f"move {n_moves + 1}: {exc}"
            break
        n_moves += 1
    if tri is None:
        z = np.full(3, np.nan)
        return TargetResult(False, reason, s.q.copy(), z, z, np.full((3, 3), np.nan), None, None, iters, {},
                            s, time.perf_counter() - t0, n_moves)
    # the point at the last accepted triangulation (and the settled state it was made in)
    p_stage = probe.xstar_stage(s_tri.q) + tri.offset_stage
    cov_stage = probe.cov_xstar_stage(s_tri.q) + tri.cov
    p_tr, cov_tr = point_in_tracker(probe, s_tri, tri.offset_stage, tri.cov)
    return TargetResult(ok, reason, s_tri.q.copy(), tri.offset_stage.copy(), p_stage, cov_stage, p_tr, cov_tr,
                        iters, {c: tuple(map(float, np.asarray(v, float).ravel()[:2])) for c, v in px_tri.items()},
                        s_tri, time.perf_counter() - t0, n_moves)


# ---------------------------------------------------------------- Direct Mode
def direct_locator(pixels_in_two_or_more: dict, *, max_reproj_px: float = 2.0, sigma_px: float = 0.3,
                   template_half_px: int = 12, search_px: int = 8) -> Locator:
    """Direct Mode: a target given as raw pixels in >= 2 images of the first settled state.

    First call: the given pixels are triangulated; a third camera's pixel is predicted and the
    given ones are checked against each other (reprojection residual <= max_reproj_px, else a
    TargetingError that names the camera and the residual). Patches around the pixels are kept
    as templates. Later calls: the pixels are predicted from the first triangulation and the
    encoder increment, then refined by normalised cross-correlation of the templates within
    +-search_px (sub-pixel by a parabola fit); a camera whose match is weak keeps the prediction.
    """
    given = {c: np.asarray(v, float).ravel()[:2] for c, v in pixels_in_two_or_more.items()}
    if len(given) < 2:
        raise TargetingError(f"Direct Mode needs the target in at least two images, got {sorted(given)}")
    state: dict = {}

    def locate(s: Settled, probe: Probe) -> dict:
        if not state:
            for c in given:
                if c not in probe.intrinsics:
                    raise TargetingError(f"Direct Mode: {c!r} is not a calibrated camera")
            tri = triangulate(probe, {c: (*v, sigma_px) for c, v in given.items()})
            bad = {c: float(np.linalg.norm(r)) for c, r in tri.reproj_px.items() if np.linalg.norm(r) > max_reproj_px}
            if bad:
                raise TargetingError("Direct Mode: the given pixels are inconsistent (their rays miss each other): "
                                     f"reprojection residual {', '.join(f'{c} {v:.2f} px' for c, v in bad.items())} "
                                     f"> {max_reproj_px} px")
            pred = probe.pixels_of_offset(tri.offset_stage)
            out = {}
            for c in probe.camera_names:
                p = given.get(c, pred[c])
                intr = probe.intrinsics[c]
                if not (0 <= p[0] < intr.width and 0 <= p[1] < intr.height):
                    if c in given:
                        raise TargetingError(f"Direct Mode: {c} pixel {p.tolist()} is outside the image")
                    continue             # predicted outside this camera's view: not used
                img = s.images.get(c)
                if img is not None:
                    t = _patch(img, p, template_half_px)
                    if t is not None:
                        state.setdefault("tmpl", {})[c] = (t, p - np.round(p))
                out[c] = p
            state.update(offset=tri.offset_stage, q=s.q.copy(), pred=pred, checked=sorted(set(out) - set(given)))
            return out
        off = state["offset"] - probe.A @ (s.q - state["q"])
        pred = probe.pixels_of_offset(off)
        out = {}
        for c, p in pred.items():
            tm = state.get("tmpl", {}).get(c)
            img = s.images.get(c)
            if tm is not None and img is not None:
                m = _match(img, tm[0], p, search_px)
                if m is not None:
                    p = m + tm[1]
                    state["matched"] = state.get("matched", 0) + 1
            out[c] = p
        return out
    locate.state = state
    return locate


def _patch(img, p, h):
    c, r = int(round(p[0])), int(round(p[1]))
    if r - h < 0 or c - h < 0 or r + h + 1 > img.shape[0] or c + h + 1 > img.shape[1]:
        return None
    t = img[r - h:r + h + 1, c - h:c + h + 1].astype(np.float32)
    return t if t.std() > 1.0 else None


def _match(img, tmpl, p, search):
    h = tmpl.shape[0] // 2
    c, r = int(round(p[0])), int(round(p[1]))
    y0, y1, x0, x1 = r - h - search, r + h + search + 1, c - h - search, c + h + search + 1
    if y0 < 0 or x0 < 0 or y1 > img.shape[0] or x1 > img.shape[1]:
        return None
    ncc = cv2.matchTemplate(img[y0:y1, x0:x1].astype(np.float32), tmpl, cv2.TM_CCOEFF_NORMED)
    iy, ix = np.unravel_index(int(np.argmax(ncc)), ncc.shape)
    if ncc[iy, ix] < 0.6 or not (0 < iy < ncc.shape[0] - 1 and 0 < ix < ncc.shape[1] - 1):
        return None

    def para(a, b, cc):
        den = a - 2 * b + cc
        return 0.0 if abs(den) < 1e-12 else 0.5 * (a - cc) / den
    dx = para(ncc[iy, ix - 1], ncc[iy, ix], ncc[iy, ix + 1])
    dy = para(ncc[iy - 1, ix], ncc[iy, ix], ncc[iy + 1, ix])
    return np.array([c - search + ix + dx, r - search + iy + dy], float)


# ---------------------------------------------------------------- Feature Mode (circles)
def _fit_ellipse(pts):
    """Algebraic least-squares conic a x^2 + b xy + c y^2 + d x + e y + f = 0 through pts (N, 2)
    (Fitzgibbon's constraint 4ac - b^2 = 1); returns (centre (2,), semi-axes (2,), conic (6,))."""
    m = pts.mean(0)
    s = pts.std() or 1.0
    x, y = ((pts - m) / s).T
    D1 = np.column_stack([x * x, x * y, y * y])
    D2 = np.column_stack([x, y, np.ones_like(x)])
    S1, S2, S3 = D1.T @ D1, D1.T @ D2, D2.T @ D2
    T = -np.linalg.solve(S3, S2.T)
    M = S1 + S2 @ T
    M = np.array([M[2] / 2, -M[1], M[0] / 2])
    w, v = np.linalg.eig(M)
    v = np.real(v)
    cond = 4 * v[0] * v[2] - v[1] ** 2
    a1 = v[:, np.argmax(cond > 0)] if np.any(cond > 0) else v[:, 0]
    a, b, c, d, e, f = np.concatenate([a1, T @ a1])
    den = b * b - 4 * a * c
    xc = (2 * c * d - b * e) / den
    yc = (2 * a * e - b * d) / den
    num = 2 * (a * e * e + c * d * d - b * d * e + den * f)
    root = np.sqrt((a - c) ** 2 + b * b)
    ax1 = np.sqrt(abs(num * (a + c + root))) / abs(den)
    ax2 = np.sqrt(abs(num * (a + c - root))) / abs(den)
    return np.array([xc, yc]) * s + m, np.array([ax1, ax2]) * s, np.array([a, b, c, d, e, f])


def ellipse_residuals(pts) -> np.ndarray:
    """First-order geometric distances (N,) of pts (N, 2) to their algebraic ellipse fit."""
    m = pts.mean(0)
    sc = pts.std() or 1.0
    a, b, c, d, e, f = _fit_ellipse(pts)[2]
    x, y = ((pts - m) / sc).T
    # _fit_ellipse's conic is in its own normalised coordinates, the same (mean, std) as here
    Q = a * x * x + b * x * y + c * y * y + d * x + e * y + f
    g = np.hypot(2 * a * x + b * y + d, b * x + 2 * c * y + e)
    return Q / np.maximum(g, 1e-15) * sc


def circle_edge_points(img, centre, radius_px, *, n_rays: int = 120, band: float = 0.45):
    """Sub-pixel edge points (N, 2) of a dark disc on a brighter surround (or a dark hole inside
    a bright edge band): along rays from `centre`, the first 50 % crossing from the inside level
    to the outer maximum within radius_px (1 +- band)."""
    img = np.asarray(img, np.float32)
    a = np.linspace(0, 2 * np.pi, n_rays, endpoint=False)
    r = np.linspace(max(radius_px * (1 - band), 0.5), radius_px * (1 + band), max(int(radius_px * 2 * band * 4), 24))
    xs = (centre[0] + np.outer(np.cos(a), r)).astype(np.float32)
    ys = (centre[1] + np.outer(np.sin(a), r)).astype(np.float32)
    prof = cv2.remap(img, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    pts, w = [], []
    for k in range(n_rays):
        p = prof[k]
        if not np.all(np.isfinite(p)):
            continue
        imax = int(np.argmax(p))
        lo = float(np.median(p[:max(3, len(p) // 6)]))
        hi = float(p[imax])
        if hi - lo < 10:
            continue
        lev = 0.5 * (lo + hi)
        above = np.flatnonzero(p[:imax + 1] >= lev)
        if above.size == 0 or above[0] == 0:
            continue
        i = int(above[0])
        f = (lev - p[i - 1]) / (p[i] - p[i - 1])
        rr = r[i - 1] + f * (r[i] - r[i - 1])
        pts.append([centre[0] + rr * np.cos(a[k]), centre[1] + rr * np.sin(a[k])])
    return np.array(pts)


def find_disc(img, roi, expected_radius_px):
    """Centre (2,) and radius (px) of the dark blob in roi (c0, r0, c1, r1) closest in size to
    expected_radius_px: Otsu threshold, contours, then ellipse fit of sub-pixel edge points
    (iterated twice). Raises TargetingError when nothing fits."""
    c0, r0, c1, r1 = (int(round(v)) for v in roi)
    H, W = img.shape[:2]
    c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, W), min(r1, H)
    if c1 - c0 < 5 or r1 - r0 < 5:
        raise TargetingError(f"ROI {roi} is empty or outside the image")
    sub = np.asarray(img[r0:r1, c0:c1])
    sub8 = cv2.normalize(sub, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8) if sub.dtype != np.uint8 else sub
    _, bw = cv2.threshold(cv2.GaussianBlur(sub8, (0, 0), 1.0), 0, 255, cv2.THRESH_BINARY_INV + cv2.THRESH_OTSU)
    cnts, _ = cv2.findContours(bw, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    best, score = None, np.inf
    exp_area = np.pi * expected_radius_px ** 2
    for c in cnts:
        area = cv2.contourArea(c)
        if area < 0.3 * exp_area or area > 3.0 * exp_area or len(c) < 5:
            continue
        (x, y), (ma, mi), _ = cv2.fitEllipse(c)
        if mi < 0.5 * ma:
            continue
        touches = c[:, 0, 0].min() <= 0 or c[:, 0, 1].min() <= 0 or c[:, 0, 0].max() >= bw.shape[1] - 1 \
            or c[:, 0, 1].max() >= bw.shape[0] - 1
        # size, then nearness to the ROI centre (a grid of equal dots: the one the ROI is on)
        dist = np.hypot(x - 0.5 * bw.shape[1], y - 0.5 * bw.shape[0]) / (0.5 * np.hypot(*bw.shape))
        sc = abs(np.log(area / exp_area)) + 2.0 * dist + (10.0 if touches else 0.0)
        if sc < score:
            best, score = np.array([x + c0, y + r0, 0.25 * (ma + mi)]), sc
    if best is None:
        raise TargetingError(f"no disc of radius ~{expected_radius_px:.1f} px in ROI {[c0, r0, c1, r1]}")
    centre, rad = best[:2], best[2]
    for _ in range(2):
        pts = circle_edge_points(img, centre, rad)
        if len(pts) < 12:
            raise TargetingError(f"too few edge points ({len(pts)}) around the disc at {np.round(centre, 1).tolist()}")
        centre, axes, _ = _fit_ellipse(pts)
        rad = float(np.mean(axes))
    return centre, rad, pts


def projected_circle_centre_bias(probe: Probe, camera: str, centre_offset, normal_stage, radius_m, n: int = 72):
    """Pixel difference (2,) between the centre of the image ellipse of a circle (centre at
    centre_offset from X*, in the plane with normal normal_stage, radius radius_m) and the image
    of the circle's centre. Under perspective they differ (the paper's ellipse-centre error)."""
    nrm = np.asarray(normal_stage, float)
    nrm = nrm / np.linalg.norm(nrm)
    u = np.cross(nrm, [1.0, 0.0, 0.0] if abs(nrm[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(nrm, u)
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    pts = [probe.pixels_of_offset(np.asarray(centre_offset) + radius_m * (np.cos(t) * u + np.sin(t) * v), [camera])[camera]
           for t in a]
    ce, _, _ = _fit_ellipse(np.array(pts))
    return ce - probe.pixels_of_offset(centre_offset, [camera])[camera]


def circle_feature_locator(roi: dict | None, expected_diameter_m: float, *, plane_normal_stage=(0.0, 0.0, 1.0),
                           correct_perspective: bool = True, margin_px: float = 25.0,
                           cameras: list | None = None) -> Locator:
    """Feature Mode for a circular feature (hole, dot, chrome circle).

    roi: {camera: (c0, r0, c1, r1)} around the feature in the FIRST settled images, or None (a
    window around x_j*, sized from expected_diameter_m plus margin_px). Each call finds the disc
    in each camera (Otsu blob, then sub-pixel edge points on rays and an ellipse fit); later
    calls move the ROI with the predicted image motion of the feature. With
    correct_perspective, the ellipse centres are corrected for the perspective shift of a
    circle's image centre (computed through the plane with normal plane_normal_stage at the
    triangulated centre). Pixels come with sigma_px from the edge fit's scatter.
    """
    if not expected_diameter_m > 0:
        raise TargetingError(f"Feature Mode: expected diameter must be > 0, got {expected_diameter_m}")
    state: dict = {}
    rad_m = 0.5 * expected_diameter_m

    def locate(s: Settled, probe: Probe) -> dict:
        cams = [c for c in (cameras or probe.camera_names) if c in s.images]
        out, sig = {}, {}
        if "q" in state:
            off = state["offset"] - probe.A @ (s.q - state["q"])
            pred = probe.pixels_of_offset(off, cams)
        else:
            off = None
            pred = None
        errs = []
        for c in cams:
            r_px = rad_m / probe.mm_per_px(c)
            if pred is not None:
                half = r_px * 1.5 + margin_px
                rc = (pred[c][0] - half, pred[c][1] - half, pred[c][0] + half, pred[c][1] + half)
            elif roi is not None:
                if c not in roi:
                    continue
                rc = roi[c]
            else:
                x = probe.xstar_px[c]
                half = r_px * 1.5 + margin_px + 0.5e-3 / probe.mm_per_px(c)
                rc = (x[0] - half, x[1] - half, x[0] + half, x[1] + half)
            try:
                ctr, rad, pts = find_disc(s.images[c], rc, r_px)
            except TargetingError as exc:
                errs.append(f"{c}: {exc}")
                continue
            # centre sd of a circle fit: edge scatter * sqrt(2 / N), N independent edge points
            # (neighbouring rays share pixels and the blur correlates neighbours over ~2 px:
            # at most one independent point per 2 px of circumference)
            n_eff = min(len(pts), np.pi * rad) - 5
            sig[c] = float(max(np.std(ellipse_residuals(pts)) * np.sqrt(2.0 / max(n_eff, 1)), 0.01))
            out[c] = ctr
        if len(out) < 2:
            raise TargetingError("Feature Mode: circle found in fewer than two cameras: " + "; ".join(errs))
        if correct_perspective:
            tri = triangulate(probe, {c: (*p, sig[c]) for c, p in out.items()})
            bias = {c: projected_circle_centre_bias(probe, c, tri.offset_stage, plane_normal_stage, rad_m) for c in out}
            out = {c: out[c] - bias[c] for c in out}
            state["bias_px"] = bias
        tri = triangulate(probe, {c: (*p, sig[c]) for c, p in out.items()})
        state.update(offset=tri.offset_stage, q=s.q.copy())
        return {c: (float(p[0]), float(p[1]), sig[c]) for c, p in out.items()}
    locate.state = state
    return locate


__all__ = ["Probe", "Triangulation", "TargetResult", "TargetingError", "Locator", "triangulate", "drive_to",
           "direct_locator", "circle_feature_locator", "triangulate_many", "point_in_tracker", "find_disc",
           "projected_circle_centre_bias", "circle_edge_points"]
