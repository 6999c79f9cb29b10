"""Pixel Probe adapter for the sim-to-real discrepancy engine (issue 11, Pixel Probe part).

The cell-agnostic engine lives in ct_calib_nodes.core.discrepancy (numpy/scipy only; picms_nodes
already depends on ct_calib_nodes, so it is imported from there rather than moved). This adapter
turns a Pixel Probe CalibrationResult (its ``design``: target points U in the probe-body frame,
the cameras' normalised disc observations and covariances, the solved poses, and the tracker link)
into the engine's Dataset with three residual blocks:

- camera: observed minus modelled disc centre per camera, station and image axis [px];
- tracker link: X* seen by the tracker at each station (constellation rigid fits) minus the rigid
  stage model p0 + R_ts A(squareness) q of the encoder readings [um];
- constellation rotation: the rigid fits' rotation of the probe body since the reference station,
  which a rigidly translating stage keeps at zero [urad].

Nominal parameters projected out: the three camera poses, the three squareness angles (shared by
the camera and tracker blocks), X*'s position and the stage frame's orientation in the tracker
frame, and the reference station's rotation (its noise is shared by every station's rotation).
The catalogue holds camera, stage and tracker terms, each a linearised basis d(residual)/d(theta)
on the blocks it acts on; a term with no basis on an acquisition reports why it cannot show.
The refit is the engine's linear joint fit (one Gauss-Newton step from the nominal estimate),
adequate for the small terms here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ct_calib_nodes.core.discrepancy import (BIC_THRESHOLD, Candidate, Dataset, analyse, finding_entry,
                                             required_noncentrality, sigma_from_chi2, unexplained_entries,
                                             verdict_sentence)

from . import timing_lag

from .calibrate import CalibrationResult, _skew, travel_matrix
from .camera import Intrinsics
from .detect import fit_cone


@dataclass(frozen=True)
class PicmsTerm:
    """One catalogue entry. Bases: ``cam(ctx, j) -> (m_j, 2, p)`` d pixel / d theta for camera j's rows
    (per-camera terms: theta is camera j's own; cell terms: shared); ``trk(ctx) -> (N, 3, p)`` d X*_tracker
    [um] / d theta; ``rot(ctx) -> (N, 3, p)`` d constellation rotation [urad] / d theta. Magnitude: rms over
    cameras of |theta_j| (per camera) or rms over the parameters (cell terms), times ``display``."""
    id: str
    name: str
    mechanism: str
    params: tuple              # parameter names (per camera, or of the cell)
    units: tuple
    display_unit: str
    display: float             # theta [SI] x display = magnitude unit
    reveal_by: str
    cam: object = None
    trk: object = None
    rot: object = None
    per_camera: bool = True
    plausible_max: float = np.inf      # in the display unit
    blind: str = ""                    # why no acquisition of this kind can show it (null limit)


#: steps of the decentring and the affine (aspect, skew) terms' silhouette bases (validated sizes ~8e-4
#: and ~1e-3: the tangent suffices)
TAN_STEP = 1e-4
AFFINE_STEP = 1e-4
EDGE_TERMS = ("k1", "p1", "p2", "fx", "skew")      # the order of ctx["edge"]'s last axis


def _edge(c, j, *names):
    """(m, 2, k) the silhouette bases of camera j for the named EDGE_TERMS."""
    return c["edge"][j][:, :, [EDGE_TERMS.index(n) for n in names]]


def _b_k1(c, j):
    # k1 bends every silhouette edge point, not only the disc's centre: the basis is the shift of the cone
    # the detector fits to the edge points (_silhouette_shift). Without edge points in
    # the design: the centre point's own shift k1 r^2 n (which misses the disc's size, ~3 rho^2 n)
    if c["edge"][j] is not None:
        return _edge(c, j, "k1")
    x, y = c["n"][j].T
    r2 = x * x + y * y
    return c["f"][j] * np.stack([x * r2, y * r2], 1)[:, :, None]


def _silhouette_shifts(intr, edges_px, n0, steps):
    """(2, k) shifts of the detector's cone axis (normalised coordinates) per unit of k intrinsic parameters
    CameraInfo leaves out: the cone fitted to the silhouette edge points edges_px (raw px) undistorted with
    CameraInfo (what the detector reported), minus the cone fitted to the same points undistorted with
    CameraInfo changed by the step (what it would have reported had CameraInfo carried it), over the step's
    size: the secant of the detector's response (the tangent as the step -> 0). ``steps``: k pairs
    (Intrinsics, size) from :func:`_steps`. The nest's missing sector and the disc's size enter through the
    edge points themselves: a full outline of angular radius rho moves by ~k1 (r^2 + 3 rho^2) n, the centre
    point alone by k1 r^2 n; a decentring distortion or a pixel aspect / skew error stretches the outline
    (by ~rho grad(T), or affinely), which moves the cone fitted to a partial outline, not to a full one."""
    def axis(intr_, xx):
        xx = intr_.undistort(xx)
        r = np.column_stack([xx, np.ones(len(xx))])
        r /= np.linalg.norm(r, axis=1, keepdims=True)
        a0 = np.array([n0[0], n0[1], 1.0]) / np.hypot(np.hypot(n0[0], n0[1]), 1.0)
        p, _cov, _res = fit_cone(r, [n0[0], n0[1], float(np.mean(np.arccos(np.clip(r @ a0, -1, 1))))])
        return p[:2]
    base = axis(intr, edges_px)
    return np.stack([(base - axis(changed, edges_px)) / size for changed, size in steps], 1)


def _steps(intr, names, k1=1e-4):
    """(Intrinsics, size) per name: CameraInfo with one parameter changed, in the catalogue terms' units:
    'k1' (by ``k1``: the secant there), 'p1', 'p2' (by TAN_STEP), 'fx' (fx by the factor 1 + AFFINE_STEP:
    pixel_aspect_error's dfx_rel) and 'skew' (K[0, 1] by AFFINE_STEP fx: sensor_skew)."""
    out = []
    for n in names:
        K, D = np.array(intr.K, float), np.array(intr.D, float)
        if n in ("k1", "p1", "p2"):
            i, h = {"k1": (0, k1), "p1": (2, TAN_STEP), "p2": (3, TAN_STEP)}[n]
            D[i] += h
        elif n == "fx":
            h = AFFINE_STEP
            K[0, 0] *= 1.0 + h
        elif n == "skew":
            h = AFFINE_STEP
            K[0, 1] += h * K[0, 0]
        else:
            raise ValueError(n)
        out.append((Intrinsics(K, D, intr.width, intr.height), h))
    return out


def _silhouette_shift(intr, edges_px, n0, k1):
    """(2,) the cone axis's shift per unit k1 (:func:`_silhouette_shifts` with the secant at ``k1``)."""
    return _silhouette_shifts(intr, edges_px, n0, _steps(intr, ["k1"], k1))[:, 0]


def _b_k2(c, j):
    x, y = c["n"][j].T
    r4 = (x * x + y * y) ** 2
    return c["f"][j] * np.stack([x * r4, y * r4], 1)[:, :, None]


def _b_tangential(c, j):
    # like k1: the shift of the cone the detector fits to the edge points; the centre point's own shift
    # without edge points in the design
    if c["edge"][j] is not None:
        return _edge(c, j, "p1", "p2")
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
    # the cone's shift when the edge points are present (the outline is stretched; see _silhouette_shifts)
    if c["edge"][j] is not None:
        return _edge(c, j, "fx")
    b = np.zeros((len(c["n"][j]), 2, 1))
    b[:, 0, 0] = c["f"][j] * c["n"][j][:, 0]
    return b


def _b_rot_drift(c, j):
    # tilt of camera j (about its image x and y axes) growing linearly over the session (rad per session);
    # a roll about the optical axis barely moves a disc near the image centre (see reveal_by)
    return c["t"][j][:, None, None] * c["jrot"][j][:, :, :2]


def _b_pos_drift(c, j):
    return c["t"][j][:, None, None] * c["jpos"][j]


def _b_skew(c, j):
    if c["edge"][j] is not None:
        return _edge(c, j, "skew")
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


def _cam_from_U(dU_fn):
    """Camera basis of a cell term from its displacement of the SMR* in the probe-body frame:
    dU_fn(ctx) -> (N, 3, p) [m per unit theta]; d pixel = (d pixel / d U) dU."""
    def fn(c, j):
        return np.einsum("mab,mbp->map", c["ju"][j], dU_fn(c)[c["ok"][j]])
    return fn


def _traceless(b):
    return b - b.mean(axis=2, keepdims=True)


def _dU_scale(c):
    # SMR* relative to X* in the body frame: U = -A diag(1 + s) dq; the common part of s (a uniform scale)
    # only moves the cameras' distance (absorbed) and is the tracker_length_scale term's: traceless here
    return _traceless(-c["A"][None, :, :] * c["dq"][:, None, :])


def _dX_scale(c):
    return 1e6 * _traceless(np.einsum("ab,nb->nab", c["R_ts"] @ c["A"], c["dq"]))


_STRAIGHT = [(a, k) for k in range(3) for a in range(3) if a != k]      # bow of axis k along a


def _dU_straight(c):
    out = np.zeros((len(c["dq"]), 3, 6))
    for m, (a, k) in enumerate(_STRAIGHT):
        out[:, a, m] = -c["dq2"][:, k]
    return out


def _dX_straight(c):
    return 1e6 * np.einsum("ab,nbp->nap", c["R_ts"], -_dU_straight(c))


def _dW_angular(c):
    # rotation of the carriage w = G q (tracker frame R_ts G q) for G[a, k] (rad per m of axis k about a)
    out = np.zeros((len(c["dq"]), 3, 9))
    for a in range(3):
        for k in range(3):
            out[:, :, 3 * a + k] = 1e6 * np.outer(c["dq"][:, k], c["R_ts"][:, a])
    return out


def _dU_angular(c):
    # the cameras ride on the carriage: turned by w = G q they see the SMR* (fixed) at
    # R_c^T (-C - A q + w x (A q) - w x (S - p_abbe)) in the body frame. The Abbe part w x (p_abbe - S) is
    # linear in q with an unknown lever (it reads as stage_axis_scale); the carriage turning the travel,
    # w x A q, is bilinear in q with no unknown but G: its part quadratic in q about the mean station (the
    # linear part is absorbed with the Abbe part); the origin of q only moves linear parts
    d = c["dq"] - c["dq"].mean(axis=0)
    Ad = d @ c["A"].T
    out = np.zeros((len(d), 3, 9))
    for a, e in enumerate(np.eye(3)):
        out[:, :, 3 * a:3 * a + 3] = np.cross(e, Ad)[:, :, None] * d[:, None, :]
    return out


def _dX_tracker_scale(c):
    # (1 + s) about the tracker origin: s X; its constant part s X(reference) only moves X*, absorbed
    return 1e6 * (c["dq"] @ (c["R_ts"] @ c["A"]).T)[:, :, None]


def _dX_encoder(c):
    # azimuth / elevation angle-scale errors: the tracker reads (1 + e) times its angles (azimuth about its
    # z axis from x, elevation from the xy plane), so each station's reading moves by e_az az r cos(el)
    # along its azimuth tangent and e_el el r along its elevation tangent, at its own angles. The part
    # common to the stations (X*'s position, a turn of the cell about the tracker) is the nominal fit's;
    # at elevation el the elevation term also turns the cell differently at each azimuth (not rigid), so
    # the tangents are taken per station, not once at the cell
    X = np.asarray(c["X_T"], float)
    r = np.linalg.norm(X, axis=1)
    az, el = np.arctan2(X[:, 1], X[:, 0]), np.arcsin(np.clip(X[:, 2] / np.maximum(r, 1e-12), -1, 1))
    t_az = np.stack([-np.sin(az), np.cos(az), np.zeros_like(az)], 1)
    t_el = np.stack([-np.sin(el) * np.cos(az), -np.sin(el) * np.sin(az), np.cos(el)], 1)
    b = np.stack([(az * r * np.cos(el))[:, None] * t_az, (el * r)[:, None] * t_el], 2)
    return 1e6 * (b - b.mean(0, keepdims=True))


def _dX_centring(c):
    return 1e6 * np.broadcast_to(np.eye(3), (len(c["dq"]), 3, 3)).copy()


def _dX_lag(c):
    # settled stations: the stage is at rest when frames and readings are taken, so a clock offset
    # between tracker and cameras moves nothing (velocity 0)
    return np.zeros((len(c["dq"]), 3, 1))


_CAMERA = "camera"
_CELL = "cell (shared by the cameras)"
CATALOGUE = (
    # ---- optics (per camera)
    PicmsTerm("lens_radial_k1", "lens radial distortion (k1) missing from CameraInfo",
              "the lens bends rays radially by k1 r^2 of the normalised radius; CameraInfo D says 0",
              ("k1",), ("1",), "1 (rms over cameras)", 1.0,
              "a disc pattern spanning the field (wider stage travel), or a lab distortion calibration",
              cam=_b_k1, plausible_max=5.0),
    PicmsTerm("lens_radial_k2", "lens radial distortion (k2, 4th order)",
              "fourth-order radial term k2 r^4 of the lens distortion",
              ("k2",), ("1",), "1 (rms over cameras)", 1.0, "features near the edge of the field",
              cam=_b_k2, plausible_max=500.0),
    PicmsTerm("lens_tangential", "lens decentring (tangential) distortion",
              "lens elements decentred: p1, p2 plumb_bob terms", ("p1", "p2"), ("1", "1"),
              "1 (rms over cameras)", 1.0, "features over the whole field", cam=_b_tangential, plausible_max=0.05),
    PicmsTerm("principal_point_error", "principal-point error in CameraInfo",
              "cx, cy of the camera matrix are off: every image point shifts by the same pixels",
              ("dcx", "dcy"), ("px", "px"), "px (rms)", 1.0,
              "a camera intrinsic calibration; in this cell it is absorbed by the camera rotation",
              cam=_b_pp, plausible_max=200.0),
    PicmsTerm("focal_length_error", "focal-length (image scale) error",
              "the camera's focal length differs from CameraInfo: image coordinates scale about the centre",
              ("df_rel",), ("1",), "1 (rms over cameras)", 1.0,
              "a change of working distance or a scale bar in the field", cam=_b_focal, plausible_max=0.1),
    PicmsTerm("pixel_aspect_error", "pixel aspect-ratio error",
              "fx and fy differ from CameraInfo by different amounts", ("dfx_rel",), ("1",),
              "1 (rms over cameras)", 1.0, "features spread horizontally across the field",
              cam=_b_aspect, plausible_max=0.05),
    PicmsTerm("sensor_skew", "sensor axis skew", "sensor columns not perpendicular to rows",
              ("skew",), ("1",), "1 (rms over cameras)", 1.0, "features spread vertically across the field",
              cam=_b_skew, plausible_max=0.05),
    PicmsTerm("camera_rotation_drift", "camera mount tilt drift (thermal)",
              "the camera mount tilts steadily (about the image axes) as it warms during the session",
              ("wx", "wy"), ("rad", "rad"), "urad over the session (rms over cameras)", 1e6,
              "a longer session, or repeat stations at its start and end; a roll drift needs features "
              "spread across the field", cam=_b_rot_drift, plausible_max=1e4),
    PicmsTerm("camera_position_drift", "camera mount position drift (thermal)",
              "the camera centre moves steadily as the mount expands during the session",
              ("vx", "vy", "vz"), ("m", "m", "m"), "um over the session (rms over cameras)", 1e6,
              "a longer session with repeat stations; sideways drift is told from tilt drift only by "
              "targets at different depths", cam=_b_pos_drift, plausible_max=1e3),
    # ---- stage linear axes (cell)
    PicmsTerm("stage_axis_scale", "stage axis scale (lead) error, differential",
              "the axes travel (1 + s_k) times what their encoders read (ball-screw lead, scale calibration); "
              "the cameras see the differences between axes (a common scale only moves their distance), and "
              "a pitch / yaw / roll of the carriage through the Abbe offset of X* looks the same to them",
              ("sx", "sy", "sz"), ("1", "1", "1"), "ppm (rms over axes, common part removed)", 1e6,
              "a laser interferometer along each axis; telling the angular (Abbe) part apart needs an "
              "autocollimator or the constellation rotation over a longer travel",
              cam=_cam_from_U(_dU_scale), trk=_dX_scale, per_camera=False,
              # lead errors of precision ball-screw grades C0-C7 stay below ~170 ppm; 300 ppm between axes is
              # beyond a precision stage (on a short travel a camera aspect error can look like one)
              plausible_max=300.0),
    PicmsTerm("stage_straightness", "stage straightness (bow of each axis)",
              "each axis bows perpendicular to its travel, quadratically in the reading: c_ak q_k^2",
              tuple(f"bow_{'xyz'[k]}_along_{'xyz'[a]}" for a, k in _STRAIGHT), ("1/m",) * 6,
              "um at 25 mm from the centre of travel (rms over the 6)", 0.025 ** 2 * 1e6,
              "a longer travel (the bow grows with its square), more frames per station (a longer dwell "
              "averages the disc noise down), or a straightedge reversal",
              cam=_cam_from_U(_dU_straight), trk=_dX_straight, per_camera=False, plausible_max=50.0),
    PicmsTerm("stage_angular", "stage angular error motions (pitch, yaw, roll)",
              "the carriage rotates by G q as the axes travel; the tracker sees the constellation turn, the "
              "cameras (riding on the carriage) see the travel turned with it, w x A q, bilinear in q (the "
              "Abbe offset's part is linear in q and reads as stage_axis_scale)",
              tuple(f"about_{'xyz'[a]}_per_{'xyz'[k]}" for a in range(3) for k in range(3)), ("rad/m",) * 9,
              "urad per 25 mm of travel (rms over the 9)", 0.025 * 1e6,
              "a longer travel with the tracker's constellation, more frames per station (a longer dwell "
              "averages the disc noise down), or an autocollimator / electronic level",
              cam=_cam_from_U(_dU_angular), rot=_dW_angular, per_camera=False, plausible_max=1e4),
    # ---- tracker (cell)
    PicmsTerm("tracker_length_scale", "tracker length scale error (or a lead error common to the three axes)",
              "the tracker's lengths are (1 + s) times true (air refractive index, ADM / interferometer scale); "
              "against the encoders it is the same as a common scale error of the stage axes",
              ("s",), ("1",), "ppm", 1e6,
              "a calibrated reference length (scale bar) or a long-travel comparison with an interferometer",
              trk=_dX_tracker_scale, per_camera=False, plausible_max=1000.0),
    PicmsTerm("tracker_angular_encoder", "tracker angular encoder error (azimuth / elevation scale)",
              "the tracker's angle encoders read (1 + e) times the angle turned: a stretch of its readings "
              "along the azimuth and elevation tangents at the cell",
              ("e_az", "e_el"), ("1", "1"), "ppm of the angle (rms)", 1e6,
              "readings over a wide angular range, or a two-face (front / back sight) test of the tracker",
              # 1000 ppm of a 1 rad turn is 1 mrad (2.4 mm at 2.4 m), far beyond a working tracker's angle MPE
              trk=_dX_encoder, per_camera=False, plausible_max=1000.0),
    PicmsTerm("smr_centring", "SMR centring error in its nest",
              "the SMR*'s optical centre is off its sphere centre (or the nest seat): every tracker reading of "
              "X* carries the same offset", ("ex", "ey", "ez"), ("m", "m", "m"), "um (rms over axes)", 1e6,
              "turning the SMR* in its nest between readings (they describe a circle of the centring radius), "
              "or swapping it for another SMR", trk=_dX_centring, per_camera=False, plausible_max=100.0,
              blind="a constant offset of the SMR* reading is absorbed by X*'s position in the tracker frame "
                    "(it biases the calibrated X* by exactly the centring error)"),
    PicmsTerm("tracker_timing_lag", "timing lag between the tracker's and the stage's clocks",
              "the tracker's stamps are offset from the stage's (and the cameras', which share them) by a constant "
              "lag; a reading then belongs to another stage position", ("lag",), ("s",), "ms", 1e3,
              "tracker readings while the stage moves (the moves between stations of any session: the lag is the "
              "displacement over the speed)", trk=_dX_lag, per_camera=False, plausible_max=1e3,
              # measured on the moves between stations instead (core/timing_lag.py, run(motion=...))
              blind="the settled stations cannot show it: the stage is at rest when frames and readings are "
                    "taken, so a clock offset moves nothing there"),
)
MIN_STATIONS = 15
CATALOGUE_BY_ID = {t.id: t for t in CATALOGUE}
#: residual components: image u, v (px); tracker x, y, z (um); constellation rotation x, y, z (urad)
COMPONENTS = ("u", "v", "tracker_x", "tracker_y", "tracker_z", "rotation_x", "rotation_y", "rotation_z")


def _camera_block(result, camera_info, U, obs, cov, cams, dA, tnorm, n_pose, p_nom, k1_secant=None):
    """Rows, Jacobian and context of the disc-centre residuals (px). ``k1_secant``: per camera, the k1
    at which the lens term's basis is the secant (None: the tangent, k1 -> 0)."""
    rows = {"r": [], "J": [], "sig": [], "comp": [], "st": [], "cam": []}
    ctx = {k: [] for k in ("jdist", "n", "f", "t", "jrot", "jpos", "ju", "ok", "idx", "edge")}
    edges = result.design.get("edges_px")
    row = 0
    for j, c in enumerate(cams):
        cr = result.cameras[c]
        R, C = np.asarray(cr.R_stage_camera), np.asarray(cr.p_stage_centre)
        f = float(camera_info[c].f_px)
        ok = np.where(np.isfinite(obs[j, :, 0]))[0]
        pc = (U[ok] - C) @ R
        n = pc[:, :2] / pc[:, 2:3]
        jr, jp, ju = (np.zeros((len(ok), 2, 3)) for _ in range(3))
        for m, i in enumerate(ok):
            x, y, z = pc[m]
            P = np.array([[1 / z, 0, -x / z ** 2], [0, 1 / z, -y / z ** 2]])
            jr[m] = f * P @ _skew(pc[m])
            jp[m] = -f * P @ R.T
            ju[m] = f * P @ R.T
            Jrow = np.zeros((2, p_nom))
            Jrow[:, 6 * j:6 * j + 3] = jr[m]
            Jrow[:, 6 * j + 3:6 * j + 6] = jp[m]
            for k in range(3):
                Jrow[:, n_pose + k] = ju[m] @ dA[k][i]
            r = f * (obs[j, i] - n[m])
            sd = f * np.sqrt(np.diag(cov[j, i]))
            for a in range(2):
                rows["r"].append(r[a])
                rows["J"].append(Jrow[a])
                rows["sig"].append(sd[a])
                rows["comp"].append(a)
                rows["st"].append(i)
                rows["cam"].append(j)
        ctx["n"].append(n)
        D = np.asarray(camera_info[c].D, float)
        ctx["jdist"].append(_distort_jacobian(D, n))
        if edges is not None and all(edges[j][i] is not None and len(edges[j][i]) >= 10 for i in ok):
            # the tangent (k1 -> 0) on the first pass; the secant at k1 ~ -0.3 differs by ~1 % of the shift,
            # nearly all of it along the shift, so the size comes out ~1 % large: :func:`run` measures again
            # with the secant at the first pass's k1 (doc/picms_discrepancy.md)
            k1s = 1e-4 if k1_secant is None or not np.isfinite(k1_secant[j]) or abs(k1_secant[j]) < 1e-4 \
                else float(k1_secant[j])
            steps = _steps(camera_info[c], EDGE_TERMS, k1s)
            ctx["edge"].append(f * np.array([_silhouette_shifts(camera_info[c], edges[j][i], obs[j, i], steps)
                                             for i in ok]))       # (m, 2, 5): EDGE_TERMS
        else:
            ctx["edge"].append(None)
        ctx["f"].append(f)
        ctx["t"].append(tnorm[ok])
        ctx["jrot"].append(jr)
        ctx["jpos"].append(jp)
        ctx["ju"].append(ju)
        ctx["ok"].append(ok)
        ctx["idx"].append(np.arange(row, row + 2 * len(ok)).reshape(-1, 2))
        row += 2 * len(ok)
    return rows, ctx


def _tracker_blocks(result, d, sq, dq, p_nom, c_trk):
    """Rows and Jacobian of the tracker link (um) and the constellation rotation (urad)."""
    rows = {"r": [], "J": [], "sig": [], "comp": [], "st": [], "cam": []}
    X, q = np.asarray(d["X_T"]), np.asarray(d["q"])
    sx = np.sqrt(np.maximum(np.diag(np.asarray(d["cov_X"])), 0)).reshape(-1, 3) * 1e6
    W = np.asarray(d["W_T"])
    sw = np.sqrt(np.maximum(np.diag(np.asarray(d["cov_W"])), 0)).reshape(-1, 3) * 1e6
    R, p0 = np.asarray(result.R_tracker_stage), np.asarray(result.p_tracker_stage)
    A = travel_matrix(sq)
    h = 1e-7
    dAk = [(travel_matrix(sq + h * e) - travel_matrix(sq - h * e)) / (2 * h) for e in np.eye(3)]
    for i in range(len(q)):
        model = p0 + R @ A @ q[i]
        Jr = np.zeros((3, p_nom))
        for k in range(3):
            Jr[:, c_trk - 3 + k] = 1e6 * R @ dAk[k] @ q[i]        # squareness (shared with the cameras)
        Jr[:, c_trk:c_trk + 3] = 1e6 * np.eye(3)                  # X* at encoder 0, tracker frame
        Jr[:, c_trk + 3:c_trk + 6] = -1e6 * R @ _skew(A @ q[i])    # stage frame orientation
        for a in range(3):
            if sx[i, a] > 0:
                rows["r"].append(1e6 * (X[i, a] - model[a]))
                rows["J"].append(Jr[a])
                rows["sig"].append(sx[i, a])
                rows["comp"].append(2 + a)
                rows["st"].append(i)
                rows["cam"].append(-1)
    for i in range(1, len(q)):                                     # the reference's own rotation is exact (0)
        Jw = np.zeros((3, p_nom))
        Jw[:, c_trk + 6:c_trk + 9] = 1e6 * np.eye(3)              # the reference station's rotation error
        for a in range(3):
            if sw[i, a] > 0:
                rows["r"].append(1e6 * W[i, a])
                rows["J"].append(Jw[a])
                rows["sig"].append(sw[i, a])
                rows["comp"].append(5 + a)
                rows["st"].append(i)
                rows["cam"].append(-1)
    return rows


def build(result: CalibrationResult, camera_info: dict, n_folds: int = 5, k1_secant=None):
    """Dataset, candidates and context arrays from a calibration. Raises ValueError on an unusable one.
    ``k1_secant``: per camera, the k1 at which the lens k1 basis is taken as the secant (None: tangent)."""
    d = result.design
    if not d or "obs" not in d:
        raise ValueError("calibration carries no pose-fit design (U, obs): nothing to analyse")
    U, obs, cov = np.asarray(d["U"]), np.asarray(d["obs"]), np.asarray(d["obs_cov"])
    cams = list(d["cameras"])
    sq = np.asarray(d["sq"], float)
    A = travel_matrix(sq)
    dq = -U @ np.linalg.inv(A).T                  # U = -(dq A^T)
    N = U.shape[0]
    if N < MIN_STATIONS:
        raise ValueError(f"{N} settled stations: too few for a discrepancy verdict (the noise floor and the "
                         f"held-out folds need >= {MIN_STATIONS}; 6 pose parameters per camera leave too few "
                         "degrees of freedom); record the grid acquisition (grid_pattern(), 33 stations)")
    dA = []
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1e-7
        dA.append(-(dq @ ((travel_matrix(sq + e) - travel_matrix(sq - e)) / 2e-7).T))   # (N, 3)
    if "t_ns" in d and N > 1 and np.ptp(d["t_ns"]) > 0:   # linear in time (drift), -0.5 .. 0.5 over the session
        t = np.asarray(d["t_ns"], float)
        tnorm = (t - t[0]) / (t[-1] - t[0]) - 0.5
    else:
        tnorm = np.linspace(-0.5, 0.5, N) if N > 1 else np.zeros(1)
    n_pose = 6 * len(cams)
    has_trk = "X_T" in d
    c_trk = n_pose + 3
    p_nom = c_trk + (9 if has_trk else 0)
    rows, ctx = _camera_block(result, camera_info, U, obs, cov, cams, dA, tnorm, n_pose, p_nom, k1_secant)
    n_cam = len(rows["r"])
    q = np.asarray(d.get("q", dq), float)
    ctx.update(A=A, dq=dq, dq2=q * q - q[0] * q[0], R_ts=np.asarray(result.R_tracker_stage),
               X_T=np.asarray(d.get("X_T", np.zeros((N, 3)))))
    if has_trk:
        tr = _tracker_blocks(result, d, sq, q - q[0], p_nom, c_trk)
        for k in rows:
            rows[k] += tr[k]
    residual = np.array(rows["r"])
    nn = residual.size
    if n_cam < 2 * p_nom:
        raise ValueError(f"{n_cam} disc-centre residuals for {p_nom} nominal parameters: too few stations to analyse")
    comp, st_of, cam_of = np.array(rows["comp"]), np.array(rows["st"]), np.array(rows["cam"])
    # neighbours: same camera (or block) and component, consecutive stations
    pairs = []
    for j in sorted(set(cam_of.tolist())):
        for a in sorted(set(comp[cam_of == j].tolist())):
            ii = np.where((cam_of == j) & (comp == a))[0]
            pairs += list(zip(ii[:-1], ii[1:]))
    fold = (st_of * n_folds) // max(N, 1)
    # locate axes (disc centres): time (station order) per camera, sensor field per camera
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
    names = tuple(f"{c}.{p}" for c in cams for p in ("rx", "ry", "rz", "cx", "cy", "cz")) + \
        ("squareness_xy", "squareness_xz", "squareness_yz")
    if has_trk:
        names += ("x_star_tracker_x", "x_star_tracker_y", "x_star_tracker_z", "stage_frame_rx", "stage_frame_ry",
                  "stage_frame_rz", "reference_rotation_x", "reference_rotation_y", "reference_rotation_z")
    rms_rows = np.zeros(nn, bool)
    rms_rows[:n_cam] = True
    ds = Dataset(residual=residual, jac=np.array(rows["J"]), nominal_names=names, sigma=np.array(rows["sig"]),
                 component=comp, group=st_of, neighbours=np.array(pairs, int), fold=fold,
                 empirical={"station order (time)": emp_t, "sensor field": emp_f}, unit="px", rms_rows=rms_rows,
                 # no shift is shared by a station's three cameras in pixels (a station's 3-D error moves
                 # each camera's disc its own way), and three members per station are too few to estimate
                 # one: an effect linear in the stage position was taken for it (discrepancy.noise_floor)
                 shared_shift=False,
                 # stations 4 mm apart: a strong effect (a lens k1 of tens of px) inflates the neighbour-difference
                 # floor ~4x; the refit and the findings' uncertainties use the floor after the terms
                 refloor_after=True)
    tk_rows = np.where(comp >= 2)[0]
    tk_idx = {(int(st_of[r]), int(comp[r])): r for r in tk_rows}
    cands = []
    for t in CATALOGUE:
        p = len(t.params)
        width = p * len(cams) if t.per_camera else p
        B = np.zeros((nn, width))
        if t.cam is not None:
            for j in range(len(cams)):
                b = t.cam(ctx, j)                      # (m, 2, p)
                cols = slice(j * p, (j + 1) * p) if t.per_camera else slice(0, p)
                for a in range(2):
                    B[ctx["idx"][j][:, a], cols] += b[:, a, :]
        for fn, c0 in ((t.trk, 2), (t.rot, 5)):
            if fn is not None and has_trk:
                b = fn(ctx)                            # (N, 3, p)
                for i in range(N):
                    for a in range(3):
                        r = tk_idx.get((i, c0 + a))
                        if r is not None:
                            B[r] = b[i, a]
        groups = len(cams) if t.per_camera else p
        scale = np.full(width, t.display)
        mag = (lambda th, s=t.display, g=groups: float(np.sqrt(np.sum((np.asarray(th) * s) ** 2) / g)))
        cands.append(Candidate(id=t.id, name=t.name, mechanism=t.mechanism,
                               param_names=tuple(f"{c}.{q}" for c in cams for q in t.params) if t.per_camera
                               else t.params,
                               param_units=tuple(u for _ in cams for u in t.units) if t.per_camera else t.units,
                               basis=B, magnitude_unit=t.display_unit, display_scale=scale, reveal_by=t.reveal_by,
                               magnitude=mag, plausible_max=t.plausible_max))
    return ds, cands, {"cameras": cams, "n_stations": N, "cam_of": cam_of[:n_cam], "station_of": st_of[:n_cam],
                       "comp": comp[:n_cam], "n_cam_rows": n_cam, "has_tracker": has_trk}


def _groups(t: PicmsTerm, n_cams: int) -> int:
    return n_cams if t.per_camera else len(t.params)


MOVING_BLOCK = "tracker readings while the stage moves"


def judge(result: CalibrationResult, camera_info: dict, motion=None, *, max_terms: int = 3):
    """The engine's verdict on a fresh calibration, for the live calibration node.

    Returns (out or None, state, text, settled): state "adequate", "inadequate" or "insufficient" (too few
    stations or data for a verdict: text says why); ``settled`` is true when a finding or unexplained
    structure sits in the data the calibration rests on (the settled stations), so the calibration itself
    is in doubt; a lag seen only on the moves between stations is not."""
    try:
        out = run(result, camera_info, motion=motion, max_terms=max_terms)
    except ValueError as exc:
        return None, "insufficient", str(exc), False
    if out["adequate"]:
        return out, "adequate", out["verdict"], False
    settled = [f for f in out["findings"] if f.get("block") != MOVING_BLOCK]
    return out, "inadequate", out["verdict"], bool(settled or out["unexplained"])


def motion_of(rec) -> dict:
    """The moving part of a recording (campaign.Recording or the offline reader's) for :func:`run`."""
    return {"joint_stamps_ns": rec.joint_stamps_ns, "joint_positions": rec.joint_positions, "tracker": rec.tracker,
            "constellation": list(rec.cell.get("tracker", {}).get("constellation", []))}


def _timing(motion, limits, findings, by_id, say):
    """tracker_timing_lag from the readings taken while the stage moves (core/timing_lag.py): its limit,
    and a finding when it is significant and predicts held-out moves better; the estimate's dict."""
    t = CATALOGUE_BY_ID["tracker_timing_lag"]
    if motion is None:
        return {"seen": False, "reason": "no stage or tracker streams given (settled stations only)"}
    try:
        lag = timing_lag.estimate(motion["joint_stamps_ns"], motion["joint_positions"], motion["tracker"],
                                  motion["constellation"])
    except (ValueError, np.linalg.LinAlgError) as exc:
        lag = {"seen": False, "reason": f"the moving readings could not be analysed: {exc}"}
    if not lag["seen"]:
        limits[t.id]["cannot_see"] = f"{t.blind}; and here: {lag['reason']}"
        return lag
    n, u = lag["n_readings"], lag["u_lag_s"]
    ln_n = np.log(n)
    lam = required_noncentrality(ln_n + BIC_THRESHOLD, 1)
    limits[t.id] = {"limit": float(np.sqrt(lam) * u * 1e3), "unit": "ms", "reveal_by": t.reveal_by,
                    "from": f"{n} constellation readings while the stage moved ({lag['n_moves']} moves)"}
    d = (lag["lag_s"] / u) ** 2
    gain = (lag["held_out_rms_before_m"] ** 2 - lag["held_out_rms_after_m"] ** 2) / lag["sigma_m"] ** 2
    say(f"timing lag: {lag['lag_s'] * 1e3:.3f} +- {u * 1e3:.3f} ms from {n} moving readings; held-out rms "
        f"{lag['held_out_rms_before_m'] * 1e6:.1f} -> {lag['held_out_rms_after_m'] * 1e6:.1f} um")
    if d - ln_n >= BIC_THRESHOLD and gain > 0:
        f = {"significance_sigma": sigma_from_chi2(d, 1), "delta_bic": float(d - ln_n), "cv_gain": float(gain),
             "degenerate_with": [], "correlated_nominal": []}
        e = finding_entry(by_id[t.id], f, [lag["lag_s"]], [u], abs(lag["lag_s"]) * 1e3, u * 1e3, "ms", set())
        e.update(block=MOVING_BLOCK,
                 held_out_rms_before_um=lag["held_out_rms_before_m"] * 1e6,
                 held_out_rms_after_um=lag["held_out_rms_after_m"] * 1e6)
        findings.append(e)
        findings.sort(key=lambda x: -x["delta_bic"])
    return lag


def _timing_verdict(f0, lag, others) -> str:
    late = "late" if lag["lag_s"] > 0 else "early"
    out = (f"The nominal model leaves out a clock offset between the tracker and the stage: the tracker's stamps "
           f"run {abs(lag['lag_s']) * 1e3:.3g} +- {lag['u_lag_s'] * 1e3:.2g} ms {late} ({f0['significance_sigma']:.1f} "
           f"sigma, {lag['n_readings']} constellation readings while the stage moved); with it their held-out "
           f"residual falls from {lag['held_out_rms_before_m'] * 1e6:.3g} to {lag['held_out_rms_after_m'] * 1e6:.3g} um "
           f"(reading scatter {lag['sigma_m'] * 1e6:.3g} um). The settled stations the calibration uses are not "
           f"affected.")
    if others:
        out += " Also: " + "; ".join(f"{f['name']} ({f['magnitude']:.3g} {f['magnitude_unit']})" for f in others) + "."
    return out


def run(result: CalibrationResult, camera_info: dict, *, progress=None, max_terms: int = 3, motion=None) -> dict:
    """The Pixel Probe analysis; the discrepancy.json dict (same keys as CT) plus ``_arrays``.

    motion: :func:`motion_of` the recording (joint_states, tracker readings, constellation names), for the
    terms only the moves between stations show (tracker_timing_lag); None: settled stations only."""
    say = progress or (lambda _m: None)
    ds, cands, ext = build(result, camera_info)
    nc = len(ext["cameras"])
    say(f"{ext['n_cam_rows']} disc-centre residuals ({nc} cameras, {ext['n_stations']} stations), "
        f"{ds.residual.size - ext['n_cam_rows']} tracker-link residuals; {len(cands)} catalogue terms")
    res = analyse(ds, cands, max_terms=max_terms, progress=say, refine=True)
    if "lens_radial_k1" in res["chosen"]:
        # k1 ~ -0.3 is far from the tangent the basis was taken at: the size came out large by 1.0 % +- 0.8 %
        # (20 seeds; its sd is the seeds' scatter). Once more with the secant at this k1: -0.2 % +- 0.8 %.
        th = next(np.asarray(f["theta"], float) for f in res["findings"] if f["term"] == "lens_radial_k1")
        if th.size == nc:
            say(f"lens k1 {np.round(th, 4).tolist()} per camera: analysed again with the secant basis there")
            ds, cands, ext = build(result, camera_info, k1_secant=th)
            res = analyse(ds, cands, max_terms=max_terms, progress=say, refine=True)
    by_id = {c.id: c for c in cands}
    findings = []
    for f in res["findings"]:
        c = by_id[f["term"]]
        g_n = _groups(CATALOGUE_BY_ID[c.id], nc)
        th, ct = np.asarray(f["theta"]), np.asarray(f["theta_cov"])
        u = np.sqrt(np.maximum(np.diag(ct), 0))
        mag = c.mag(th)
        g = np.zeros_like(th)
        if mag > 0:
            g = (th * c.display_scale ** 2) / (g_n * mag)
        mag_u = float(np.sqrt(max(g @ ct @ g, 0.0)))
        sep = {c.reveal_by} | {by_id[d].reveal_by for d in f["degenerate_with"]}
        findings.append(finding_entry(c, f, th, u, mag, mag_u, c.magnitude_unit, sep))
    limits = {}
    for c in cands:
        lim, t = res["limits"][c.id], CATALOGUE_BY_ID[c.id]
        if not np.any(c.basis):
            limits[c.id] = {"limit": None, "unit": c.magnitude_unit, "reveal_by": c.reveal_by,
                            "cannot_see": t.blind or "no residual of this recording responds to it"}
        elif lim["absorbed_fraction"] > 1 - 1e-7 or not np.isfinite(lim["limit"]):
            limits[c.id] = {"limit": None, "unit": c.magnitude_unit, "reveal_by": c.reveal_by,
                            "cannot_see": t.blind or "absorbed by the calibrated parameters in this acquisition"}
        else:
            # the engine's limit is on the parameter vector's smallest-eigen direction (display units);
            # our magnitude is an rms over cameras or parameters
            limits[c.id] = {"limit": lim["limit"] / np.sqrt(_groups(t, nc)), "unit": c.magnitude_unit,
                            "reveal_by": c.reveal_by, "absorbed_fraction": lim["absorbed_fraction"]}
    lag = _timing(motion, limits, findings, by_id, say)
    unexplained = unexplained_entries(res["unexplained"])
    adequate = not findings and not unexplained
    fl = res["floor"]
    floor_d = fl.to_dict("px (u, v); um (tracker_*); urad (rotation_*)", COMPONENTS[:len(fl.factor)])
    floor_d["stated_sigma_median_px"] = float(np.median(ds.sigma[:ext["n_cam_rows"]]))
    for a, name in enumerate(COMPONENTS[:len(fl.factor)]):     # the engine states them at the overall median
        floor_d["independent_sd"][name] = float(fl.factor[a] * np.median(ds.sigma[ds.component == a]))
    if res.get("floor_after") is not None:         # the floor the refit and the findings' u are stated under
        fa = res["floor_after"]
        floor_d["after_terms"] = {
            "independent_sd": {name: float(fa.factor[a] * np.median(ds.sigma[ds.component == a]))
                               for a, name in enumerate(COMPONENTS[:len(fa.factor)])},
            "u_factor": float(res["after"].get("u_factor", 1.0)),
            "note": "the joint fit and the findings' uncertainties are stated under this floor (the residuals' "
                    "after the findings; the floor above, of the residuals before, decides the names), times "
                    "u_factor (the Birge ratio of that fit, at least 1)"}
    sd = fl.factor[:2] * floor_d["stated_sigma_median_px"]

    def fmt(key, unit):
        v = limits[key]["limit"]
        return "not observable" if v is None or not np.isfinite(v) else f"{v:.3g} {unit}"
    verdict = verdict_sentence(
        findings, unexplained, name_of={t.id: t.name for t in CATALOGUE}, n_obs=ext["n_cam_rows"] // 2,
        obs_noun="disc centres", floor_sd=sd, floor_axes="u / v", held_out_before=res["before"]["held_out_rms"],
        held_out_after=res["after"]["held_out_rms"],
        clean_examples=(f"no lens k1 above {fmt('lens_radial_k1', '')}, no differential stage axis scale above "
                        f"{fmt('stage_axis_scale', 'ppm')} and no camera tilt drift above "
                        f"{fmt('camera_rotation_drift', 'urad')} over the session").replace(" ,", ","))
    if findings and findings[0]["term"] == "tracker_timing_lag":
        verdict = _timing_verdict(findings[0], lag, findings[1:])
    xr = np.hstack([ds.jac] + [by_id[i].basis for i in res["chosen"]])
    r_after = ds.residual - xr @ res["beta"]
    m = ext["n_cam_rows"]
    return {
        "verdict": verdict, "adequate": bool(adequate), "noise_floor": floor_d,
        "fit_before": res["before"], "fit_after": res["after"], "findings": findings, "unexplained": unexplained,
        "located": [dict(e) for e in res["located"]], "detection_limits": limits,
        "catalogue": [{"id": t.id, "name": t.name, "mechanism": t.mechanism, "parameters": list(t.params),
                       "units": list(t.units), "per": _CAMERA if t.per_camera else _CELL,
                       "magnitude_unit": t.display_unit, "reveal_by": t.reveal_by,
                       "residual_blocks": [b for b, fn in (("camera", t.cam), ("tracker link", t.trk),
                                                           ("constellation rotation", t.rot)) if fn is not None]}
                      for t in CATALOGUE],
        "n_observations": int(m // 2), "n_tracker_residuals": int(ds.residual.size - m),
        "n_stations": ext["n_stations"], "bic_threshold": BIC_THRESHOLD,
        "timing_lag": {k: v for k, v in lag.items() if k != "per_move"},
        "_arrays": {"residual_before": ds.residual[:m], "residual_after": r_after[:m], "station": ext["station_of"],
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
