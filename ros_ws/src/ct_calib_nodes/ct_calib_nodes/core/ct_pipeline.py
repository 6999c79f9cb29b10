"""The CT calibration pipeline as plain functions and small state holders.

Three front doors share this module: the live nodes (detector, geometry
solver, error-motion node), the offline replay of a recording, and tests.
Identical inputs give identical numbers in all three.

- ``PositionSegmenter`` splits the time-ordered stage readings into stage
  positions: a new position starts when the reported SRD moves away from the
  current position's readings (their median) by more than a tolerance. A
  position is a stretch of time: returning to an SRD visited before is a new
  position (a revisit), never merged with the earlier one.
- ``CampaignAccumulator`` groups sphere-centre observations into those
  positions, in the order the frames come.
- ``revisit_groups`` / ``repeatability`` compare the visits of one nominal SRD.
- ``solve_campaign_static`` / ``solve_campaign_position`` run the static and
  error-motion solvers on an accumulated position.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .error_motion import MotionResult, solve_error_motion
from .geometry import DetectorSpec
from .observations import CentreObservations
from .static_solver import StaticResult, solve_static


#: Default tolerance of the position segmenter [m]: far above the read-back jitter of a stage
#: encoder (micrometres), far below any stage step of a calibration campaign (millimetres).
DEFAULT_POSITION_TOLERANCE_M = 1e-4


class PositionSegmenter:
    """Stage positions from the time-ordered sequence of reported SRDs.

    A reading belongs to the current position when it lies within
    ``tolerance_m`` of the median of that position's readings so far;
    otherwise the stage has moved and a new position starts. Positions are
    numbered in time; a position is never reopened, so a return to an SRD
    visited earlier (a revisit, a bidirectional run) is a new position.

    Parameters
    ----------
    tolerance_m : float
        Largest departure from the current position's median reading that is
        still the same position [m]; set it above the read-back jitter and
        below the smallest stage step.
    """

    def __init__(self, tolerance_m: float = DEFAULT_POSITION_TOLERANCE_M):
        tol = float(tolerance_m)
        if not (np.isfinite(tol) and tol > 0):
            raise ValueError(f"stage position tolerance must be a positive length [m], got {tolerance_m}")
        self.tolerance_m = tol
        self.k = -1
        self._readings: list = []

    @property
    def reference_m(self) -> float:
        """Median of the current position's readings [m] (NaN before the first reading)."""
        return float(np.median(self._readings)) if self._readings else float("nan")

    def moved(self, srd_reported_m: float) -> bool:
        """Would this reading start a new position?"""
        return self.k < 0 or abs(float(srd_reported_m) - self.reference_m) > self.tolerance_m

    def push(self, srd_reported_m: float) -> tuple:
        """Take the next reading in time; returns (position index, True if it starts a new position)."""
        srd = float(srd_reported_m)
        if not np.isfinite(srd):
            raise ValueError(f"non-finite SRD reading {srd_reported_m}")
        new = self.moved(srd)
        if new:
            self.k += 1
            self._readings = []
        self._readings.append(srd)
        return self.k, new


@dataclass
class PositionData:
    """Observations of one stage position, frame by frame.

    ``srd_reported_m`` is the median of the position's SRD readings."""

    srd_reported_m: float
    srd_readings_m: list = field(default_factory=list)
    stamps_ns: list = field(default_factory=list)
    alphas_rad: list = field(default_factory=list)
    uv_px: list = field(default_factory=list)           # per frame (Q_j, 2)
    sphere_index: list = field(default_factory=list)    # per frame (Q_j,)
    sigma_px: list = field(default_factory=list)        # per frame (Q_j,)
    minor_axis_px: list = field(default_factory=list)   # per frame (Q_j,) or None
    systematic_px: list = field(default_factory=list)   # per frame (Q_j, 2) or None (detect.FrameDetections)
    n_rejected: int = 0

    @property
    def n_frames(self) -> int:
        return len(self.stamps_ns)

    @property
    def n_obs(self) -> int:
        return int(sum(len(s) for s in self.sphere_index))

    def observations(self) -> CentreObservations:
        """All frames of this position as one CentreObservations, in stamp order."""
        order = np.argsort(np.asarray(self.stamps_ns, dtype=np.int64), kind="stable")
        pick = lambda seq: [seq[i] for i in order]  # noqa: E731
        sig = pick(self.sigma_px)
        use_sigma = all(len(s) == 0 or np.all(np.asarray(s) > 0) for s in sig)
        minor = pick(self.minor_axis_px)
        use_minor = all(m is not None for m in minor)      # the ellipse-centre model needs every axis
        syst = pick(self.systematic_px)
        use_sys = any(s is not None and np.any(s) for s in syst)
        return CentreObservations.from_views(
            pick(self.uv_px), pick(self.sphere_index), np.asarray(self.alphas_rad)[order],
            stamp_ns_per_view=np.asarray(self.stamps_ns, dtype=np.int64)[order],
            sigma_px_per_view=sig if use_sigma else None,
            minor_axis_px_per_view=minor if use_minor else None,
            systematic_px_per_view=[np.zeros((len(i), 2)) if s is None else s
                                    for s, i in zip(syst, pick(self.sphere_index))] if use_sys else None)


