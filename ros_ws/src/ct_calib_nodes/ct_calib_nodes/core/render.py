"""Physics-based renderer of cone-beam CT projections of a sphere reference object.

Image formation (all in the detector frame {DF}, detector plane z = 0):

1. The instrument geometry (13 static parameters) and the stage error motion
   place the sphere centres with :func:`geometry.static_to_detector_frame` and
   :func:`geometry.sphere_centres_df` (k = 1 is ``motion = zeros(6)``).
2. Every image pixel is sampled at ``oversample x oversample`` sub-pixel
   points; from the focal spot a ray goes to each point and the exact chord
   length through every sphere (and through the carbon-fibre tube wall, an
   exact hollow finite cylinder) is computed.
3. Beer-Lambert: the sub-ray transmission is ``exp(-sum mu_j * chord_j)``; the
   pixel value is the mean over its sub-rays (the detector integrates
   intensity, not line integrals).
4. Detector blur: a Gaussian of ``blur_sigma_px`` on the expected signal.
5. Noise: counts ~ Poisson(flat_field_counts * T) (see ``poisson_exact_below``).
6. Output: mono16 counts (clipped to 0..65535) or float32 I/I0.

Only the neighbourhood (bounding box) of each sphere shadow is ray traced at
the full sub-sampling, each box with every sphere whose box meets it, so
overlaps are exact. The tube outside those boxes is traced at ``tube_oversample``.

Hidden physics (all off by default; the solvers are never told about them):

- ``focal_spot_drift_m_per_s`` (3,) in {DF}: the focal spot sits at
  ``S(t) = S_0 + drift * time_s``.
- ``encoder_eccentricity_rad`` A and ``encoder_phase_rad`` phi: the true
  rotary angle is ``alpha_true = alpha + A * sin(alpha + phi)`` where alpha is
  the reported (commanded) angle.
- ``detector_distortion_k1_per_m2`` k1: a ray that lands at detector-plane
  position x (metric, from the detector centre) is RECORDED at
  ``x_rec = x * (1 + k1 * |x|^2)``; pixel (c, r) integrates the rays whose
  recorded position falls in it. ``centre_px`` in the truth is the recorded
  position of the true centre projection.
- ``ellipse_centre_bias`` (physics, ON by default): the exact cone-sphere
  silhouette is rendered, whose ellipse centre lies further from the
  principal point than the centre projection by about
  ``SDD * tan(psi) * sec^2(psi) * (r / D)^2`` (Clackdoyle & Mennessier 2011;
  Deng et al. 2015), see :func:`geometry.silhouette_ellipses`. The solvers
  model it (ct_model.py). False translates each shadow so that its ellipse
  centre coincides with the centre projection (the textbook model of the
  paper), for tests of that model only.
- ``effects``: further hidden physics from render_effects.py (detector bow,
  rotary runout and tilt error motions, stage and detector drift, thermal
  expansion of the object, encoder harmonics), applied through small hooks on
  the rotary angle, the placed scene and the detector's recorded position.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import cv2

from .geometry import (  # noqa: F401 - silhouette_ellipses is part of this module's interface
    DetectorFrameGeometry,
    DetectorSpec,
    _check_static,
    project_df,
    silhouette_ellipses,
    sphere_centres_df,
    static_to_detector_frame,
)
from .phantom import MU_STEEL_100KEV_PER_M, ReferenceObject
from . import render_effects

MONO16_MAX = 65535


@dataclass(frozen=True)
class RenderSettings:
    """Physics and hidden-physics switches of :func:`render_projection`.

    Attributes
    ----------
    flat_field_counts : float
        Mean open-beam counts I0 per pixel (mono16 frames).
    mu_sphere_per_m : float
        Linear attenuation of the spheres [1/m]; default steel at ~100 keV
        effective energy (150-225 kV tube, see phantom.py for the source).
    mu_tube_per_m : float or None
        Attenuation of the carbon-fibre tube [1/m]; None uses the tube's own
        ``mu_per_m``; 0 switches the tube off.
    blur_sigma_px : float
        Standard deviation of the Gaussian detector blur [px]; 0 = none.
    oversample : int
        Sub-samples per pixel axis near the spheres (>= 1).
    tube_oversample : int
        Sub-samples per pixel axis for the tube away from the spheres.
    margin_px : int
        Extra pixels traced around each shadow's bounding box.
    poisson : bool
        Add counting noise. If False the image is the expected value.
    poisson_exact_below : float
        Expected counts below which noise is drawn from an exact Poisson law;
        at or above it from N(lam, lam) rounded to integers (same mean and
        variance, skewness error 1/sqrt(lam) < 3 %); ``inf`` gives exact Poisson
        everywhere (about 10x slower at 50000 counts).
    focal_spot_drift_m_per_s : tuple of 3 floats
        Hidden: focal-spot velocity in {DF} [m/s]; zeros = off.
    encoder_eccentricity_rad, encoder_phase_rad : float
        Hidden: angle error amplitude A [rad] and phase phi [rad] of
        ``alpha_true = alpha + A sin(alpha + phi)``; A = 0 = off.
    detector_distortion_k1_per_m2 : float
        Hidden: radial distortion k1 [1/m^2] of the recorded landing position,
        ``x_rec = x (1 + k1 |x|^2)`` about the detector centre; 0 = off.
    ellipse_centre_bias : bool
        Physics, default True: render the exact cone-sphere silhouette; False
        translates each shadow so its ellipse centre is the centre projection
        (the paper's textbook model, for tests of it).
    touch_gap_px : float
        Two shadows count as ``overlapping`` when their bounding circles
        (radius = ellipse semi-major axis) come closer than this [px].
    """

    flat_field_counts: float = 50000.0
    mu_sphere_per_m: float = MU_STEEL_100KEV_PER_M
    mu_tube_per_m: float | None = None
    blur_sigma_px: float = 0.7
    oversample: int = 4
    tube_oversample: int = 1
    margin_px: int = 2
    poisson: bool = True
    poisson_exact_below: float = 1000.0
    focal_spot_drift_m_per_s: tuple = (0.0, 0.0, 0.0)
    encoder_eccentricity_rad: float = 0.0
    encoder_phase_rad: float = 0.0
    detector_distortion_k1_per_m2: float = 0.0
    ellipse_centre_bias: bool = True
    touch_gap_px: float = 1.0
    effects: tuple = ()     # render_effects.RenderEffect instances (hidden physics, off by default)

    def __post_init__(self):
        scalars = {
            "flat_field_counts": self.flat_field_counts,
            "mu_sphere_per_m": self.mu_sphere_per_m,
            "blur_sigma_px": self.blur_sigma_px,
            "encoder_eccentricity_rad": self.encoder_eccentricity_rad,
            "encoder_phase_rad": self.encoder_phase_rad,
            "detector_distortion_k1_per_m2": self.detector_distortion_k1_per_m2,
            "touch_gap_px": self.touch_gap_px,
        }
        for k, v in scalars.items():
            if not np.isfinite(float(v)):
                raise ValueError(f"{k} must be finite, got {v}")
        if self.flat_field_counts <= 0:
            raise ValueError("flat_field_counts must be > 0")
        if self.mu_sphere_per_m < 0 or self.blur_sigma_px < 0:
            raise ValueError("mu_sphere_per_m and blur_sigma_px must be >= 0")
        if self.mu_tube_per_m is not None and not (np.isfinite(self.mu_tube_per_m) and self.mu_tube_per_m >= 0):
            raise ValueError("mu_tube_per_m must be None or finite >= 0")
        if int(self.oversample) < 1 or int(self.tube_oversample) < 1 or int(self.margin_px) < 0:
            raise ValueError("oversample and tube_oversample must be >= 1, margin_px >= 0")
        if not (self.poisson_exact_below >= 0):
            raise ValueError("poisson_exact_below must be >= 0")
        drift = np.asarray(self.focal_spot_drift_m_per_s, dtype=float)
        if drift.shape != (3,) or not np.all(np.isfinite(drift)):
            raise ValueError(f"focal_spot_drift_m_per_s must be 3 finite values, got {drift.shape}")
        object.__setattr__(self, "focal_spot_drift_m_per_s", tuple(float(x) for x in drift))
        object.__setattr__(self, "effects", render_effects.check_effects(self.effects))


@dataclass(frozen=True)
class FrameTruth:
    """Ground truth of one rendered frame (never handed to a solver).

    Attributes
    ----------
    ids : ndarray of shape (N,)
    centre_px : ndarray of shape (N, 2)
        (col, row) [px] of the true projection of each sphere centre with all
        hidden physics applied (what a perfect centre detector reports).
    ellipse_centre_px : ndarray of shape (N, 2)
        (col, row) [px] of the centre of each rendered shadow ellipse (equals
        centre_px unless ``ellipse_centre_bias``; distortion applied to the centre).
    radius_px : ndarray of shape (N,)
        sqrt(a * b) of the shadow ellipse [px] (approximate shadow radius).
    semi_axes_px : ndarray of shape (N, 2)
        Semi-major and semi-minor axes of the shadow ellipse [px] (undistorted).
    in_view : ndarray of shape (N,), bool
        Shadow (ellipse bounding box) lies fully on the detector.
    overlapping : ndarray of shape (N,), bool
        The shadow touches or overlaps another sphere's shadow.
    alpha_rad, alpha_true_rad : float
        Reported and true rotary angle [rad].
    time_s : float
    source_df_m : ndarray of shape (3,)
        Focal spot in {DF} at time_s [m].
    centres_df_m : ndarray of shape (N, 3)
        Sphere centres in {DF} [m].
    geometry : DetectorFrameGeometry
        The k = 1 geometry (undrifted source) from the true static parameters.
    static_w : ndarray of shape (13,)
    motion : ndarray of shape (6,)
    """

    ids: np.ndarray
    centre_px: np.ndarray
    ellipse_centre_px: np.ndarray
    radius_px: np.ndarray
    semi_axes_px: np.ndarray
    in_view: np.ndarray
    overlapping: np.ndarray
    alpha_rad: float
    alpha_true_rad: float
    time_s: float
    source_df_m: np.ndarray
    centres_df_m: np.ndarray
    geometry: DetectorFrameGeometry
    static_w: np.ndarray
    motion: np.ndarray

    @property
    def usable(self) -> np.ndarray:
        """in_view and not overlapping, shape (N,) bool."""
        return self.in_view & ~self.overlapping


@dataclass(frozen=True)
class RenderedFrame:
    """One projection and its truth.

    Attributes
    ----------
    image : ndarray of shape (rows, cols)
        uint16 counts (``output="mono16"``) or float32 I/I0 (``"transmission"``).
    truth : FrameTruth
    n_rays : int
        Number of rays traced (sub-samples), for profiling.
    """

    image: np.ndarray
    truth: FrameTruth
    n_rays: int = 0


# --------------------------------------------------------------------------
# Analytic pieces
# --------------------------------------------------------------------------

def distort(xy_m, k1_per_m2: float) -> np.ndarray:
    """Landing position -> recorded position, ``x (1 + k1 |x|^2)``; shape (..., 2) [m]."""
    xy = np.asarray(xy_m, dtype=float)
    if k1_per_m2 == 0.0:
        return xy
    return xy * (1.0 + k1_per_m2 * np.sum(xy * xy, axis=-1, keepdims=True))


def undistort(xy_rec_m, k1_per_m2: float, iterations: int = 6) -> np.ndarray:
    """Inverse of :func:`distort` by fixed-point iteration (|k1| |x|^2 << 1)."""
    xr = np.asarray(xy_rec_m, dtype=float)
    if k1_per_m2 == 0.0:
        return xr
    x = xr
    for _ in range(iterations):
        x = xr / (1.0 + k1_per_m2 * np.sum(x * x, axis=-1, keepdims=True))
    return x


def true_rotary_angle(alpha_rad: float, settings: RenderSettings) -> float:
    """Encoder eccentricity: ``alpha + A sin(alpha + phi)`` [rad]."""
    return float(alpha_rad + settings.encoder_eccentricity_rad
                 * np.sin(alpha_rad + settings.encoder_phase_rad)
                 + render_effects.angle_delta(settings.effects, alpha_rad))


def sphere_chords(source_df_m, x_m, y_m, centre_df_m, radius_m) -> np.ndarray:
    """Chord length [m] through one sphere of the rays from S to (x, y, 0) in {DF}.

    Parameters
    ----------
    source_df_m : array_like of shape (3,)
    x_m, y_m : ndarray of shape (...)
        Landing points in the detector plane [m].
    centre_df_m : array_like of shape (3,)
    radius_m : float

    Returns
    -------
    ndarray of shape (...)
        ``2 sqrt(r^2 - d^2)`` with d the distance of the sphere centre from the ray.
    """
    s = np.asarray(source_df_m, dtype=float)
    w = np.asarray(centre_df_m, dtype=float) - s
    gx = x_m - s[0]
    gy = y_m - s[1]
    gz = -s[2]
    wg = w[0] * gx + w[1] * gy + w[2] * gz
    g2 = gx * gx + gy * gy + gz * gz
    d2 = (w @ w) - wg * wg / g2
    return 2.0 * np.sqrt(np.maximum(radius_m * radius_m - d2, 0.0))


def tube_chords(source_df_m, x_m, y_m, tube_df) -> np.ndarray:
    """Chord length [m] through a hollow finite cylinder of the rays S -> (x, y, 0).

    Parameters
    ----------
    source_df_m : array_like of shape (3,)
    x_m, y_m : ndarray of shape (...)
    tube_df : tuple
        (axis point A0 (3,), unit axis a (3,), half height [m], outer radius
        [m], inner radius [m]) in {DF}; the tube spans A0 + t a, |t| <= half height.

    Returns
    -------
    ndarray of shape (...)
    """
    a0, ax, half_h, ro, ri = tube_df
    s = np.asarray(source_df_m, dtype=float)
    w = s - a0                        # ray X(t) = S + t g, t in [0, 1] to the detector
    wa = w @ ax
    wp = w - wa * ax
    gx = x_m - s[0]
    gy = y_m - s[1]
    gz = -s[2]
    ga = ax[0] * gx + ax[1] * gy + ax[2] * gz
    g2 = gx * gx + gy * gy + gz * gz
    qa = g2 - ga * ga                 # |g_perp|^2
    hb = wp[0] * gx + wp[1] * gy + wp[2] * gz   # g_perp . w_perp
    # axial slab |wa + t ga| <= half_h
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (-half_h - wa) / ga
        tb = (half_h - wa) / ga
    par = np.abs(ga) < 1e-15
    lo = np.where(par, np.where(abs(wa) <= half_h, -np.inf, np.inf), np.minimum(ta, tb))
    hi = np.where(par, np.where(abs(wa) <= half_h, np.inf, -np.inf), np.maximum(ta, tb))
    lo = np.maximum(lo, 0.0)
    out = np.zeros(np.shape(qa))
    wp2 = wp @ wp
    for sign, rad in ((1.0, ro), (-1.0, ri)):
        if rad <= 0:
            continue
        disc = hb * hb - qa * (wp2 - rad * rad)
        ok = disc > 0
        sq = np.sqrt(np.where(ok, disc, 0.0))
        t1 = (-hb - sq) / qa
        t2 = (-hb + sq) / qa
        seg = np.minimum(hi, t2) - np.maximum(lo, t1)
        out += sign * np.where(ok, np.maximum(seg, 0.0), 0.0)
    return np.maximum(out, 0.0) * np.sqrt(g2)


# --------------------------------------------------------------------------
# Truth
# --------------------------------------------------------------------------

def _check_inputs(static_w, motion, alpha_rad, ref, detector, settings, time_s):
    w = _check_static(static_w)
    m = np.asarray(motion, dtype=float)
    if m.shape != (6,):
        raise ValueError(f"motion must have shape (6,), got {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError("motion contains NaN or inf")
    a = np.asarray(alpha_rad, dtype=float)
    if a.shape != () or not np.isfinite(a):
        raise ValueError(f"alpha_rad must be a finite scalar, got {alpha_rad!r}")
    t = np.asarray(time_s, dtype=float)
    if t.shape != () or not np.isfinite(t):
        raise ValueError(f"time_s must be a finite scalar, got {time_s!r}")
    if not isinstance(ref, ReferenceObject):
        raise ValueError("ref must be a ReferenceObject")
    if not isinstance(detector, DetectorSpec):
        raise ValueError("detector must be a DetectorSpec")
    if not isinstance(settings, RenderSettings):
        raise ValueError("settings must be a RenderSettings")
    return w, m, float(a), float(t)


def _check_render_call(static_w, motion, alpha_rad, ref, detector, settings, rng, time_s, output):
    """Checks shared by the renderers; returns (settings, w, motion, alpha, time)."""
    settings = RenderSettings() if settings is None else settings
    w, m, a, t = _check_inputs(static_w, motion, alpha_rad, ref, detector, settings, time_s)
    if output not in ("mono16", "transmission"):
        raise ValueError(f"output must be 'mono16' or 'transmission', got {output!r}")
    if settings.poisson and not isinstance(rng, np.random.Generator):
        raise ValueError("rng (numpy.random.Generator) is required when settings.poisson is True")
    return settings, w, m, a, t


def _object_points_df(w, ref, motion, alpha_true, extra_of=None):
    pts = ref.centres_of_m if extra_of is None else np.vstack([ref.centres_of_m, extra_of])
    geom = static_to_detector_frame(w, pts)
    c = sphere_centres_df(geom, motion, [alpha_true])[0]
    n = ref.n_spheres
    geom_spheres = DetectorFrameGeometry(geom.source_df_m, geom.stage_df_m, geom.axis_df,
                                         geom.centres_df_m[:n])
    return geom_spheres, c[:n], c[n:]


def _truth_from_placed(ref, detector, settings, w, m, alpha, alpha_true, time_s, geom, centres_df):
    src = geom.source_df_m + np.asarray(settings.focal_spot_drift_m_per_s) * time_s
    pitch = detector.pixel_pitch_m
    k1 = settings.detector_distortion_k1_per_m2
    cp_m = project_df(src, centres_df, DetectorSpec(1, 1, 1.0))  # (col,row) about centre 0: x, -y
    cp_m = np.stack([cp_m[:, 0], -cp_m[:, 1]], axis=1)            # metric (x, y) in the plane
    ell_m, axes_m = silhouette_ellipses(src, centres_df, ref.radii_m)
    rec_cp = render_effects.recorded_from_landing(settings.effects, distort(cp_m, k1), src)
    rec_ell = (render_effects.recorded_from_landing(settings.effects, distort(ell_m, k1), src)
               if settings.ellipse_centre_bias else rec_cp)
    centre_px = np.stack(detector.pixels_from_metric(rec_cp[:, 0], rec_cp[:, 1]), axis=1)
    ell_px = np.stack(detector.pixels_from_metric(rec_ell[:, 0], rec_ell[:, 1]), axis=1)
    axes_px = axes_m / pitch
    # local scale of the distortion map, bounds the recorded shadow size
    scale = 1.0 + 3.0 * abs(k1) * np.sum(ell_m * ell_m, axis=1)
    half = axes_px[:, 0] * scale
    in_view = ((ell_px[:, 0] - half >= -0.5) & (ell_px[:, 0] + half <= detector.cols - 0.5)
               & (ell_px[:, 1] - half >= -0.5) & (ell_px[:, 1] + half <= detector.rows - 0.5))
    diff = ell_px[:, None, :] - ell_px[None, :, :]
    dist = np.sqrt(np.sum(diff * diff, axis=-1))
    lim = half[:, None] + half[None, :] + settings.touch_gap_px
    close = dist < lim
    np.fill_diagonal(close, False)
    return FrameTruth(
        ids=ref.ids.copy(),
        centre_px=centre_px,
        ellipse_centre_px=ell_px,
        radius_px=np.sqrt(axes_px[:, 0] * axes_px[:, 1]),
        semi_axes_px=axes_px,
        in_view=in_view,
        overlapping=close.any(axis=1),
        alpha_rad=alpha,
        alpha_true_rad=alpha_true,
        time_s=time_s,
        source_df_m=src,
        centres_df_m=centres_df,
        geometry=geom,
        static_w=w.copy(),
        motion=m.copy(),
    ), cp_m, ell_m


def frame_truth(static_w, motion, alpha_rad, ref: ReferenceObject, detector: DetectorSpec,
                settings: RenderSettings | None = None, *, time_s: float = 0.0) -> FrameTruth:
    """Truth of a view without rendering: which spheres are visible and non-overlapping.

    Same arguments as :func:`render_projection`; cheap (no ray tracing).
    ``frame_truth(...).usable`` lists the spheres a detector should report.
    """
    settings = RenderSettings() if settings is None else settings
    w, m, a, t = _check_inputs(static_w, motion, alpha_rad, ref, detector, settings, time_s)
    at = true_rotary_angle(a, settings)
    geom, c, _ = _object_points_df(w, ref, m, at)
    geom, c, _ = render_effects.place(settings.effects, geom, c, None, a, t)
    return _truth_from_placed(ref, detector, settings, w, m, a, at, t, geom, c)[0]


# --------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------

def _sample_points(detector, c0, c1, r0, r1, os, k1, effects=(), source_df_m=None):
    """Physical landing points x, y [m] in {DF} of the sub-samples of a pixel box."""
    sub = (np.arange(os) + 0.5) / os - 0.5
    cols = (np.arange(c0, c1 + 1)[:, None] + sub[None, :]).ravel()
    rows = (np.arange(r0, r1 + 1)[:, None] + sub[None, :]).ravel()
    x, y = detector.metric_from_pixels(cols[None, :], rows[:, None])
    x, y = np.broadcast_arrays(x, y)
    if effects:   # recorded = effects(distort(landing)): undo the effects first
        xy = render_effects.landing_from_recorded(effects, np.stack([x, y], axis=-1), source_df_m)
        x, y = xy[..., 0], xy[..., 1]
    if k1 != 0.0:
        xy = undistort(np.stack([x, y], axis=-1), k1)
        x, y = xy[..., 0], xy[..., 1]
    return x, y                                  # each (H*os, W*os)


def _block_mean(a, os):
    h, w = a.shape[0] // os, a.shape[1] // os
    return a.reshape(h, os, w, os).mean(axis=(1, 3))


@dataclass(frozen=True)
class _Scene:
    """Everything placed for one frame (internal)."""

    truth: FrameTruth
    src: np.ndarray          # (3,) focal spot in {DF} at time_s
    centres: np.ndarray      # (N, 3)
    radii: np.ndarray        # (N,)
    shift: np.ndarray        # (N, 2) textbook-mode translation of each shadow [m]
    ell_m: np.ndarray        # (N, 2) physical ellipse centres [m]
    mu_s: float
    mu_t: float
    tube_df: tuple | None
    k1: float
    holders: tuple = ()      # placed holders (core/holders.py), each with .line_integral(src, x, y)


def _place_scene(w, m, a, t, ref, detector, settings, holders=()) -> _Scene:
    at = true_rotary_angle(a, settings)
    tube = ref.tube
    mu_t = 0.0 if tube is None else (tube.mu_per_m if settings.mu_tube_per_m is None else settings.mu_tube_per_m)
    extra = None
    if tube is not None and mu_t > 0:
        extra = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    anchors = [h.anchor_points_of() for h in holders]
    if anchors:
        extra = np.vstack(([] if extra is None else [extra]) + anchors)
    geom, centres, extra_df = _object_points_df(w, ref, m, at, extra)
    geom, centres, extra_df = render_effects.place(settings.effects, geom, centres, extra_df, a, t)
    placed = []
    if anchors:
        k = 0 if not (tube is not None and mu_t > 0) else 2
        for h, an in zip(holders, anchors):
            placed.append(h.placed(extra_df[k:k + len(an)]))
            k += len(an)
        extra = extra[:2] if (tube is not None and mu_t > 0) else None
    truth, cp_m, ell_m = _truth_from_placed(ref, detector, settings, w, m, a, at, t, geom, centres)
    # textbook mode: evaluate sphere i's exact shadow at X + (ellipse centre - centre projection)
    shift = np.zeros((ref.n_spheres, 2))
    if not settings.ellipse_centre_bias:
        shift[:] = ell_m - cp_m
    tube_df = None
    if extra is not None:
        ax = extra_df[1] - extra_df[0]
        tube_df = (extra_df[0], ax / np.linalg.norm(ax), tube.height_m / 2.0,
                   tube.outer_radius_m, tube.inner_radius_m)
    return _Scene(truth, truth.source_df_m, centres, ref.radii_m, shift, ell_m,
                  float(settings.mu_sphere_per_m), float(mu_t), tube_df,
                  float(settings.detector_distortion_k1_per_m2), tuple(placed))


def _line_integrals(sc: _Scene, xs, ys, members) -> np.ndarray:
    """sum_j mu_j * chord_j of the rays S -> (xs, ys, 0), spheres ``members`` + tube."""
    line = np.zeros(np.shape(xs))
    for j in members:
        line += sc.mu_s * sphere_chords(sc.src, xs + sc.shift[j, 0], ys + sc.shift[j, 1],
                                        sc.centres[j], sc.radii[j])
    if sc.tube_df is not None:
        line += sc.mu_t * tube_chords(sc.src, xs, ys, sc.tube_df)
    for h in sc.holders:
        line += h.line_integral(sc.src, xs, ys)
    return line


def render_projection_bruteforce(static_w, motion, alpha_rad, ref: ReferenceObject, detector: DetectorSpec,
                                 settings: RenderSettings | None = None, rng: np.random.Generator | None = None,
                                 *, time_s: float = 0.0, output: str = "mono16",
                                 rows_per_chunk: int = 32) -> RenderedFrame:
    """Reference renderer: every sub-sample of every pixel traced through every sphere.

    Same physics and arguments as :func:`render_projection` (the tube is traced
    at ``oversample`` everywhere), without the bounding-box shortcut. Slow:
    meant for tests and benchmarks that check the fast renderer against it.
    """
    settings, w, m, a, t = _check_render_call(static_w, motion, alpha_rad, ref, detector, settings, rng,
                                              time_s, output)
    sc = _place_scene(w, m, a, t, ref, detector, settings)
    os_ = int(settings.oversample)
    trans = np.ones((detector.rows, detector.cols), dtype=np.float32)
    allj = np.arange(ref.n_spheres)
    for r0 in range(0, detector.rows, rows_per_chunk):
        r1 = min(r0 + rows_per_chunk, detector.rows) - 1
        xs, ys = _sample_points(detector, 0, detector.cols - 1, r0, r1, os_, sc.k1, settings.effects, sc.src)
        trans[r0:r1 + 1] = _block_mean(np.exp(-_line_integrals(sc, xs, ys, allj)), os_)
    n_rays = detector.rows * detector.cols * os_ * os_
    return _finish(trans, sc.truth, settings, rng, output, n_rays)


def render_projection(static_w, motion, alpha_rad, ref: ReferenceObject, detector: DetectorSpec,
                      settings: RenderSettings | None = None, rng: np.random.Generator | None = None,
                      *, time_s: float = 0.0, output: str = "mono16", holders=()) -> RenderedFrame:
    """Render one cone-beam projection of a sphere reference object.

    Parameters
    ----------
    static_w : array_like of shape (13,)
        True static parameters (geometry.py order) [m, rad].
    motion : array_like of shape (6,)
        True error motion of the stage position (zeros = k = 1) [m, rad].
    alpha_rad : float
        Reported rotary angle [rad] (the encoder reading).
    ref : ReferenceObject
    detector : DetectorSpec
    settings : RenderSettings, optional
    rng : numpy.random.Generator
        Required when ``settings.poisson`` is True.
    time_s : float
        Acquisition time [s] (focal-spot drift).
    output : {"mono16", "transmission"}
        uint16 counts, or float32 I/I0 (noisy counts / I0 if poisson).
    holders : sequence of core.holders.PlateHolder, optional
        Extra absorbers in {OF} that turn with the object (e.g. an acrylic plate).

    Returns
    -------
    RenderedFrame
    """
    settings, w, m, a, t = _check_render_call(static_w, motion, alpha_rad, ref, detector, settings, rng,
                                              time_s, output)

    sc = _place_scene(w, m, a, t, ref, detector, settings, tuple(holders))
    truth, ell_m, k1, src = sc.truth, sc.ell_m, sc.k1, sc.src
    tube, tube_df = ref.tube, sc.tube_df
    os_ = int(settings.oversample)

    trans = np.ones((detector.rows, detector.cols), dtype=np.float32)
    n_rays = 0
    if sc.holders:      # holders (and the tube) over the whole frame, edges re-traced (core/holders.py)
        from .holders import trace_background  # noqa: PLC0415
        trans, n_rays = trace_background(lambda x, y: _line_integrals(sc, x, y, []), detector, k1,
                                         int(settings.tube_oversample), _sample_points, settings.effects, src)
    elif tube_df is not None:
        a0, ax = tube_df[0], tube_df[1]
        # bounding box of the tube's shadow from the 8 corners of its box
        u = np.cross(ax, [1.0, 0.0, 0.0])
        if np.linalg.norm(u) < 1e-6:
            u = np.cross(ax, [0.0, 0.0, 1.0])
        u /= np.linalg.norm(u)
        v = np.cross(ax, u)
        ro, hh = tube.outer_radius_m, tube.height_m / 2.0
        corners = np.array([a0 + sa * hh * ax + sb * ro * u + sc_ * ro * v
                            for sa in (-1, 1) for sb in (-1, 1) for sc_ in (-1, 1)])
        pc = project_df(src, corners, DetectorSpec(1, 1, 1.0))
        pc = distort(np.stack([pc[:, 0], -pc[:, 1]], axis=1), k1)
        cc, rr = detector.pixels_from_metric(pc[:, 0], pc[:, 1])
        c0 = max(int(np.floor(cc.min())) - 1, 0)
        c1 = min(int(np.ceil(cc.max())) + 1, detector.cols - 1)
        r0 = max(int(np.floor(rr.min())) - 1, 0)
        r1 = min(int(np.ceil(rr.max())) + 1, detector.rows - 1)
        if c0 <= c1 and r0 <= r1:
            tos = int(settings.tube_oversample)
            xs, ys = _sample_points(detector, c0, c1, r0, r1, tos, k1, settings.effects, src)
            tt = np.exp(-_line_integrals(sc, xs, ys, []))
            n_rays += tt.size
            trans[r0:r1 + 1, c0:c1 + 1] = _block_mean(tt, tos) if tos > 1 else tt

    # sphere boxes in recorded pixels
    ell_px = truth.ellipse_centre_px
    scale = 1.0 + 3.0 * abs(k1) * np.sum(ell_m * ell_m, axis=1)
    half = truth.semi_axes_px[:, 0] * scale + 1.0 + settings.margin_px
    boxes = np.stack([np.floor(ell_px[:, 0] - half), np.ceil(ell_px[:, 0] + half),
                      np.floor(ell_px[:, 1] - half), np.ceil(ell_px[:, 1] + half)], axis=1).astype(int)
    onscreen = ((boxes[:, 1] >= 0) & (boxes[:, 0] <= detector.cols - 1)
                & (boxes[:, 3] >= 0) & (boxes[:, 2] <= detector.rows - 1))
    # Each on-screen sphere's box is traced with every sphere whose box meets
    # it. A sphere's shadow lies inside its own box, so any sphere that
    # shadows a pixel of box i is among those, and the pixels shared by two
    # boxes get the same (exact) value from either: writing order is irrelevant.
    b = boxes
    for i in np.nonzero(onscreen)[0]:
        c0, c1 = max(b[i, 0], 0), min(b[i, 1], detector.cols - 1)
        r0, r1 = max(b[i, 2], 0), min(b[i, 3], detector.rows - 1)
        members = np.nonzero((b[:, 0] <= c1) & (c0 <= b[:, 1]) & (b[:, 2] <= r1) & (r0 <= b[:, 3]))[0]
        xs, ys = _sample_points(detector, c0, c1, r0, r1, os_, k1, settings.effects, src)
        line = _line_integrals(sc, xs, ys, members)
        n_rays += line.size
        trans[r0:r1 + 1, c0:c1 + 1] = _block_mean(np.exp(-line), os_)

    return _finish(trans, truth, settings, rng, output, n_rays)


def _finish(trans, truth, settings, rng, output, n_rays):
    """Blur, noise and output conversion of a transmission image."""
    if settings.blur_sigma_px > 0:
        trans = cv2.GaussianBlur(trans, (0, 0), settings.blur_sigma_px,
                                 borderType=cv2.BORDER_REPLICATE)
    i0 = float(settings.flat_field_counts)
    if settings.poisson:
        lam = trans * np.float32(i0)
        counts = _counting_noise(lam, rng, settings.poisson_exact_below)
        if output == "mono16":
            img = np.clip(counts, 0, MONO16_MAX).astype(np.uint16)
        else:
            img = (counts / i0).astype(np.float32)
    else:
        if output == "mono16":
            img = np.clip(np.rint(trans.astype(np.float64) * i0), 0, MONO16_MAX).astype(np.uint16)
        else:
            img = trans.astype(np.float32)
    return RenderedFrame(image=img, truth=truth, n_rays=int(n_rays))


def _counting_noise(lam, rng, exact_below):
    """Counts with mean and variance lam: exact Poisson below ``exact_below``, else rounded normal."""
    lam = np.asarray(lam, dtype=np.float32)
    if not np.isfinite(exact_below) or np.all(lam < exact_below):
        return rng.poisson(lam.astype(np.float64)).astype(np.float64)
    z = rng.standard_normal(lam.shape, dtype=np.float32)
    out = np.rint(lam + np.sqrt(lam) * z).astype(np.float64)
    low = lam < exact_below
    if np.any(low):
        out[low] = rng.poisson(lam[low].astype(np.float64))
    return out
