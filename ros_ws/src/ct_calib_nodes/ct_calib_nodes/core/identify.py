"""Sphere identity: which detected shadow belongs to which calibrated sphere.

Uses only what a recording carries: the detected centres of each frame, the
rotary angle alpha, the instrument's nominal geometry (reported SRD, stated
SDD, detector size and pitch) and the reference object's calibrated centres
and diameters; optionally a solved geometry from the solver.

Method
------
``SphereIdentifier.initialise`` places the object on the NOMINAL instrument
(source, axis at the reported SRD, detector perpendicular at the stated SDD,
centred) and searches its pose:

1. coarse, for an object whose centres lie on one cylinder about its Y axis
   (helix49): a lean vote (``_lean_starts``). For each trial lean of the
   object's axis (grid of ``lean_step_deg`` = 1 deg up to
   ``lean_search_deg`` = 15 deg from the rotation axis, both orientations),
   each detection's ray (nominal instrument, undone by the table rotation)
   meets the cylinder at two points, each an (axial height, azimuth) on the
   object; the right lean puts them onto the calibrated (h_i, phi_i) moved by
   one (height offset, spin), so every detection votes for (h - h_i,
   phi - phi_i) over all spheres and the lean whose vote peaks highest wins
   (labelling and spin need not be known to vote, so the lean is searched
   apart from rho_Y and height). The 12 best distinct leans are fitted on the
   detections their peak labels (robust least squares), scored with the
   truncated nearest-neighbour cost below, and the ``n_starts`` best go on.
   A winning pose leaning more than ``lean_accept_deg`` (12 deg) is refused.
   The vote runs only when the initialisation frames span ``lean_min_arc_deg``
   (1 deg) of rotation: one view does not observe the lean (a pose leaning
   23 deg explained one frame of the upright object to 0.026 px).
   Before (round 19) the object was held upright here and a lean beyond ~2 deg
   was refused on most instruments (ct_detect.md, "Independent renderer
   check", failure 3). Other objects: rho_Y over 360 deg in 2-deg steps,
   the object upright or upside
   down (rho_X = 0 or pi, rho_Z = 0), its origin on the axis, a lateral offset and height
   that match the mean detected position, plus a height grid of +-4 mm in
   1 mm steps; each candidate is scored by a truncated nearest-neighbour cost
   over all initial frames (``sum min(d, gate)^2``), robust to missed and
   spurious detections; this grid does not search a lean (the fine stage
   takes up ~2 deg);
2. fine, from each of the 6 best distinct coarse poses: alternate gated,
   mutually unique nearest-neighbour matching and a least-squares fit of
   x_D, eta, x_P, y_P, z_P, rho_X, rho_Y, rho_Z (z_R, z_D, theta, phi stay
   nominal, y_D is absorbed by y_P) over the matched points, with a
   shrinking gate;
3. screw shifts: a helix is invariant under a screw motion (helix49 to
   5e-10 m), and the relabelling i -> i + k fits every sphere but the k end
   spheres to a fraction of a pixel. The calibrated centres are checked for
   such shifts (k = +-1 .. +-3 in the file's order) when the identifier is
   made; the best refined pose (with the lean vote: of each orientation, as
   the vote is blind to a screw shift) composed with each motion is refined
   and scored too, so the coarse search need not have started every labelling;
4. decision: the refined pose that leaves the fewest detections unmatched and
   the fewest predicted spheres undetected that the detector would have found
   (inside the detector, outline 6 px or more from every other shadow:
   ``isolated_gap_px``) wins, and it must beat every other labelling by
   ``min_margin``. Only the end spheres tell the screw shifts apart; when they
   do not (ends hidden behind neighbours in these frames) a pose that fits is
   refused with a message naming the screw symmetry (the replay then tries
   the next frames). Counting every predicted sphere 2 px clear of its
   neighbours as "missing" (before round 19) buried the end spheres under
   ~100 spheres the detector refuses anyway, and 12 of 22 independent
   recordings came out labelled 1-3 spheres along, reported as success.
5. orientation: the search covers the object upright (as in its calibration
   frame) and turned upside down (rho_X = pi). When both explain the frames
   alike, the calibrated centres decide: an object whose centres map onto
   themselves under that turn (relabelled; the ideal helix49 does, i -> 50 - i)
   to within ``symmetric_tolerance_m`` gives the same instrument geometry
   either way (upright labelling taken, said in the message); otherwise the
   pose whose residuals are ``flip_ms_ratio`` times smaller wins, or the
   initialisation refuses and says why. A failed search tries the frames
   mirrored (columns, rows) and the rotation reversed, and says "check image
   orientation / rotation direction", naming the variant that fits.

``assign`` then predicts every sphere at the frame's alpha and assigns each
detection to its nearest prediction if (a) it is within ``gate_px``, (b) no
other prediction lies within two predicted shadow radii (+ margin) of the
detection (two spheres in one blob: ``ambiguous_identity``), and (c) no other
detection claims the same sphere (``ambiguous_identity``). Otherwise the id
is -1 with a reason. A sphere id is never used twice in one frame.

Before the tight assignment a loose first pass (3x gate) estimates a 2-D
shift and scale about the detector centre from the matched set (median
based), which absorbs slow drifts and, at a new stage position, the error of
predicting with the nominal stage travel.

For stage positions k > 1 either call ``initialise`` again with the new
reported SRD (the pose search does not need the k = 1 result), or hand the
solved geometry over with ``update_geometry`` (static parameters at k = 1
plus the motion of position k, or the nominal travel only).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from .geometry import (
    DetectorSpec,
    cylinder_about_y,
    forward_df,
    forward_srf,
    object_rotation,
    rot_x,
    rot_y,
    sphere_centres_df,
    static_to_detector_frame,
)

__all__ = ["IdentifySettings", "InitialisationResult", "Assignment", "SphereIdentifier",
           "ASSIGN_REASONS"]

ASSIGN_REASONS = ("ok", "unmatched", "ambiguous_identity", "not_initialised")

# indices into the 13 static parameters (geometry.py order)
_FREE = np.array([1, 6, 7, 8, 9, 10, 11, 12])   # x_D, eta, x_P, y_P, z_P, rho_X, rho_Y, rho_Z


def _arc_deg(alphas) -> float:
    """Rotary arc covered by the angles [deg]: 360 less the largest gap between neighbours on the circle."""
    a = np.sort(np.mod(np.asarray(alphas, dtype=np.float64).reshape(-1), 2 * np.pi))
    if a.size < 2:
        return 0.0
    gaps = np.diff(np.concatenate([a, a[:1] + 2 * np.pi]))
    return float(np.degrees(2 * np.pi - gaps.max()))


@dataclass(frozen=True)
class IdentifySettings:
    """Tuning of :class:`SphereIdentifier`.

    Attributes
    ----------
    gate_px : float or None
        Largest accepted distance detection -> prediction [px]; None: 0.35 x
        the smallest predicted shadow radius (about 3.5 px at SRD 364 mm,
        1.9 px at 724 mm) but at least 1.5 px.
    separation_margin_px : float
        A detection with a second prediction closer than two predicted shadow
        radii plus this margin is ``ambiguous_identity``.
    coarse_step_deg : float
        rho_Y step of the coarse pose search.
    coarse_gate_px : float or None
        Truncation of the coarse score; None: one predicted shadow diameter.
    height_search_m, height_step_m : float
        Object-height grid of the coarse search around the height that
        matches the mean detected row [m]. A helix is (nearly) invariant
        under a screw motion (one sphere step up and one azimuth step round),
        so the poses that relabel i -> i +- 1 fit all but the end spheres:
        the grid makes sure these hypotheses are started and compared.
    n_starts : int
        Distinct coarse minima refined and compared.
    min_margin : int
        The best hypothesis must leave at least this many fewer detections
        or visible isolated spheres unexplained than the runner-up, else the
        initialisation fails instead of guessing.
    upside_down : bool
        Also search the object turned upside down (180 deg about its X axis).
    symmetric_tolerance_m : float
        When the upright and the upside-down pose explain the frames equally,
        an object whose calibrated centres map onto themselves under that turn
        (relabelled) to within this rms [m] is symmetric: either labelling gives
        the same instrument geometry, and the upright one is taken.
    flip_ms_ratio : float
        Otherwise the upright / upside-down question is decided only when one
        pose's mean squared residual is this many times smaller than the
        other's; else the initialisation refuses, naming why.
    isolated_gap_px : float
        A predicted sphere counts as missing (no detection near it) only when its shadow lies inside the
        detector and its outline is at least this far from every other predicted shadow [px]: the detector
        refuses shadows within 4 px of a neighbour (detect.py ``proximity_margin_px``) and finds only part
        of those at 4-6 px (ct_detect.md), so closer spheres say nothing about a pose.
    screw_shifts : int
        Screw symmetry: the calibrated centres shifted by k places in the file's order (k = +-1 ..
        +-screw_shifts) that map onto the unshifted ones by a rigid motion to within ``screw_tolerance_m``
        rms (helix49 does, to 5e-10 m) give labellings that fit every sphere but the k end spheres. The
        best pose is composed with each such motion and the shifted labellings are scored like any other
        hypothesis (the coarse search need not start them).
    screw_tolerance_m : float
        Rms [m] below which a shift counts as a screw symmetry.
    follow_pose : bool
        Refit the identification pose on the frames assigned so far whenever the
        rotation has covered twice the arc the pose was last fitted on (and at
        least ``follow_min_step_deg`` more), until it rests on half a turn. A pose
        found on a few frames 1 deg apart extrapolates badly a quarter turn later;
        without this, scans with fine angular steps lose identity mid-rotation.
    follow_min_step_deg : float
        Smallest extra arc that triggers a refit [deg].
    follow_frames : int
        Frames (evenly spread over the arc covered) used by each refit.
    lean_search_deg : float
        Lean search (objects whose centres lie on a cylinder about their Y axis, as helix49): leans of the
        object's axis up to this angle from the rotation axis are searched [deg]; 0 switches it off.
    lean_accept_deg : float
        A pose found leaning more than this (or than ``lean_search_deg`` less one step) is refused [deg]:
        measured with the independent renderer's instruments, none was labelled wrong up to 11.7 deg, one
        at 13.9 deg was (fitted at 0.12 px, with the search at 12 and at 15 deg; ct_detect.md).
    lean_step_deg : float
        Grid step of the lean search [deg].
    lean_starts : int
        Distinct lean hypotheses (the best of the vote) fitted on the detections their vote labels; the
        ``n_starts`` best fits are refined and compared.
    cylinder_tolerance_m : float
        The lean search runs only when every calibrated centre lies this close to the cylinder about the
        object's Y axis through its mean [m].
    lean_min_arc_deg : float
        The lean search runs only when the initialisation frames span at least this rotary arc [deg]; with
        less (one frame) the object is held upright as before round 21. One view does not observe the lean
        (the upright object was refused as leaning 23 deg); from 2 frames 1 deg apart the vote did better
        than the upright search (ideal detector, lean up to 5 deg, 12 instruments: 6 right / 0 wrong / 6
        refused against 2 / 2 / 8; ct_detect.md).
    """

    gate_px: float | None = None
    separation_margin_px: float = 2.0
    coarse_step_deg: float = 2.0
    coarse_gate_px: float | None = None
    height_search_m: float = 4e-3
    height_step_m: float = 1e-3
    n_starts: int = 6
    min_margin: int = 2
    upside_down: bool = True
    symmetric_tolerance_m: float = 2e-6
    flip_ms_ratio: float = 3.0
    isolated_gap_px: float = 6.0
    screw_shifts: int = 3
    screw_tolerance_m: float = 5e-4
    follow_pose: bool = True
    follow_min_step_deg: float = 10.0
    follow_frames: int = 12
    lean_search_deg: float = 15.0
    lean_accept_deg: float = 12.0
    lean_step_deg: float = 1.0
    lean_starts: int = 12
    cylinder_tolerance_m: float = 5e-4
    lean_min_arc_deg: float = 1.0


@dataclass(frozen=True)
class InitialisationResult:
    """Outcome of the pose search.

    Attributes
    ----------
    estimate : ndarray of shape (13,)
        Static parameters of the identification model (nominal instrument with
        the fitted object pose; NOT a calibration result).
    residuals : ndarray of shape (2 Q,)
        Reprojection residuals of the Q matched detections [px].
    rms_px : float
    n_matched, n_detections : int
    cost : float
        0.5 sum residuals^2 [px^2].
    success : bool
        rms below the gate and at least 60 % of the detections matched.
    message : str
    nfev : int
    covariance : None
        Not computed (identification model only).
    """

    estimate: np.ndarray
    residuals: np.ndarray
    rms_px: float
    n_matched: int
    n_detections: int
    cost: float
    success: bool
    message: str
    nfev: int
    covariance: None = None


@dataclass(frozen=True)
class Assignment:
    """Identity of the M detections of one frame.

    Attributes
    ----------
    ids : ndarray of shape (M,), int
        Sphere id, -1 where rejected.
    reasons : tuple of str, length M
        ``ok``, ``unmatched``, ``ambiguous_identity`` or ``not_initialised``.
    residual_px : ndarray of shape (M,)
        Distance to the assigned (or nearest) prediction [px].
    predicted_px : ndarray of shape (N, 2)
        Predicted centres of all N spheres (after the shift/scale update).
    """

    ids: np.ndarray
    reasons: tuple
    residual_px: np.ndarray
    predicted_px: np.ndarray

    @property
    def n_assigned(self) -> int:
        return int(np.count_nonzero(self.ids >= 0))


def _is_flipped(w) -> bool:
    """Is the pose's rho_X nearer pi than 0 (the object upside down)?"""
    return bool(abs(np.angle(np.exp(1j * w[10]))) > np.pi / 2)