class CampaignAccumulator:
    """Sphere-centre observations of a campaign, grouped by stage position.

    Frames must come in time order (as a stage delivers them); positions are
    split on motion by a :class:`PositionSegmenter`.

    Parameters
    ----------
    srd_tolerance_m : float
        Tolerance of the position segmenter [m].
    """

    def __init__(self, srd_tolerance_m: float = DEFAULT_POSITION_TOLERANCE_M):
        self.segmenter = PositionSegmenter(srd_tolerance_m)
        self.srd_tolerance_m = self.segmenter.tolerance_m
        self.positions: list[PositionData] = []
        self._seen_stamps: set = set()

    def add_frame(self, stamp_ns: int, alpha_rad: float, srd_reported_m: float, sphere_index, uv_px,
                  sigma_px=None, n_rejected: int = 0, minor_axis_px=None, systematic_px=None) -> int:
        """Add the accepted observations of one frame; returns its position index.

        ``minor_axis_px`` (Q,): semi-minor axes of the shadow ellipses [px], or None.
        ``systematic_px`` (Q, 2): the detector's shared systematic pattern (detect.FrameDetections), or None.

        A frame whose stamp was already added is ignored (returns -1): replays and
        re-deliveries must not count twice.
        """
        stamp_ns = int(stamp_ns)
        if stamp_ns in self._seen_stamps:
            return -1
        if not (np.isfinite(alpha_rad) and np.isfinite(srd_reported_m)):
            raise ValueError(f"non-finite stage reading alpha={alpha_rad} srd={srd_reported_m}")
        idx = np.asarray(sphere_index, dtype=np.int64).reshape(-1)
        uv = np.asarray(uv_px, dtype=float).reshape(-1, 2)
        if len(idx) != len(uv):
            raise ValueError(f"{len(idx)} sphere indices but {len(uv)} centres")
        sig = np.full(len(idx), -1.0) if sigma_px is None else np.asarray(sigma_px, dtype=float).reshape(-1)
        minor = None if minor_axis_px is None else np.asarray(minor_axis_px, dtype=float).reshape(-1)
        if minor is not None and len(minor) != len(idx):
            raise ValueError(f"{len(idx)} sphere indices but {len(minor)} ellipse axes")
        syst = None if systematic_px is None else np.asarray(systematic_px, dtype=float).reshape(-1, 2)
        if syst is not None and (len(syst) != len(idx) or not np.all(np.isfinite(syst))):
            raise ValueError(f"{len(idx)} sphere indices but {len(syst)} systematic shifts (or non-finite ones)")
        k, new = self.segmenter.push(srd_reported_m)
        if new:
            self.positions.append(PositionData(float(srd_reported_m)))
        p = self.positions[k]
        p.srd_readings_m.append(float(srd_reported_m))
        p.srd_reported_m = self.segmenter.reference_m
        p.stamps_ns.append(stamp_ns)
        p.alphas_rad.append(float(alpha_rad))
        p.uv_px.append(uv)
        p.sphere_index.append(idx)
        p.sigma_px.append(sig)
        p.minor_axis_px.append(minor)
        p.systematic_px.append(syst)
        p.n_rejected += int(n_rejected)
        self._seen_stamps.add(stamp_ns)
        return k

    @property
    def srd_reported_m(self) -> np.ndarray:
        return np.array([p.srd_reported_m for p in self.positions])


def solve_campaign_static(acc: CampaignAccumulator, centres_of_m, detector: DetectorSpec,
                          sdd_reported_m: float, **kwargs) -> StaticResult:
    """Static geometry from the first stage position of a campaign (section 3.1).

    kwargs go to solve_static (e.g. ``centre_uncertainty_m`` from the reference object)."""
    if not acc.positions:
        raise ValueError("no observations yet")
    p = acc.positions[0]
    return solve_static(p.observations(), centres_of_m, detector, p.srd_reported_m, sdd_reported_m, **kwargs)


def solve_campaign_position(acc: CampaignAccumulator, k: int, static: StaticResult, detector: DetectorSpec,
                            mode: str = "multi", multi: MotionResult | None = None, **kwargs) -> MotionResult:
    """Error motions of stage position k (0-based; k = 0 is the reference) relative to k = 0.

    ``multi``: the multi-projection result of the same position, when solved already; a
    "single" solve takes the size of the per-projection shared shift from it (else it solves
    the multi-projection problem itself for that).
    """
    if not 0 <= k < len(acc.positions):
        raise ValueError(f"stage position {k} not in 0..{len(acc.positions) - 1}")
    p = acc.positions[k]
    if mode == "single" and multi is not None and multi.success and multi.noise is not None:
        kwargs.setdefault("view_sd_px", multi.noise.view_sd_px)
    return solve_error_motion(p.observations(), static, detector, p.srd_reported_m,
                              acc.positions[0].srd_reported_m, mode=mode, **kwargs)


def static_result_from_estimate(w, covariance, centres_of_m, *, names=None, units=None, rms_px=np.nan,
                                n_obs=0, message="rebuilt from a published estimate", obs=None, detector=None,
                                centre_uncertainty_m=None) -> StaticResult:
    """A StaticResult holding a published static estimate (values and covariance).

    Lets a consumer of ``/ct/geometry`` (or of a results file) run the error-motion
    solver with the static uncertainty propagated, exactly as if it had solved
    the static geometry itself. With the first position's observations ``obs``
    (and the ``detector``) the uncertainty is rebuilt from the data at the
    published estimate, as the static solver computes it (noise model,
    noise-only covariance, sensitivity to the calibrated centres): the
    error-motion node and the offline solve then propagate the centres'
    uncertainty through both paths. Fields only the original solve knows
    (residuals, evaluation counts) are empty.
    """
    from .geometry import STATIC_PARAM_NAMES, STATIC_PARAM_UNITS, static_to_detector_frame  # noqa: PLC0415

    x = np.asarray(w, dtype=float)
    cov = np.asarray(covariance, dtype=float) if covariance is not None else np.full((len(x), len(x)), np.nan)
    centres = np.asarray(centres_of_m, dtype=float)
    noise = cov_noise = centre_sens = u_c = d_sys = None
    if obs is not None and detector is not None and len(x) == 13 and obs.n_obs > 0:
        from .ct_model import StaticKernel  # noqa: PLC0415
        from .static_solver import static_uncertainty  # noqa: PLC0415

        kern = StaticKernel(obs, centres, detector)
        sigma = None if obs.sigma_px is None else kern.blocked_weights(obs.sigma_px)
        _info, noise, cov_noise, centre_sens, _total, d_sys = static_uncertainty(x, kern, obs, sigma, len(centres),
                                                                                 centre_uncertainty_m)
        if centre_sens is not None:
            u_c = np.broadcast_to(np.asarray(centre_uncertainty_m, dtype=float), (len(centres),))
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sd, sd)
    return StaticResult(
        x=x, names=tuple(names or STATIC_PARAM_NAMES), units=tuple(units or STATIC_PARAM_UNITS),
        covariance=cov, correlation=corr, normal_inverse=cov, variance_factor=1.0,
        residuals_px=np.zeros((0, 2)), rms_px=float(rms_px), cost=np.nan, success=True, status=0,
        message=message, nfev=0, njev=0, n_iter=0, n_obs=int(n_obs), n_views=0, n_spheres=len(centres),
        condition=np.nan, geometry=static_to_detector_frame(x[:13], centres), x0=x.copy(), loss="linear",
        f_scale_px=None, terms=(), centres_of_m=centres, weights=None, noise=noise, covariance_noise=cov_noise,
        centre_sensitivity=centre_sens, centre_uncertainty_m=u_c, systematic_sensitivity=d_sys)