def _rigid_rms(a, b) -> float:
    """RMS distance [m] left after the best proper rigid motion of points a (N, 3) onto b (Kabsch)."""
    return _rigid_fit(a, b)[2]


def _rigid_fit(a, b):
    """Proper rigid motion (R, t) with R a + t ~ b for points a, b (N, 3) and its rms [m] (Kabsch)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _s, vt = np.linalg.svd((a - ca).T @ (b - cb))
    dfix = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    r = vt.T @ dfix @ u.T
    t = cb - r @ ca
    return r, t, float(np.sqrt(np.mean(np.sum((a @ r.T + t - b) ** 2, axis=1))))


def _object_angles(r):
    """(rho_X, rho_Y, rho_Z) with object_rotation(rho_X, rho_Y, rho_Z) = r (Ry Rz Rx)."""
    rho_z = float(np.arcsin(np.clip(r[1, 0], -1.0, 1.0)))
    return float(np.arctan2(-r[1, 2], r[1, 1])), float(np.arctan2(-r[2, 0], r[0, 0])), rho_z


def _check_centres(c, name="centres_px"):
    a = np.asarray(c, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"{name} must have shape (M, 2), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or inf")
    return a


class SphereIdentifier:
    """Frame-by-frame sphere identity for one reference object on one instrument.

    Parameters
    ----------
    ids : array_like of shape (N,)
        Sphere ids of the reference object.
    centres_of_m : array_like of shape (N, 3)
        Calibrated centres in {OF} [m].
    diameters_m : array_like of shape (N,)
        Calibrated diameters [m].
    detector : DetectorSpec
        From ct_instrument.yaml.
    sdd_m : float
        Source-to-detector distance as the instrument states it [m].
    settings : IdentifySettings, optional
    """

    def __init__(self, ids, centres_of_m, diameters_m, detector: DetectorSpec, sdd_m: float,
                 settings: IdentifySettings | None = None):
        self.ids = np.asarray(ids).astype(np.int64).reshape(-1)
        c = np.asarray(centres_of_m, dtype=np.float64)
        n = self.ids.size
        if c.shape != (n, 3) or not np.all(np.isfinite(c)):
            raise ValueError(f"centres_of_m must be finite with shape ({n}, 3), got {c.shape}")
        d = np.asarray(diameters_m, dtype=np.float64)
        if d.ndim == 0:
            d = np.full(n, float(d))
        if d.shape != (n,) or not np.all(np.isfinite(d)) or np.any(d <= 0):
            raise ValueError(f"diameters_m must be positive with shape ({n},)")
        if np.unique(self.ids).size != n:
            raise ValueError("ids must be unique")
        if not isinstance(detector, DetectorSpec):
            raise ValueError("detector must be a DetectorSpec")
        if not (np.isfinite(sdd_m) and sdd_m > 0):
            raise ValueError(f"sdd_m must be positive, got {sdd_m}")
        self.centres_of_m = c
        self.radii_m = d / 2.0
        self.detector = detector
        self.sdd_m = float(sdd_m)
        self.settings = settings if settings is not None else IdentifySettings()
        self._w = None            # static params of the prediction model (SRF)
        self._geom = None         # or a DetectorFrameGeometry ...
        self._motion = None       # ... plus a motion (6,)
        self._shift = np.zeros(2)
        self._scale = 1.0
        self._follow = None       # pose following during the rotation (see _follow_pose)
        self.pose_refits = 0      # how many times the pose was refitted during the rotation
        self._df_cache = (None, None)   # (w bytes, its static_to_detector_frame) of _raw_predict
        self.screws = self._screw_symmetries()
        self._cyl = self._cylinder()

    def _screw_symmetries(self):
        """[(k, R, t, rms)]: rigid motions with R c_i + t ~ c_(i+k) (file order) to screw_tolerance_m."""
        c = self.centres_of_m
        out = []
        for k in range(1, min(self.settings.screw_shifts, len(c) - 3) + 1):
            r, t, rms = _rigid_fit(c[:-k], c[k:])
            if rms <= self.settings.screw_tolerance_m:
                out += [(k, r, t, rms), (-k, r.T, -r.T @ t, rms)]
        return out

    def _cylinder(self):
        """(radius, heights, azimuths) when every calibrated centre lies on one cylinder about the object's
        Y axis (to ``cylinder_tolerance_m``, helix49 to 1e-9 m); else None (no lean search)."""
        return cylinder_about_y(self.centres_of_m, tol_m=self.settings.cylinder_tolerance_m)

    def _shifted_pose(self, w, r, t):
        """Pose w composed with the object motion x -> r x + t: a sphere is then labelled as the one the
        motion carries onto it."""
        r0 = object_rotation(w[10], w[11], w[12])
        out = np.array(w, dtype=np.float64)
        out[10], out[11], out[12] = _object_angles(r0 @ r)
        out[7:10] = r0 @ t + w[7:10]
        return out

    # ------------------------------------------------------------------ model
    @property
    def initialised(self) -> bool:
        return self._w is not None or self._geom is not None

    def _nominal_w(self, srd_m: float) -> np.ndarray:
        w = np.zeros(13)
        w[0] = srd_m
        w[3] = self.sdd_m
        w[9] = srd_m
        return w

    def _raw_predict(self, alpha_rad, w=None):
        """Predicted centres (A, N, 2) and shadow radii (A, N) [px] at angles (A,)."""
        a = np.atleast_1d(np.asarray(alpha_rad, dtype=np.float64))
        if w is not None or self._geom is None:
            w = self._w if w is None else w
            pts = forward_srf(w, self.centres_of_m, a, self.detector)
            key = np.asarray(w, dtype=np.float64).tobytes()
            if self._df_cache[0] != key:        # the same pose frame after frame: converted once
                self._df_cache = (key, static_to_detector_frame(w, self.centres_of_m))
            geom = self._df_cache[1]
            c_df = sphere_centres_df(geom, np.zeros(6), a)
        else:
            geom, motion = self._geom, self._motion
            pts = forward_df(geom, motion, a, self.detector)
            c_df = sphere_centres_df(geom, motion, a)
        dist = np.linalg.norm(c_df - geom.source_df_m, axis=-1)
        r_px = self.radii_m * (-geom.source_df_m[2]) / dist / self.detector.pixel_pitch_m
        return pts, r_px

    def predict(self, alpha_rad: float):
        """Predicted centres (N, 2) [px] of all spheres at one angle (with the shift/scale update)."""
        if not self.initialised:
            raise ValueError("SphereIdentifier is not initialised")
        pts, _ = self._raw_predict([alpha_rad])
        return self._apply_similarity(pts[0])

    def _apply_similarity(self, pts):
        c0 = np.array(self.detector.centre_px)
        return c0 + self._scale * (pts - c0) + self._shift

    def _in_view(self, pts, r_px):
        return ((pts[..., 0] >= -r_px) & (pts[..., 0] <= self.detector.cols - 1 + r_px)
                & (pts[..., 1] >= -r_px) & (pts[..., 1] <= self.detector.rows - 1 + r_px))

    # ------------------------------------------------------------------ initialise
    def initialise(self, frames_centres_px, alphas_rad, srd_m: float, diagnose: bool = True) -> InitialisationResult:
        """Find the object pose on the nominal instrument from a few frames.

        Parameters
        ----------
        frames_centres_px : sequence of ndarray of shape (M_j, 2)
            Detected centres of J frames (J >= 1; 4-8 frames spread over the
            rotation work best).
        alphas_rad : array_like of shape (J,)
            Rotary angles of those frames [rad].
        srd_m : float
            Reported source-to-rotation-axis distance [m].

        Returns
        -------
        InitialisationResult
        """
        frames = [_check_centres(f, "frames_centres_px[j]") for f in frames_centres_px]
        alphas = np.asarray(alphas_rad, dtype=np.float64).reshape(-1)
        if len(frames) == 0 or alphas.size != len(frames) or not np.all(np.isfinite(alphas)):
            raise ValueError("need one finite alpha per frame and at least one frame")
        if not (np.isfinite(srd_m) and 0 < srd_m < self.sdd_m):
            raise ValueError(f"srd_m must be in (0, sdd), got {srd_m}")
        self._geom, self._motion = None, None
        self._shift, self._scale = np.zeros(2), 1.0
        self._alphas = alphas
        n_det = sum(len(f) for f in frames)
        if n_det < 4:
            self._w = None
            return InitialisationResult(np.full(13, np.nan), np.zeros(0), np.nan, 0, n_det, np.nan, False,
                                        "fewer than 4 detections", 0)
        mag = self.sdd_m / srd_m
        pitch = self.detector.pixel_pitch_m
        r_nom = float(np.median(self.radii_m)) * mag / pitch
        coarse_gate = self.settings.coarse_gate_px or 2.0 * r_nom
        allc = np.vstack(frames)
        mean_det = allc.mean(axis=0)
        # the lean vote needs frames at more than one rotary angle: one view of helix49 is explained to a few
        # hundredths of a pixel by a pose leaning tens of degrees (measured: the upright default object refused
        # as leaning 23 deg with one initialisation frame); else the upright grid as before round 21
        lean = (self._cyl is not None and self.settings.lean_search_deg > 0
                and _arc_deg(alphas) >= self.settings.lean_min_arc_deg)
        # coarse grid over rho_Y and object height (the object upright on the axis); keep the best few distinct
        # poses. With the lean search (centres on a cylinder, as helix49) the vote below replaces it.
        cands = []
        dy_grid = np.arange(-self.settings.height_search_m, self.settings.height_search_m + 1e-12,
                            self.settings.height_step_m)
        flips = (0.0, np.pi) if self.settings.upside_down else (0.0,)
        grid = [(f, r) for f in flips for r in np.deg2rad(np.arange(0.0, 360.0, self.settings.coarse_step_deg))]
        if lean:
            grid = []
        for flip, rho_y in grid:
            w0 = self._nominal_w(srd_m)
            w0[10] = flip
            w0[11] = rho_y
            pred, r_px = self._raw_predict(alphas, w0)
            vis = self._in_view(pred, r_px)
            if not np.any(vis):
                continue
            mp = np.array([pred[..., 0][vis].mean(), pred[..., 1][vis].mean()])
            dcol, drow = mean_det - mp
            for dy in dy_grid:
                w = w0.copy()
                w[1] -= dcol * pitch                # detector offset: a uniform column shift
                w[8] += -drow * pitch / mag + dy    # object height
                pred = forward_srf(w, self.centres_of_m, alphas, self.detector)     # centres only
                cands.append((self._score(frames, pred, coarse_gate), w))
        cands.sort(key=lambda t: t[0])
        starts = []
        for flip in flips:                  # the best few distinct poses of each orientation
            n0 = len(starts)
            for sc, w in cands:
                if w[10] != flip:
                    continue
                if all(abs(np.angle(np.exp(1j * (w[11] - v[11])))) > np.deg2rad(5.0) or abs(w[8] - v[8]) > 1e-3
                       or v[10] != flip for v in starts):
                    starts.append(w)
                if len(starts) - n0 >= self.settings.n_starts:
                    break
        nfev = 0
        results = []

        def consider(w0):
            """Refine a start and keep it as a hypothesis unless its labelling is already one."""
            nonlocal nfev
            w, res, n_match, nf = self._refine(frames, alphas, w0, coarse_gate)
            nfev += nf
            gate = self._gate(w, alphas)
            pred, r_px = self._raw_predict(alphas, w)
            # the same labelling reached from another start is not a rival hypothesis
            if any(np.max(np.abs(pred - r[6])) < gate for r in results):
                return
            results.append((self._unexplained(frames, pred, r_px, gate),
                            float(np.mean(res ** 2)) if res.size else np.inf, w, res, n_match, gate, pred))

        for w in starts:
            consider(w)
        if lean:
            x_d = -(mean_det[0] - self.detector.centre_px[0]) * pitch
            y_p = (self.detector.centre_px[1] - mean_det[1]) * pitch / mag
            for w in self._lean_starts(frames, alphas, srd_m, x_d, y_p):
                consider(w)
        results.sort(key=lambda t: (t[0], t[1]))
        # screw symmetry: the labellings shifted along the object, composed onto the best pose (of each
        # orientation when the lean vote made the starts: its peaks are blind to a screw shift, and the best
        # upright labelling of helix49 can be a turned-over one)
        bests = [results[0][2]]
        if lean:
            bests += [q[2] for q in results if _is_flipped(q[2]) != _is_flipped(bests[0])][:1]
        for best in bests:
            for k, r, t, _rms in self.screws:
                consider(self._shifted_pose(best, r, t))
        results.sort(key=lambda t: (t[0], t[1]))
        margin = results[1][0] - results[0][0] if len(results) > 1 else np.inf
        note, refuse = "", ""
        settled = []           # the orientation rival, once _orientation has decided against it
        if margin < self.settings.min_margin and _is_flipped(results[0][2]) != _is_flipped(results[1][2]):
            # upright and upside down explain the frames alike: symmetric object, or decide on residuals
            results, note, refuse = self._orientation(results, frames)
            settled = [results[1]]
        # every other labelling must leave min_margin more unexplained; one that predicts the same
        # positions (a symmetric object turned upside down) is the same geometry, not a rival
        win = results[0]
        rivals = [q[0] for q in results[1:] if not any(q is x for x in settled)
                  and not self._same_positions(q[6], win[6], win[5])]
        if not refuse:
            margin = min(rivals) - win[0] if rivals else np.inf
        bad, _, w, res, n_match, gate_final, _ = results[0]
        self._w = w
        rms = float(np.sqrt(np.mean(res ** 2) * 2)) if res.size else np.nan
        fits = bool(res.size and rms < gate_final and n_match >= 0.6 * n_det)
        # a pose that fits but whose labelling a screw shift explains as well: say so (no diagnosis needed)
        screw_refused = bool(fits and margin < self.settings.min_margin and self.screws and not refuse)
        if screw_refused:
            k = max(abs(s[0]) for s in self.screws)
            refuse = (f"the object is screw-symmetric (its centres shifted by up to {k} places in the file's "
                      f"order map onto themselves to {max(s[3] for s in self.screws) * 1e6:.2g} um rms): "
                      f"labellings shifted along it differ only at its end spheres, and these frames do not show "
                      f"the ends clearly enough to tell them apart; use frames where the end spheres are clear "
                      f"of their neighbours")
        lean_refused = False
        if lean and fits and not refuse:
            # a pose leaning more than lean_accept_deg: not trusted (measured: an instrument leaning 13.9 deg was
            # labelled wrong, fitted at 0.12 px, with the search at 12 and at 15 deg; none wrong up to 11.7 deg)
            tilt = float(np.degrees(np.arccos(min(1.0, abs(object_rotation(*w[10:13])[1, 1])))))
            if tilt > min(self.settings.lean_accept_deg, self.settings.lean_search_deg - self.settings.lean_step_deg):
                refuse = (f"the object leans {tilt:.1f} deg from the rotation axis, more than the identity search "
                          f"accepts ({self.settings.lean_accept_deg:g} deg, IdentifySettings.lean_accept_deg): "
                          f"set the object upright")
                lean_refused = True
        ok = fits and margin >= self.settings.min_margin and not refuse
        msg = (f"{n_match} of {n_det} detections matched, rms {rms:.3f} px, {bad} unexplained"
               + (f" (next pose hypothesis: {bad + margin})" if np.isfinite(margin) else ""))
        if ok:
            self._start_following(alphas)
            msg = "pose found: " + msg + ("; mounted upside down (turned 180 deg about its X axis)"
                                          if _is_flipped(w) else "") + note
        else:
            msg = "pose search failed: " + msg + (f"; {refuse}" if refuse else "")
            self._w = None
            if diagnose and not screw_refused and not lean_refused:    # the pose fits; only the labelling is open
                msg += "; " + self._diagnose(frames, alphas, srd_m)
        return InitialisationResult(w, res, rms, n_match, n_det, 0.5 * float(np.sum(res ** 2)), ok, msg, nfev)

    @staticmethod
    def _same_positions(pa, pb, gate) -> bool:
        """Do two hypotheses predict the same set of positions (whatever the labels) in every frame?"""
        for a, b in zip(pa, pb):
            if np.max(np.min(np.linalg.norm(a[:, None] - b[None], axis=2), axis=1)) >= gate:
                return False
        return True

    def _orientation(self, results, frames):
        """Decide between an upright and an upside-down pose that leave the same detections
        unexplained. Returns (results reordered, note, refusal reason or "")."""
        a, b = results[0], results[1]
        # which sphere of a sits where each sphere of b is predicted, over all frames
        votes = np.full((len(self.ids), len(self.ids)), 0)
        for pa, pb in zip(a[6], b[6]):
            d = np.linalg.norm(pb[:, None] - pa[None], axis=2)
            votes[np.arange(len(self.ids)), d.argmin(axis=1)] += 1
        perm = votes.argmax(axis=1)
        c = self.centres_of_m
        d_sym = _rigid_rms(c, c[perm]) if np.unique(perm).size == perm.size else np.inf
        up, down = (a, b) if not _is_flipped(a[2]) else (b, a)
        if d_sym > self.settings.symmetric_tolerance_m:
            # the identification model holds the instrument nominal (model error ~0.3 px): compare the two
            # labellings with every geometry parameter free, where only the detection noise is left
            ms = {id(r): self._full_fit_ms(frames, r[2], r[5]) for r in (a, b)}
            a, b = sorted((a, b), key=lambda r: ms[id(r)])
            ms_a, ms_b = ms[id(a)], ms[id(b)]
            results = [a, b] + results[2:]
        if d_sym <= self.settings.symmetric_tolerance_m:
            return ([up, down] + results[2:],
                    f"; the object is symmetric under turning it upside down (relabelled, to {d_sym * 1e6:.2f} um "
                    f"rms): upright and upside down look alike and give the same instrument geometry; the upright "
                    f"labelling is used", "")
        if ms_b >= self.settings.flip_ms_ratio * ms_a:
            other = "upside-down" if _is_flipped(b[2]) else "upright"
            return results, (f"; the {other} pose fits {np.sqrt(ms_b / ms_a):.1f} times worse (rms, all geometry "
                             f"free); the object is not symmetric under turning it upside down "
                             f"({d_sym * 1e6:.1f} um rms)"), ""
        return results, "", (f"cannot tell whether the object is mounted upright or upside down: its centres are "
                             f"symmetric under that turn to {d_sym * 1e6:.1f} um rms, which these frames do not "
                             f"resolve (rms {np.sqrt(2 * ms_a):.3f} vs {np.sqrt(2 * ms_b):.3f} px with all geometry "
                             f"free); mount it as its file says (sphere {self.ids[np.argmin(c[:, 1])]} at the "
                             f"bottom) or use more frames")

    def _full_fit_ms(self, frames, w, gate) -> float:
        """Mean squared residual [px^2] of the matched detections with all 13 parameters free."""
        fj, fi, sn = self._match_frames(frames, self._alphas, w, gate)
        if len(fj) < 14:
            return np.inf
        obs = np.vstack([frames[j][i] for j, i in zip(fj, fi)])
        alphas = self._alphas

        def fun(x):
            return (forward_srf(x, self.centres_of_m, alphas, self.detector)[fj, sn] - obs).ravel()

        scale = np.array([1e-3, 1e-3, 1e-3, 1e-3, 1e-2, 1e-2, 1e-2, 1e-3, 1e-3, 1e-3, 1e-2, 1e-2, 1e-2])
        sol = least_squares(fun, w, x_scale=scale, method="lm", max_nfev=400)
        return float(np.mean(sol.fun ** 2))

    # ------------------------------------------------------------------ lean search
    @staticmethod
    def _lean_axis(tx, tz):
        """Unit axis Rz(tz) Rx(tx) e_y of an object leaning by tx about X and tz about Z [rad]."""
        return np.array([-np.sin(tz) * np.cos(tx), np.cos(tz) * np.cos(tx), np.sin(tx)])

    @staticmethod
    def _rotation_onto(a):
        """A proper rotation L with L e_y = a (the smallest)."""
        ey = np.array([0.0, 1.0, 0.0])
        v = np.cross(ey, a)
        sn, cs = float(np.linalg.norm(v)), float(a @ ey)
        if sn < 1e-12:
            return np.eye(3)
        k = v / sn
        kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        return np.eye(3) + sn * kx + (1.0 - cs) * kx @ kx

    def _lean_starts(self, frames, alphas, srd_m, x_d, y_p):
        """Poses of a leaning object from a vote on the cylinder the centres lie on.

        Each detection is a ray from the source (nominal instrument, the detector shifted by ``x_d``); for a
        trial lean of the object's axis (through (0, y_p, srd) at alpha = 0, undone per frame by the table
        rotation) the ray meets the cylinder of the calibrated centres at two points, each an (axial height h,
        azimuth phi) on the object. A right lean puts the detections' (h, phi) onto the calibrated (h_i, phi_i)
        moved by one common (height offset, spin): every detection votes for (h - h_i, phi - phi_i) over all
        spheres i, and the lean whose vote peaks highest wins. Neither labelling nor spin is needed to vote,
        so the lean is searched on its own grid (2 angles) instead of inside the rho_Y x height grid.
        Returns [(start pose w, frame index, detection index, sphere index)] of the ``lean_starts`` best
        distinct leans (both orientations), with the detections the peak labels.
        """
        st = self.settings
        rad, hk, pk = self._cyl
        hs = np.unique(np.round(hk, 9))
        hbin = 0.5 * float(np.median(np.diff(hs))) if hs.size > 1 else float(np.median(self.radii_m))
        hbin = max(hbin, 1e-4)
        pbin = 2.0 * hbin / rad
        # the height is left to the vote: the mean detected row misses the object's centre by up to ~8 mm
        # (shadows lost unevenly to overlaps and the detector edges)
        hrange = float(np.ptp(hk)) + 2.0 * hbin
        nh, npb = int(np.ceil(2 * hrange / hbin)), int(np.ceil(2 * np.pi / pbin))
        pbin = 2 * np.pi / npb
        axis = np.array([0.0, 0.0, srd_m])
        centre = np.array([0.0, y_p, srd_m])
        o_all, d_all, fj_all, fi_all = [], [], [], []
        for j, (f, a) in enumerate(zip(frames, alphas)):
            u, v = self.detector.metric_from_pixels(f[:, 0], f[:, 1])
            d = np.column_stack([u + x_d, v, np.full(len(f), self.sdd_m)])
            ra = rot_y(-a)                       # undo the table rotation: the object at alpha = 0
            o_all.append(np.repeat((ra @ (-axis) + axis - centre)[None], len(f), axis=0))
            d_all.append(d @ ra.T)
            fj_all.append(np.full(len(f), j))
            fi_all.append(np.arange(len(f)))
        o0, d0 = np.vstack(o_all), np.vstack(d_all)
        d0 /= np.linalg.norm(d0, axis=1)[:, None]
        fj_all, fi_all = np.concatenate(fj_all), np.concatenate(fi_all)
        orient = [(0, hk, pk)] + ([(1, -hk, -pk)] if st.upside_down else [])

        def points(tx, tz):
            """(h, phi, detection row) of the ray-cylinder meeting points for one lean."""
            lm = self._rotation_onto(self._lean_axis(tx, tz))
            o, d = o0 @ lm, d0 @ lm
            qa = d[:, 0] ** 2 + d[:, 2] ** 2
            qb = 2.0 * (o[:, 0] * d[:, 0] + o[:, 2] * d[:, 2])
            qc = o[:, 0] ** 2 + o[:, 2] ** 2 - rad * rad
            disc = qb * qb - 4.0 * qa * qc
            ok = (disc > 0) & (qa > 1e-12)
            sq = np.sqrt(np.where(ok, disc, 0.0))
            p, row = [], []
            for sgn in (-1.0, 1.0):
                t = (-qb + sgn * sq) / (2.0 * np.where(ok, qa, 1.0))
                p.append((o + t[:, None] * d)[ok])
                row.append(np.nonzero(ok)[0])
            p = np.vstack(p)
            return p[:, 1], np.arctan2(p[:, 2], p[:, 0]), np.concatenate(row), lm

        def vote(h, ph, hk_, pk_):
            dh = h[:, None] - hk_[None]
            m = np.abs(dh) < hrange
            ih = ((dh[m] + hrange) / hbin).astype(np.int64)
            ip = (((ph[:, None] - pk_[None])[m] % (2 * np.pi)) / pbin).astype(np.int64) % npb
            hist = np.bincount(ih * npb + ip, minlength=nh * npb)[: nh * npb].reshape(nh, npb)
            sm = hist + np.roll(hist, 1, axis=1)         # 2 x 2 bins: a peak on a bin edge is not split
            sm = sm[:-1] + sm[1:]
            i = int(np.argmax(sm))
            return int(sm.flat[i]), (i // npb + 1) * hbin - hrange, (i % npb) * pbin

        lim = np.deg2rad(st.lean_search_deg)
        g = np.arange(-lim, lim + 1e-12, np.deg2rad(st.lean_step_deg))
        scored = []
        for tx in g:
            for tz in g:
                if tx * tx + tz * tz > lim * lim * (1 + 1e-9):
                    continue
                h, ph, _, _ = points(tx, tz)
                for flip, hk_, pk_ in orient:
                    n, dh, dp = vote(h, ph, hk_, pk_)
                    scored.append((n, tx, tz, flip, dh, dp))
        scored.sort(key=lambda t: -t[0])
        picked = []
        for q in scored:
            if all(q[3] != p[3] or np.hypot(q[1] - p[1], q[2] - p[2]) > 2.5 * np.deg2rad(st.lean_step_deg)
                   for p in picked):
                picked.append(q)
            if len(picked) >= st.lean_starts:
                break
        out = []
        for n, tx, tz, flip, dh, dp in picked:
            h, ph, row, lm = points(tx, tz)
            hk_, pk_ = orient[flip][1], orient[flip][2]
            eh = np.abs(h[:, None] - hk_[None] - dh)
            ep = np.abs(np.angle(np.exp(1j * (ph[:, None] - pk_[None] - dp))))
            hit = (eh <= hbin) & (ep <= pbin)
            pair_row, pair_k = np.nonzero(hit)
            det = row[pair_row]
            # a detection with two candidate spheres, or a sphere claimed twice in a frame: not used
            key = fj_all[det] * len(hk_) + pair_k
            uk, ck = np.unique(key, return_counts=True)
            ud, cd = np.unique(det, return_counts=True)
            keep = np.isin(key, uk[ck == 1]) & np.isin(det, ud[cd == 1])
            r_obj = lm @ rot_y(-dp) @ (rot_x(np.pi) if flip else np.eye(3))
            w = self._nominal_w(srd_m)
            w[1] = x_d
            w[7:10] = centre + dh * (lm @ np.array([0.0, 1.0, 0.0]))
            w[10], w[11], w[12] = _object_angles(r_obj)
            w = self._fit_labelled(frames, alphas, w, fj_all[det[keep]], fi_all[det[keep]], pair_k[keep])
            pred, r_px = self._raw_predict(alphas, w)
            out.append((self._score(frames, pred, self._gate(r_px=r_px)), flip, w))
        # the refinement is the costly part: only the n_starts best fits go on (and the other orientation's best)
        out.sort(key=lambda t: t[0])
        keep = out[: st.n_starts]
        keep += [q for q in out[st.n_starts:] if q[1] not in {k[1] for k in keep}][:1]
        return [q[2] for q in keep]

    def _fit_labelled(self, frames, alphas, w, fj, fi, sn):
        """Least-squares pose (the refinement's parameters) on given detection -> sphere pairs, robust
        to a few wrong pairs."""
        if len(fj) < 6:
            return w
        obs = np.vstack([frames[j][i] for j, i in zip(fj, fi)])

        def fun(x):
            ww = w.copy()
            ww[_FREE] = x
            return (forward_srf(ww, self.centres_of_m, alphas, self.detector)[fj, sn] - obs).ravel()

        scale = np.array([1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-2, 1e-2, 1e-2])
        sol = least_squares(fun, w[_FREE], x_scale=scale, loss="soft_l1", f_scale=2.0, max_nfev=100)
        out = w.copy()
        out[_FREE] = sol.x
        return out

    def _diagnose(self, frames, alphas, srd_m) -> str:
        """Why a pose search failed: try the frames mirrored and the rotation reversed."""
        c0 = self.detector.cols - 1
        r0 = self.detector.rows - 1
        trials = (("the image mirrored left-right (columns)", [f * [-1, 1] + [c0, 0] for f in frames], alphas),
                  ("the image mirrored top-bottom (rows)", [f * [1, -1] + [0, r0] for f in frames], alphas),
                  ("the rotation direction reversed", frames, -np.asarray(alphas)))
        found = []
        for what, fr, al in trials:
            probe = SphereIdentifier(self.ids, self.centres_of_m, 2 * self.radii_m, self.detector, self.sdd_m,
                                     self.settings)
            if probe.initialise(fr, al, srd_m, diagnose=False).success:
                found.append(what)
        self._w = None
        if found:
            return (f"the frames fit with {' or '.join(found)}: check image orientation / rotation direction "
                    f"(INTERFACES.md: column index along +X of the detector, row 0 at the top)")
        return ("check image orientation / rotation direction, the reference object file and the instrument's "
                "SDD and pixel pitch (no mirrored or reversed variant fits either)")

    def _unexplained(self, frames, pred, r_px, gate) -> int:
        """Unmatched detections plus visible predicted spheres the detector would accept (outline gap
        >= ``isolated_gap_px`` to every other shadow) with no detection near."""
        n_unmatched = 0
        n_missing = 0
        for j, f in enumerate(frames):
            idx, _, _ = self._match(f, pred[j], r_px[j], gate)
            n_unmatched += int(np.count_nonzero(idx < 0))
            vis = self._in_view(pred[j], -r_px[j])
            gap = np.linalg.norm(pred[j][:, None] - pred[j][None], axis=2) - r_px[j][:, None] - r_px[j][None]
            np.fill_diagonal(gap, np.inf)
            iso = vis & (gap.min(axis=1) >= self.settings.isolated_gap_px)
            if len(f):
                near = np.linalg.norm(pred[j][:, None] - f[None], axis=2).min(axis=1)
            else:
                near = np.full(len(pred[j]), np.inf)
            n_missing += int(np.count_nonzero(iso & (near > gate)))
        return n_unmatched + n_missing

    def initialise_tracked(self, previous_w, previous_srd_m: float, frames_centres_px, alphas_rad,
                           srd_m: float) -> InitialisationResult:
        """Identity at a new stage position from the pose found at the previous one.

        The object sits on the rotary table: moving the stage carries it along the travel
        without turning it (error motions are arcseconds and micrometres), so the previous
        identification pose, moved by the change of the reported SRD along {SRF} Z, predicts
        the new frames; it is refined on them (no pose search, so the labelling decided at the
        first position is kept). Succeeds only when the refined pose explains the frames at
        least as well as a pose search must (rms below the gate, 90 % of the detections
        matched, at most 10 % unexplained: missed or rejected detections); the caller then falls
        back to :meth:`initialise`.
        """
        frames = [_check_centres(f, "frames_centres_px[j]") for f in frames_centres_px]
        alphas = np.asarray(alphas_rad, dtype=np.float64).reshape(-1)
        if len(frames) == 0 or alphas.size != len(frames) or not np.all(np.isfinite(alphas)):
            raise ValueError("need one finite alpha per frame and at least one frame")
        w = np.asarray(previous_w, dtype=np.float64).copy()
        if w.shape != (13,) or not np.all(np.isfinite(w)):
            raise ValueError("previous_w must be 13 finite values")
        if not (np.isfinite(srd_m) and 0 < srd_m < self.sdd_m and np.isfinite(previous_srd_m)):
            raise ValueError(f"srd_m must be in (0, sdd), got {srd_m}")
        self._geom, self._motion = None, None
        self._shift, self._scale = np.zeros(2), 1.0
        n_det = sum(len(f) for f in frames)
        travel = float(srd_m) - float(previous_srd_m)
        w[0] += travel          # the rotation axis ...
        w[9] += travel          # ... and the object on it
        r_nom = float(np.median(self.radii_m)) * (self.sdd_m / srd_m) / self.detector.pixel_pitch_m
        coarse_gate = self.settings.coarse_gate_px or 2.0 * r_nom
        w, res, n_match, nfev = self._refine(frames, alphas, w, coarse_gate)
        gate = self._gate(w, alphas)
        pred, r_px = self._raw_predict(alphas, w)
        bad = self._unexplained(frames, pred, r_px, gate)
        rms = float(np.sqrt(np.mean(res ** 2) * 2)) if res.size else np.nan
        ok = bool(n_det >= 4 and res.size and rms < gate and n_match >= 0.9 * n_det and bad <= max(2, 0.10 * n_det))
        msg = (f"{n_match} of {n_det} detections matched, rms {rms:.3f} px, {bad} unexplained, "
               f"pose tracked from the previous stage position ({travel * 1e3:+.3f} mm)")
        msg = ("pose found: " if ok else "pose tracking failed: ") + msg
        self._w = w if ok else None
        if ok:
            self._start_following(alphas)
        return InitialisationResult(w, res, rms, n_match, n_det, 0.5 * float(np.sum(res ** 2)), ok, msg, nfev)

    # ------------------------------------------------------------------ pose following
    def _start_following(self, alphas):
        a = np.unwrap(np.asarray(alphas, dtype=np.float64))
        self._follow = {"span": float(a.max() - a.min()) if a.size else 0.0, "alphas": [], "obs": [],
                        "idx": []} if self.settings.follow_pose else None

    def _follow_pose(self, alpha, det, idx):
        """Keep the frame's accepted matches; refit the pose when the arc covered has grown enough."""
        f = self._follow
        if f is None or self._geom is not None or self._w is None or f["span"] >= np.pi:
            return
        ok = idx >= 0
        if np.count_nonzero(ok) < 3:
            return
        f["alphas"].append(float(alpha))
        f["obs"].append(det[ok])
        f["idx"].append(idx[ok])
        a = np.unwrap(np.array(f["alphas"]))
        span = float(a.max() - a.min())
        if span < max(2.0 * f["span"], f["span"] + np.deg2rad(self.settings.follow_min_step_deg)):
            return
        n = len(a)
        pick = np.unique(np.round(np.linspace(0, n - 1, min(n, self.settings.follow_frames))).astype(int))
        fj = np.concatenate([np.full(len(f["idx"][j]), k) for k, j in enumerate(pick)])
        sn = np.concatenate([f["idx"][j] for j in pick])
        obs = np.vstack([f["obs"][j] for j in pick])
        alphas = np.array([f["alphas"][j] for j in pick])
        w0 = self._w

        def fun(x):
            ww = w0.copy()
            ww[_FREE] = x
            return (forward_srf(ww, self.centres_of_m, alphas, self.detector)[fj, sn] - obs).ravel()

        scale = np.array([1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-2, 1e-2, 1e-2])
        sol = least_squares(fun, w0[_FREE], x_scale=scale, method="lm", max_nfev=200)
        rms = float(np.sqrt(np.mean(sol.fun ** 2) * 2))
        f["span"] = span            # this arc is done either way: the next try needs twice as much
        if np.isfinite(rms) and rms < self._gate(w0, alphas):
            w = w0.copy()
            w[_FREE] = sol.x
            self._w = w
            self.pose_refits += 1

    @staticmethod
    def _score(frames, pred, gate):
        """Truncated nearest-neighbour cost sum_i min(d_i, gate)^2 over all frames' detections."""
        sizes = [len(f) for f in frames]
        if not sum(sizes):
            return 0.0
        det = np.concatenate(frames)                                   # (D, 2)
        fj = np.repeat(np.arange(len(frames)), sizes)
        dx = det[:, 0, None] - pred[fj, :, 0]                          # (D, N)
        d2 = det[:, 1, None] - pred[fj, :, 1]
        d2 *= d2
        dx *= dx
        d2 += dx
        return float(np.sum(np.minimum(d2.min(axis=1), gate * gate)))

    def _refine(self, frames, alphas, w, coarse_gate):
        nfev = 0
        res = np.zeros(0)
        n_match = 0
        gate_final = self._gate(w, alphas)
        for gate in (coarse_gate, 0.5 * coarse_gate, gate_final, gate_final):
            fj, fi, sn = self._match_frames(frames, alphas, w, gate)
            if len(fj) < 6:
                break
            obs = np.vstack([frames[j][i] for j, i in zip(fj, fi)])

            def fun(x, fj=fj, sn=sn, obs=obs, w=w):
                ww = w.copy()
                ww[_FREE] = x
                p = forward_srf(ww, self.centres_of_m, alphas, self.detector)
                return (p[fj, sn] - obs).ravel()

            scale = np.array([1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-2, 1e-2, 1e-2])
            sol = least_squares(fun, w[_FREE], x_scale=scale, method="lm", max_nfev=200)
            nfev += int(sol.nfev)
            w = w.copy()
            w[_FREE] = sol.x
            res = sol.fun
            n_match = len(fj)
        return w, res, n_match, nfev

    def _gate(self, w=None, alphas=(0.0,), r_px=None):
        """Match gate [px]; ``r_px``: the shadow radii ``_raw_predict(alphas, w)`` gave, if at hand."""
        if self.settings.gate_px is not None:
            return float(self.settings.gate_px)
        if r_px is None:
            _, r_px = self._raw_predict(np.atleast_1d(alphas), w)
        return max(1.5, 0.35 * float(np.min(r_px)))

    def _match_frames(self, frames, alphas, w, gate):
        pred, r_px = self._raw_predict(alphas, w)
        fj, fi, sn = [], [], []
        for j, f in enumerate(frames):
            idx, _, _ = self._match(f, pred[j], r_px[j], gate)
            for i, s in enumerate(idx):
                if s >= 0:
                    fj.append(j)
                    fi.append(i)
                    sn.append(s)
        return np.array(fj, int), np.array(fi, int), np.array(sn, int)

    def _match(self, det, pred, r_px, gate):
        """Sphere index per detection (-1 rejected), reasons, distances."""
        m = len(det)
        out = np.full(m, -1, int)
        reasons = ["unmatched"] * m
        if m == 0:
            return out, tuple(reasons), np.zeros(0)
        d = np.linalg.norm(det[:, None, :] - pred[None, :, :], axis=2)     # (M, N)
        order = np.argsort(d, axis=1)
        near = order[:, 0]
        d1 = d[np.arange(m), near]
        d2 = d[np.arange(m), order[:, 1]] if pred.shape[0] > 1 else np.full(m, np.inf)
        sep = 2.0 * r_px[near] + self.settings.separation_margin_px
        for i in range(m):
            if d1[i] > gate:
                continue
            if d2[i] < sep[i]:
                reasons[i] = "ambiguous_identity"
                continue
            out[i] = near[i]
            reasons[i] = "ok"
        # mutual uniqueness: a sphere claimed twice -> all claimants rejected
        vals, counts = np.unique(out[out >= 0], return_counts=True)
        for v in vals[counts > 1]:
            for i in np.nonzero(out == v)[0]:
                out[i] = -1
                reasons[i] = "ambiguous_identity"
        return out, tuple(reasons), d1

    # ------------------------------------------------------------------ per frame
    def assign(self, centres_px, alpha_rad: float) -> Assignment:
        """Assign sphere ids to the detections of one frame.

        Parameters
        ----------
        centres_px : array_like of shape (M, 2)
            Detected centres (col, row) [px].
        alpha_rad : float
            Rotary angle of the frame [rad].

        Returns
        -------
        Assignment
        """
        det = _check_centres(centres_px)
        m = len(det)
        if not self.initialised:
            return Assignment(np.full(m, -1, np.int64), ("not_initialised",) * m, np.full(m, np.nan),
                              np.zeros((0, 2)))
        if not np.isfinite(alpha_rad):
            raise ValueError("alpha_rad must be finite")
        raw, r_px = self._raw_predict([float(alpha_rad)])
        gate = self._gate(r_px=r_px)
        raw, r_px = raw[0], r_px[0] * self._scale
        # loose pass: 2-D shift and scale about the detector centre (median based)
        pred = self._apply_similarity(raw)
        idx, _, _ = self._match(det, pred, r_px, 3.0 * gate)
        use = idx >= 0
        if np.count_nonzero(use) >= 6:
            c0 = np.array(self.detector.centre_px)
            p, q = pred[idx[use]] - c0, det[use] - c0
            rp = np.linalg.norm(p, axis=1)
            good = rp > 20.0
            s = float(np.median(np.sum(q[good] * p[good], axis=1) / rp[good] ** 2)) if good.sum() >= 3 else 1.0
            shift = np.median(q - s * p, axis=0)
            pred = c0 + s * (pred - c0) + shift
        idx, reasons, dist = self._match(det, pred, r_px, gate)
        ids = np.where(idx >= 0, self.ids[np.clip(idx, 0, None)], -1)
        self._follow_pose(float(alpha_rad), det, idx)
        return Assignment(ids.astype(np.int64), reasons, dist, pred)

    # ------------------------------------------------------------------ solver hand-over
    def update_geometry(self, static_w=None, *, motion=None, travel_m: float | None = None):
        """Predict from a solved geometry instead of the identification pose.

        Parameters
        ----------
        static_w : array_like of shape (13,), optional
            Solved static parameters at k = 1. None keeps the current model.
        motion : array_like of shape (6,), optional
            Error motion of the current stage position relative to k = 1
            (solved, or from a previous position).
        travel_m : float, optional
            Nominal stage travel from k = 1 (reported SRD change) [m]; used
            when ``motion`` is None: the stage point moves along {SRF} Z.
        """
        if static_w is not None:
            w = np.asarray(static_w, dtype=np.float64)
            if w.shape != (13,) or not np.all(np.isfinite(w)):
                raise ValueError("static_w must be 13 finite values")
            self._w = w
        if self._w is None:
            raise ValueError("no geometry: give static_w or call initialise first")
        self._shift, self._scale = np.zeros(2), 1.0
        self._follow = None
        if motion is None and travel_m is None:
            self._geom, self._motion = None, None
            return
        geom = static_to_detector_frame(self._w, self.centres_of_m)
        if motion is not None:
            mo = np.asarray(motion, dtype=np.float64)
            if mo.shape != (6,) or not np.all(np.isfinite(mo)):
                raise ValueError("motion must be 6 finite values")
        else:
            # travel along {SRF} Z expressed in {DF}
            z_df = (geom.stage_df_m - geom.source_df_m)
            z_df = z_df / np.linalg.norm(z_df)
            mo = np.zeros(6)
            mo[:3] = float(travel_m) * z_df
        self._geom, self._motion = geom, mo