def campaign_error_map(acc: CampaignAccumulator, motion_results: dict, static: StaticResult, *,
                       definition: str = "travel", name: str = "multi", index_repeatability_rad=None):
    """Error map over the positions solved so far (position 0 = reference, zero motion).

    The uncertainty is the joint covariance of all positions: each position's
    own (conditional) covariance plus the static geometry's, which every
    position shares (error_map.joint_motion_covariance), and the detector's
    shared systematic pattern (MotionResult.systematic_shift), one more
    shared input of unit variance.

    Parameters
    ----------
    motion_results : dict k -> MotionResult (successful ones are used)
    definition : {"travel", "detector"}
        See error_map.py.
    name : str
    index_repeatability_rad : float, optional
        Rotary indexing repeatability to include in u(yaw) [rad].

    Returns
    -------
    (ErrorMap, ks) with ks the position indices included (0 first).
    """
    from .error_map import error_map, joint_motion_covariance  # noqa: PLC0415

    ks = [0] + sorted(k for k, r in motion_results.items() if k > 0 and r.success)
    motions = np.zeros((len(ks), 6))
    covs = np.zeros((len(ks), 6, 6))
    n_s = len(static.x)
    sens = np.zeros((len(ks), 6, n_s))
    s_noise = static.covariance if static.covariance_noise is None else static.covariance_noise
    have_sens = s_noise is not None and np.all(np.isfinite(s_noise))
    u_c = static.centre_uncertainty_m
    n_c = 0 if static.centre_sensitivity is None else static.centre_sensitivity.shape[1]
    csens = np.zeros((len(ks), 6, n_c))
    have_centres = u_c is not None and n_c > 0
    dsys = np.zeros((len(ks), 6, 1))
    have_sys = static.systematic_sensitivity is not None or any(
        getattr(motion_results[k], "systematic_shift", None) is not None for k in ks[1:])
    for i, k in enumerate(ks[1:], start=1):
        r = motion_results[k]
        motions[i] = r.x
        covs[i] = r.covariance                      # conditional on the static geometry
        if getattr(r, "static_sensitivity", None) is not None and r.static_sensitivity.shape == (6, n_s):
            sens[i] = r.static_sensitivity
        else:
            have_sens = False
        if have_centres and getattr(r, "centre_sensitivity", None) is not None and r.centre_sensitivity.shape == (6, n_c):
            csens[i] = r.centre_sensitivity
        else:
            have_centres = False
        if getattr(r, "systematic_shift", None) is not None:
            dsys[i, :, 0] = r.systematic_shift
    srd = np.array([acc.positions[k].srd_reported_m for k in ks])
    if have_sens and have_centres:
        shared = np.diag(np.repeat(np.asarray(u_c) ** 2, 3))
        if have_sys:
            csens = np.concatenate([csens, dsys], axis=2)
            shared = np.block([[shared, np.zeros((len(shared), 1))], [np.zeros((1, len(shared))), np.ones((1, 1))]])
        joint = joint_motion_covariance(covs, sens, s_noise, csens, shared)
    elif have_sens:
        joint = joint_motion_covariance(covs, sens, static.covariance_without_systematic,
                                        *((dsys, np.ones((1, 1))) if have_sys else ()))
    else:
        joint = joint_motion_covariance(covs, *((None, None, dsys, np.ones((1, 1))) if have_sys else ()))
    return error_map(srd, motions, joint, definition=definition, name=name,
                     index_repeatability_rad=index_repeatability_rad), ks


def revisit_groups(srd_reported_m, tolerance_m: float = DEFAULT_POSITION_TOLERANCE_M) -> list:
    """Positions that visit the same nominal SRD: lists of position indices (time order), one
    per nominal SRD visited more than once.

    Two positions are visits of one nominal SRD when their reported SRDs (medians) agree within
    ``tolerance_m`` (chained: sorted readings closer than the tolerance to their neighbour).
    """
    srd = np.asarray(srd_reported_m, dtype=float).reshape(-1)
    if srd.size == 0:
        return []
    order = np.argsort(srd, kind="stable")
    groups, cur = [], [int(order[0])]
    for a, b in zip(order[:-1], order[1:]):
        if srd[b] - srd[a] <= tolerance_m:
            cur.append(int(b))
        else:
            groups.append(cur)
            cur = [int(b)]
    groups.append(cur)
    return [sorted(g) for g in groups if len(g) > 1]


def repeatability(em, ks, tolerance_m: float = DEFAULT_POSITION_TOLERANCE_M) -> list:
    """Repeatability of the stage from revisits: every error-map component at each revisit of a
    nominal SRD minus its value at the first visit, with the standard uncertainty of that
    difference from the map's joint covariance (correlations through the shared static geometry
    included).

    Parameters
    ----------
    em : error_map.ErrorMap
        A map whose row i is stage position ``ks[i]``.
    ks : sequence of int
        Position index of each map row (campaign_error_map's second return value).
    tolerance_m : float
        Reported SRDs within this of each other are one nominal SRD [m].

    Returns
    -------
    list of dict, one per nominal SRD visited more than once (JSON-ready, SI units; angles also
    in arcseconds): ``positions`` (time order), ``srd_reported_m``, per component ``<c>``
    (differences to the first visit, one per later visit), ``u_<c>`` (or None), and
    ``range_<c>`` (max - min over all visits).
    """
    from .error_map import ARCSEC_PER_RAD, COMPONENT_FIELDS  # noqa: PLC0415

    ks = [int(k) for k in ks]
    srd = np.asarray(em.srd_reported_m, dtype=float)
    out = []
    for rows in revisit_groups(srd, tolerance_m):
        first, later = rows[0], rows[1:]
        g = {"positions": [ks[i] for i in rows], "srd_reported_m": [float(srd[i]) for i in rows],
             "definition": em.definition,
             "meaning": "value at each revisit minus the value at the first visit of the same nominal SRD"}
        for c, f in enumerate(COMPONENT_FIELDS):
            v = em.values(f)
            d = np.array([v[i] - v[first] for i in later])
            u = None
            if em.covariance is not None:
                cv = em.covariance
                a = 6 * first + c
                u = [float(np.sqrt(max(cv[6 * i + c, 6 * i + c] + cv[a, a] - 2 * cv[6 * i + c, a], 0.0)))
                     for i in later]
            g[f] = d.tolist()
            g["u_" + f] = u
            g["range_" + f] = float(np.ptp(v[rows]))
            if f.endswith("_rad"):
                g[f.replace("_rad", "_arcsec")] = (d * ARCSEC_PER_RAD).tolist()
        out.append(g)
    return out


def campaign_residuals(acc: CampaignAccumulator, static_x, centres_of_m, detector: DetectorSpec,
                       motions: dict, terms=(), label: str = "campaign"):
    """Reprojection residuals (observed - modelled) [px] of every stage position with a model.

    Position 0 against the static model at ``static_x``; position k > 0 against the error-motion
    model with ``motions[k]`` (6,) on the k = 1 geometry. Positions without a motion are left
    out. Returns a report.ReprojectionResiduals, or None when nothing is left.
    """
    from .ct_model import motion_residuals, static_residuals  # noqa: PLC0415
    from .geometry import static_to_detector_frame  # noqa: PLC0415
    from .report import ReprojectionResiduals  # noqa: PLC0415

    x = np.asarray(static_x, dtype=float)
    if not acc.positions or not np.all(np.isfinite(x)):
        return None
    centres = np.asarray(centres_of_m, dtype=float)
    geom = static_to_detector_frame(x[:13], centres)
    parts = []
    for k, pos in enumerate(acc.positions):
        obs = pos.observations()
        if obs.n_obs == 0 or (k > 0 and k not in motions):
            continue
        if k == 0:
            r = static_residuals(x, obs, centres, detector, terms)
        else:
            r = motion_residuals(np.asarray(motions[k], dtype=float), obs, geom, detector, terms, x[13:])
        parts.append((r.reshape(-1, 2), obs.view_index, obs.sphere_index, np.full(obs.n_obs, k)))
    if not parts:
        return None
    return ReprojectionResiduals(*(np.concatenate(p) for p in zip(*parts)), label=label)


# ------------------------------------------------------------------------------------------------
# Frame processing: detection + identity, frame by frame (detector node and offline replay)

REASON_FLAGS = {"overlap": 1, "edge_cut": 2, "not_a_sphere_size": 3, "not_a_sphere_shape": 3,
                "not_a_sphere_contrast": 3, "fit_failed": 4, "background_structure": 4, "ambiguous_identity": 5,
                "unmatched": 5,
                "not_initialised": 5}


@dataclass(frozen=True)
class FrameResult:
    """Observations of one frame, accepted and rejected, with ids.

    ``ids`` is -1 and ``flag`` non-zero (metro_msgs/SphereObservation codes) for
    rejections; ``reason`` says why in words.
    """

    stamp_ns: int
    alpha_rad: float
    srd_reported_m: float
    ids: np.ndarray           # (M,)
    flag: np.ndarray          # (M,) uint8
    reason: tuple             # (M,)
    centre_px: np.ndarray     # (M, 2)
    sigma_px: np.ndarray      # (M,)
    semi_axes_px: np.ndarray  # (M, 2) the cone section's: fitted + the detector's level shift
    angle_rad: np.ndarray     # (M,)
    fit_rms_px: np.ndarray    # (M,)
    systematic_px: np.ndarray | None = None   # (M, 2) detect.FrameDetections.systematic_px, NaN for rejections

    def accepted_systematic(self):
        """(Q, 2) shared systematic pattern of the accepted observations [px], or None."""
        return None if self.systematic_px is None else self.systematic_px[self.flag == 0]

    def accepted(self):
        """(ids, centre_px, sigma_px, semi-minor axis [px]) of the accepted observations."""
        ok = self.flag == 0
        return self.ids[ok], self.centre_px[ok], self.sigma_px[ok], self.semi_axes_px[ok, 1]


class FrameProcessor:
    """Sphere detection and identity for a stream of CT frames.

    Identity is initialised afresh at every stage position (a new position
    starts when the reported SRD moves, PositionSegmenter) from that position's first
    ``init_frames`` frames, which are buffered and then released together;
    afterwards every frame is assigned as it comes. Identity therefore depends
    only on the frames themselves, never on when a solved geometry arrives:
    the same frames in the same order give the same results, live or offline.

    With ``track_identity`` (default) a position after the first starts from the
    previous position's identification pose moved by the reported travel
    (SphereIdentifier.initialise_tracked, about 50 times cheaper than the pose
    search); the full pose search runs when that does not explain the frames.
    """

    def __init__(self, ref, detector: DetectorSpec, sdd_reported_m: float, flat_field_counts: float,
                 init_frames: int = 6, detection_settings=None, identify_settings=None,
                 srd_tolerance_m: float = DEFAULT_POSITION_TOLERANCE_M, track_identity: bool = True, dark=None):
        from .identify import SphereIdentifier  # noqa: PLC0415

        self.ref = ref
        self.detector = detector
        self.sdd = float(sdd_reported_m)
        self.flat = (np.asarray(flat_field_counts, dtype=np.float32) if np.ndim(flat_field_counts)
                     else (float(flat_field_counts) if flat_field_counts else None))   # scalar or flat-field image
        self.dark = dark
        self.init_frames = max(1, int(init_frames))
        self.segmenter = PositionSegmenter(srd_tolerance_m)
        self.srd_tolerance_m = self.segmenter.tolerance_m
        self.detection_settings = detection_settings
        self.identify_settings = identify_settings
        self._new_identifier = lambda: SphereIdentifier(ref.ids, ref.centres_of_m, ref.diameters_m, detector,
                                                        self.sdd, identify_settings)
        self.identifier = None
        self.track = bool(track_identity)
        self._track_from = None     # (identification pose, its SRD) of the previous position
        self._init_srd = None
        self._diagnosed = False
        self._pending = []          # (stamp, alpha, srd, detections) of this position before initialisation
        self._set_aside = []        # the same, left out of a failed initialisation (assigned once one succeeds)
        self.srd_current = None
        self.n_frames = 0
        self.init_messages = []     # (srd, message) of every identity initialisation

    def diameter_range_px(self, srd_m: float):
        from .detect import shadow_diameter_range_px  # noqa: PLC0415

        return shadow_diameter_range_px(self.ref.diameters_m, self.ref.centres_of_m, self.sdd, srd_m,
                                        self.detector.pixel_pitch_m)

    def detect(self, image, encoding: str, srd_m: float):
        from .detect import detect_spheres  # noqa: PLC0415

        return detect_spheres(image, encoding=encoding, flat_field_counts=self.flat, dark=self.dark,
                              expected_shape=(self.detector.rows, self.detector.cols),
                              diameter_px_range=self.diameter_range_px(srd_m), settings=self.detection_settings)

    def push(self, stamp_ns: int, image, encoding: str, alpha_rad: float, srd_m: float) -> list:
        """Process one frame; returns the FrameResults now ready (0, 1, or a buffered batch).

        Raises detect.FrameError for a frame that cannot be used (the caller logs and skips it),
        including a stage reading no instrument can produce (non-finite, or the object at or
        beyond the detector: SRD outside (0, SDD)).
        """
        self.check_stage(alpha_rad, srd_m)
        det = self.detect(image, encoding, srd_m)      # may raise FrameError
        return self.push_detections(stamp_ns, det, alpha_rad, srd_m)

    def check_stage(self, alpha_rad: float, srd_m: float) -> None:
        """Raise detect.FrameError for a stage reading no instrument can produce."""
        from .detect import FrameError  # noqa: PLC0415

        if not (np.isfinite(alpha_rad) and np.isfinite(srd_m) and 0.0 < srd_m < self.sdd):
            raise FrameError("bad_stage_reading", f"rotary angle {alpha_rad} rad, reported SRD {srd_m} m: the SRD "
                                                  f"must be finite and between 0 and the source-to-detector "
                                                  f"distance {self.sdd} m")

    def push_detections(self, stamp_ns: int, det, alpha_rad: float, srd_m: float) -> list:
        """The identity half of :meth:`push`, for detections made elsewhere (``detect`` of a
        FrameProcessor with the same settings, e.g. in a worker process): frames given in the
        same order give the same results bit for bit as :meth:`push`."""
        self.n_frames += 1
        out = []
        _k, new_position = self.segmenter.push(srd_m)
        if new_position:
            out += self.flush()                        # the previous position ends here
            if self.identifier is not None and self.identifier.initialised and self.identifier._geom is None:
                self._track_from = (self.identifier._w.copy(), self._init_srd)
            self.identifier = self._new_identifier()
            self._diagnosed = False
        self.srd_current = self.segmenter.reference_m
        if self.identifier.initialised:
            return out + [self._assign(int(stamp_ns), float(alpha_rad), float(srd_m), det)]
        self._pending.append((int(stamp_ns), float(alpha_rad), float(srd_m), det))
        if len(self._pending) >= self.init_frames:
            out += self._try_initialise(final=False)
        return out

    def flush(self) -> list:
        """Release the frames still buffered (end of a position or of the stream): identity is
        initialised from however many there are, or they come out rejected."""
        return self._try_initialise(final=True) if (self._pending or self._set_aside) else []

    def _try_initialise(self, final: bool) -> list:
        """Initialise identity from the pending frames. On failure (not final) the oldest is set aside and
        the next frame tried with the rest; the frames set aside are assigned, in recording order, once an
        initialisation succeeds, or come out rejected with the reason at the end: no frame is dropped."""
        p = self._pending if self._pending else self._set_aside[-self.init_frames:]
        centres, alphas, srd = [f[3].centre_px for f in p], [f[1] for f in p], p[0][2]
        init = None
        if self.track and self._track_from is not None:
            init = self.identifier.initialise_tracked(self._track_from[0], self._track_from[1], centres, alphas, srd)
            self.init_messages.append((srd, init.message))
        if init is None or not init.success:
            # the mirrored / reversed diagnosis costs three pose searches: once per position
            init = self.identifier.initialise(centres, alphas, srd, diagnose=not self._diagnosed)
            self._diagnosed = self._diagnosed or not init.success
            self.init_messages.append((srd, init.message))
        if init.success:
            self._init_srd = srd
        if not init.success and not final:
            self._set_aside.append(self._pending.pop(0))    # try again with a newer set of frames
            return []
        # not initialised -> every detection rejected with a reason
        out = [self._assign(*f) for f in self._set_aside + self._pending]
        self._pending, self._set_aside = [], []
        return out

    def _assign(self, stamp, alpha, srd, det) -> FrameResult:
        m = len(det.centre_px)
        a = self.identifier.assign(det.centre_px, alpha) if m else None
        ids = a.ids if a is not None else np.zeros(0, np.int64)
        reasons = list(a.reasons) if a is not None else []
        flag = np.array([0 if r == "ok" else REASON_FLAGS.get(r, 5) for r in reasons], dtype=np.uint8)
        cov = np.asarray(det.centre_cov_px2).reshape(-1, 2, 2)
        sigma = np.sqrt(np.maximum(0.5 * (cov[:, 0, 0] + cov[:, 1, 1]), 0.0)) if m else np.zeros(0)
        rej = det.rejected
        nr = len(rej.reason)
        return FrameResult(
            stamp_ns=stamp, alpha_rad=alpha, srd_reported_m=srd,
            ids=np.concatenate([ids, np.full(nr, -1)]).astype(np.int64),
            flag=np.concatenate([flag, [REASON_FLAGS.get(r, 3) for r in rej.reason]]).astype(np.uint8),
            reason=tuple(["" if r == "ok" else r for r in reasons] + [f"{r}: {d}" for r, d in zip(rej.reason, rej.detail)]),
            centre_px=np.concatenate([np.asarray(det.centre_px).reshape(-1, 2), np.asarray(rej.centre_px).reshape(-1, 2)]),
            sigma_px=np.concatenate([sigma, np.full(nr, np.nan)]),
            # the semi-axes of the cone section the centre belongs to: the fitted ellipse's plus the
            # blur's inward level shift (detect.FrameDetections.level_shift_px; the ellipse-centre model)
            semi_axes_px=np.concatenate([np.asarray(det.semi_axes_px).reshape(-1, 2)
                                         + float(det.level_shift_px), np.full((nr, 2), np.nan)]),
            angle_rad=np.concatenate([np.asarray(det.angle_rad).reshape(-1), np.full(nr, np.nan)]),
            fit_rms_px=np.concatenate([np.asarray(det.fit_rms_px).reshape(-1), np.full(nr, np.nan)]),
            systematic_px=None if det.systematic_px is None else np.concatenate(
                [np.asarray(det.systematic_px).reshape(-1, 2), np.full((nr, 2), np.nan)]))


class FrameRateMonitor:
    """Processing time per frame against the interval between frame stamps (smoothed)."""

    def __init__(self, smoothing: float = 0.2, warm_up: int = 5, margin: float = 1.05):
        self.a, self.warm_up, self.margin = smoothing, warm_up, margin
        self.proc_s = self.interval_s = None
        self.last_stamp = None
        self.n = 0

    @staticmethod
    def _ewma(old, new, a):
        return new if old is None else (1 - a) * old + a * new

    def add(self, stamp_ns: int, seconds: float) -> bool:
        """Record one frame; True when frames come faster than they are processed."""
        self.proc_s = self._ewma(self.proc_s, seconds, self.a)
        if self.last_stamp is not None and stamp_ns > self.last_stamp:
            self.interval_s = self._ewma(self.interval_s, (stamp_ns - self.last_stamp) * 1e-9, self.a)
        self.last_stamp = stamp_ns if self.last_stamp is None else max(self.last_stamp, stamp_ns)
        self.n += 1
        return bool(self.n > self.warm_up and self.interval_s and self.proc_s > self.margin * self.interval_s)

    @property
    def processing_hz(self) -> float:
        return 1.0 / self.proc_s if self.proc_s else float("nan")

    @property
    def arrival_hz(self) -> float:
        return 1.0 / self.interval_s if self.interval_s else float("nan")
