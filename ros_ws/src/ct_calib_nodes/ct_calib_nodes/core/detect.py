"""Sub-pixel detection of sphere shadows in CT projections.

One pure function, :func:`detect_spheres`, turns one projection (counts in
``mono16``/``16UC1``/``mono8``/``8UC1`` or ``32FC1`` transmission, see
INTERFACES.md) into the ellipse centres of every sphere shadow it can
measure, plus the list of candidates it refused and why. It keeps no state,
so a bad frame raises :class:`FrameError` for that frame only and the rest of
a run is unaffected. Nothing in it assumes a particular holder (tube, plate,
foam) or its orientation in the image.

Pipeline (one named function per stage; numbers are the defaults of
:class:`DetectionSettings`)
------------------------------------------------------------------
1. Flat field, :func:`to_transmission`: frame checks and
   ``T = (I - dark) / (flat - dark)`` (float32; flat a scalar or an image, dark
   a level or an image, both optional). Bad frames -> :class:`FrameError`.
2. Segmentation background, ``_segmentation_background``: the pointwise
   minimum of closings with line segments in 6 directions, longer than a
   shadow (half resolution, 16 bit). Each closing removes every shadow and
   keeps straight steps of any orientation (a monotone profile is its own
   closing); the minimum keeps dark bands long in some direction (tube walls
   at any tilt, a plate seen edge-on).
3. Candidates, ``_candidates``: ``T / background < 1 - 0.10`` (at 50000
   counts ~22 noise sd), 8-connected components, screening with a reason
   code per refusal: ``edge_cut``, ``not_a_sphere_size``, ``overlap`` (too
   large, elongated or not elliptical, or a neighbour closer than 4 px, whose
   penumbra would bias the edge). A blob refused as merged is first split by a
   binary opening with a disk of 0.8 x the smallest shadow (a sphere on a band,
   two shadows joined by their rims) and the pieces screened. A piece still
   refused as merged whose largest inscribed disk holds all its depth (the rest
   shallower than half of it: a bump of a thin band) is screened as that disk
   (``band_core``). Overlapping shadows are rejected, never split into two fits.
4. Local background per shadow, ``_local_backgrounds``: the direction of the
   strongest structure round the shadow from the structure tensor of the
   frame's gradients off the shadows, replaced by the frame's dominant
   direction if within ``snap_sigma`` sd of its own noise of it
   (``_blend_direction``), then snapped to the pixel axes within 1.5 deg; on a
   grid turned to it, every line across the shadow is fitted by a straight line
   along the structure through the samples outside the shadow (radius + 3 px;
   other shadows masked; samples 4 noise sd below the first fit dropped), so
   steps and bands of any orientation through the shadow and any smooth
   gradient (heel effect, vignetting) are interpolated across it. Hot
   and dead pixels in these windows (beyond all 8 neighbours by 6 noise sd)
   are replaced by their neighbours' mean and counted.
5. Sub-pixel edges, ``_edge_points``: ``n_rays`` radial profiles from the
   blob centre, exact (float64 weight) bilinear interpolation, divided by the
   local background, cut at the iso-level ``1 - 0.5 (1 - q_in)`` half way
   between the background and the inner shadow. Every iso-transmission
   contour of a sphere is an iso-chord contour, i.e. the section of a circular
   cone of rays around the source-to-centre line, hence an exact ellipse.
   A second pass re-centres the rays on the first fit.
5. Ellipse fit of the edge points. OpenCV's ``fitEllipse`` (Fitzgibbon-type
   algebraic fit), ``fitEllipseAMS``, ``fitEllipseDirect`` and a geometric
   (orthogonal distance, Gauss-Newton) refinement are all available through
   ``DetectionSettings.ellipse_fitter``; their measured centre accuracy on
   rendered frames is in doc/ct_detect.md. With 64 edge points spread evenly
   round a near-circle and edge noise of a few hundredths of a pixel, the
   algebraic fitters' bias is O(sigma^2 / R) ~ 1e-4 px and all four agree to
   well under 0.005 px, so the default is ``cv2.fitEllipse`` (fastest; the
   geometric refinement costs ~10x more and buys nothing measurable).
6. Rejection after the fit, ``_screen_fits``: ``not_a_sphere_contrast``,
   ``overlap`` (axis ratio, darker than one sphere), ``not_a_sphere_shape``
   (edge RMS), ``not_a_sphere_size``, ``background_structure`` (the background
   also changes along its main structure, > 2x the frame's median: a corner
   of two steps; or the local model misfits > 3x the frame's median).
   6b. ``_corner_pass``: those shadows are measured again on a corner model
   (plane + two straight blurred ramps + their product, ``_fit_corner``) if it
   fits the annulus within ``max_corner_misfit`` x the noise there; its own
   uncertainty is propagated to the centre (doc/ct_detect.md).
7. Centre uncertainty, ``_centre_uncertainty``: ``f sigma_edge^2 (sum_i n_i
   n_i^T)^-1`` with ``n_i`` the edge normals, ``sigma_edge`` the fit RMS
   (degrees-of-freedom corrected) and ``f = max(1, n / (pi r))`` for the
   correlation of neighbouring rays, which sample shared pixels. Shadows whose
   edge crosses a background edge (band or step: the sub-pixel mixing of the
   two is not undone by any division) add, from their own data, the outer
   product of the centre's change when the points on that edge are left out
   of the fit and a cluster-robust term with each run of those points as one
   cluster.
8. Optional Deng / Clackdoyle correction from the ellipse centre to the
   projection of the sphere centre, given the nominal source-to-detector
   distance in pixels and the principal point (detector centre by default).
   For a cone of half angle beta around an axis at angle tau from the detector
   normal (distance D), the section has centre e = D sin t cos t / k, semi-axes
   a = D sin b cos b / k, b = D sin b / sqrt(k), with k = cos^2 t - sin^2 b,
   while the sphere centre projects to p = D tan t. The shift e - p is
   ~ e (b / D)^2: at most ~0.012 px on the default instrument (3 mm sphere,
   SRD 364 mm, detector corner), so the correction is small but free.

Coordinates follow OpenCV: pixel (c, r) is centred at (c, r); ``centre_px``
columns are (col, row).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import cv2
import numpy as np

__all__ = [
    "FrameError",
    "DetectionSettings",
    "RejectedCandidates",
    "FrameDetections",
    "detect_spheres",
    "to_transmission",
    "baseline_detect",
    "deng_correction",
    "REJECT_REASONS",
]

REJECT_REASONS = (
    "overlap",
    "edge_cut",
    "not_a_sphere_size",
    "not_a_sphere_shape",
    "not_a_sphere_contrast",
    "fit_failed",
    "background_structure",
)

FRAME_ERROR_REASONS = (
    "wrong_dtype",
    "wrong_encoding",
    "wrong_size",
    "non_finite",
    "all_dark",
    "saturated",
    "uniform",
    "bad_flat_field",
    "bad_stage_reading",
)


# sd [rad] below which a frame's summed structure tensor gives it a dominant background direction
# (snap_sigma); a holder's band or step in the beam gives a few hundredths of a degree
FRAME_DIRECTION_SD = np.deg2rad(0.5)


class FrameError(ValueError):
    """A frame that cannot be measured at all.

    Attributes
    ----------
    reason : str
        One of ``wrong_dtype``, ``wrong_encoding``, ``wrong_size``,
        ``non_finite``, ``all_dark``, ``saturated``, ``uniform``,
        ``bad_flat_field``, ``bad_stage_reading`` (raised by the frame pipeline
        for a stage reading no instrument can produce).
    """

    def __init__(self, reason: str, message: str):
        super().__init__(f"{reason}: {message}")
        self.reason = reason


@dataclass(frozen=True)
class DetectionSettings:
    """Tuning of :func:`detect_spheres` (defaults justified in the module docstring).

    Attributes
    ----------
    segment_depth : float
        Shadow pixels are ``T < b (1 - segment_depth)``, b the open-beam level.
    edge_level : float
        Iso-level of the sub-pixel edge as a fraction of the local shadow depth
        (0 = background, 1 = inner shadow level).
    n_rays : int
        Radial profiles per sphere.
    n_samples : int
        Samples per profile.
    ellipse_fitter : str
        ``"fitEllipse"``, ``"fitEllipseAMS"``, ``"fitEllipseDirect"`` or
        ``"geometric"`` (orthogonal-distance Gauss-Newton started from
        ``cv2.fitEllipse``).
    n_passes : int
        Edge-sampling passes; pass >= 2 re-centres the rays on the previous fit.
    min_contrast : float
        Minimum shadow depth ``1 - T_min / b`` of a sphere.
    max_axis_ratio : float
        Largest accepted major/minor semi-axis ratio. A sphere at the corner
        of the default detector (cone angle 15.5 deg) gives 1.04.
    max_fit_rms_px : float
        Largest accepted RMS distance of the edge points from the ellipse.
    min_edge_fraction : float
        Least fraction of rays that must give a valid edge point.
    size_tolerance : float
        Relative slack on ``diameter_px_range``.
    overlap_darkness : float or None
        A blob whose ``-log(T_min)`` exceeds this factor times the frame's
        median over blobs is two spheres in line (overlap). None disables.
    proximity_margin_px : float
        Two shadows whose threshold outlines are closer than this are both
        rejected as ``overlap`` (their blurred edges bias each other).
    proximity_pixel_outline : bool
        The gap to a neighbour whose blob is elongated (merged shadows) is measured to its
        own pixels, not to the circle of its area about its centroid, and blobs of merged
        shadows (up to 3.5 shadows' area) count as neighbours (False: the circle, and
        neighbours up to one shadow's size only: the former behaviour).
    border_margin_px : float
        Shadows whose measuring annulus comes closer than this to the image
        border are ``edge_cut``.
    background_window_px : int or None
        Length L of the segmentation closings' line segments; None:
        ``1.5 * max diameter * (1 + size_tolerance) + 7`` px (61 px without a range).
    n_orientations : int
        Directions of the segmentation closings (180 deg / n apart).
    snap_deg : float
        Local background orientations within this of a pixel axis are snapped to it.
    snap_sigma : float
        A window's orientation within this many standard deviations of its own noise of the
        frame's dominant orientation is replaced by the frame's (0 = off; see ``_blend_direction``).
    direction_blend : bool
        Instead of that hard switch, a smooth blend (the frame's wholly within ``snap_sigma`` / 2
        sd, the window's own beyond 1.5 ``snap_sigma``): no jump where the decision flips, but
        more windows move a little when the evidence changes (``_blend_direction``).
    edge_spread_px : float or None
        Sd of the detector's edge spread (blur and pixel aperture) for the blur correction of
        edge points on a background gradient (see :func:`_edge_spread2`); None estimates it per
        frame from the shadows' edges, 0 switches the correction off.
    frame_gradient_share : float
        Share of the blur correction applied for the frame-wide smooth part of the background's
        gradient (a quadratic in ln B fitted over the frame's shadows, :func:`_frame_field`); the
        local remainder (holder walls, plates: material in the beam) is always corrected in
        full. A gain applied after the blur (a detector gain map, a flat field the recording
        did not divide out) needs no correction, a fluence gradient before it (the anode heel)
        the full one, and one frame cannot tell them apart (doc/ct_detect.md, "A gain gradient
        applied after the blur"). The default, half, is off by at most half the correction
        either way; the rest is reported as one systematic pattern shared by every centre of
        the recording (``FrameDetections.systematic_px``), which the solvers propagate.
    exclusion_px : float
        Margin beyond the blob radius left out of the local background fit (blur, penumbra).
    background_span_px : float
        Least length of the background samples on each side of a shadow along the structure.
    max_background_misfit, max_cross_structure : float
        ``background_structure`` when the local model's misfit, or the gradient energy
        along the main structure, exceeds this factor times the frame's median.
    hot_pixel_sigma : float
        Hot/dead pixel threshold in noise sd beyond all 8 neighbours; 0 disables.
    fixed_orientation_deg : float or None
        For comparisons only: one orientation of the local model everywhere (0 = vertical lines).
    background_edge_gradient, background_edge_min_fraction : float
        A shadow more than ``min_fraction`` of whose edge points lie where the local
        background changes by more than ``gradient`` (relative) over 4 px across its
        structure (a band or step edge) is ``on_background_edge``: averaging the product of
        shadow and band over a pixel (and the detector blur) mixes them, which no division
        by a background undoes.
    background_edge_refit : bool
        For those shadows, add the outer product of the centre's change when the points on
        the background edge are left out of the fit (the data's own estimate of the effect).
    background_edge_clusters : float
        Weight of the cluster-robust term (each run of edge points on the background edge
        one cluster of the sandwich covariance); 0 disables.
    max_corner_misfit : float or None
        Largest rms misfit of the corner background model on the annulus, in units of the
        pixel noise there, for a ``background_structure`` shadow to be measured on it
        (``_corner_pass``); None disables the corner model.
    band_core : bool
        A blob piece refused as merged whose largest inscribed disk holds all of its depth (the
        rest shallower than half of it: a piece of a thin band, see ``_band_merged_core``) is
        screened again as that disk (False: refused, the former behaviour).
    grey_moment_screen : bool
        A small blob whose binary moment axis ratio exceeds ``max_axis_ratio`` by no more than
        the pixelation of its size explains is kept when the axis ratio of its depth-weighted
        moments is within the limit (``_merged_by_moments``; False: refused, the former behaviour).
    background_edge_sigma_px : float
        A fixed extra sd [px] across the structure for those shadows (0 = off; the former
        default 0.012 px was calibrated on the simulator's carbon tube).
    arc_pass, max_arc_sector_misfit, min_arc_sectors
        ``arc_pass``: a shadow the corner model refuses too is measured on the part of its edge
        whose surroundings a plane fits (``_arc_measure``): a plane of log T on a narrow annulus,
        30 deg sectors whose rms misfit exceeds ``max_arc_sector_misfit`` x the pixel noise
        dropped one at a time (worst first), at least ``min_arc_sectors`` of 12 kept, and the
        edge rays of the dropped sectors left out of the ellipse fit.
    model_check_misfit, model_check_degree
        An accepted shadow whose one-direction background misfits its samples more than
        ``model_check_misfit`` x the frame's median is measured again with a surface of degree
        ``model_check_degree`` in image coordinates as its background, and the two centres'
        difference enters its covariance (``_model_check``); the centre is not changed. None
        disables (the former behaviour).
    two_model_pass : bool
        A shadow refused by every background model (the one-direction model's structure screens,
        the corner model, the partial edge) is kept on its one-direction measurement when no dark
        pixel lies within ``proximity_margin_px`` outside it, with two terms in its covariance: the
        difference to its measurement on the ``model_check_degree`` surface, and the shift when the
        one-direction background is corrected by its misfit next to the shadow
        (``_two_model_pass``). False: refused as ``background_structure`` (the former behaviour).
    """

    segment_depth: float = 0.10
    edge_level: float = 0.5
    n_rays: int = 64
    n_samples: int = 40
    ellipse_fitter: str = "fitEllipse"
    n_passes: int = 2
    min_contrast: float = 0.15
    max_axis_ratio: float = 1.12
    max_fit_rms_px: float = 0.35
    min_edge_fraction: float = 0.8
    size_tolerance: float = 0.25
    overlap_darkness: float | None = 1.5
    proximity_margin_px: float = 4.0
    border_margin_px: float = 1.0
    background_window_px: int | None = None
    n_orientations: int = 6
    snap_deg: float = 1.5
    exclusion_px: float = 3.0
    background_span_px: float = 6.0
    max_background_misfit: float = 3.0
    max_cross_structure: float = 2.0
    hot_pixel_sigma: float = 6.0
    fixed_orientation_deg: float | None = None
    background_edge_gradient: float = 0.04
    background_edge_min_fraction: float = 0.05
    background_edge_sigma_px: float = 0.0
    background_edge_clusters: float = 1.0
    background_edge_refit: bool = True
    max_corner_misfit: float | None = 1.5
    edge_spread_px: float | None = None
    frame_gradient_share: float = 0.5
    snap_sigma: float = 4.0
    band_core: bool = True
    direction_blend: bool = False
    grey_moment_screen: bool = True
    arc_pass: bool = True
    proximity_pixel_outline: bool = True
    max_arc_sector_misfit: float = 1.5
    min_arc_sectors: int = 6
    model_check_misfit: float | None = 1.25
    model_check_degree: int = 4
    two_model_pass: bool = True

    def __post_init__(self):
        if self.ellipse_fitter not in ("fitEllipse", "fitEllipseAMS", "fitEllipseDirect", "geometric"):
            raise ValueError(f"unknown ellipse_fitter {self.ellipse_fitter!r}")
        if not 0.0 < self.segment_depth < 1.0:
            raise ValueError("segment_depth must be in (0, 1)")
        if not 0.0 < self.edge_level < 1.0:
            raise ValueError("edge_level must be in (0, 1)")
        if not 0.0 <= self.frame_gradient_share <= 1.0:
            raise ValueError(f"frame_gradient_share must be in [0, 1], got {self.frame_gradient_share}")
        if int(self.n_rays) < 8 or int(self.n_samples) < 8:
            raise ValueError("n_rays and n_samples must be >= 8")
        if self.model_check_misfit is not None and not (self.model_check_misfit > 0
                                                        and 1 <= int(self.model_check_degree) <= 6):
            raise ValueError("model_check_misfit must be > 0 (or None) and model_check_degree in 1..6")
        if not (self.background_edge_gradient > 0 and 0 <= self.background_edge_min_fraction < 1
                and self.background_edge_sigma_px >= 0):
            raise ValueError("background_edge_gradient must be > 0, background_edge_min_fraction in [0, 1) "
                             "and background_edge_sigma_px >= 0")
        if int(self.n_passes) < 1:
            raise ValueError("n_passes must be >= 1")
        if int(self.n_orientations) < 2 or not self.hot_pixel_sigma >= 0 or not self.exclusion_px >= 0:
            raise ValueError("n_orientations must be >= 2, hot_pixel_sigma and exclusion_px >= 0")
        if not (self.max_background_misfit > 0 and self.max_cross_structure > 0 and self.background_span_px > 0
                and self.background_edge_clusters >= 0):
            raise ValueError("max_background_misfit, max_cross_structure, background_span_px must be > 0, "
                             "background_edge_clusters >= 0")


@dataclass(frozen=True)
class RejectedCandidates:
    """Blobs that were found and refused.

    Attributes
    ----------
    centre_px : ndarray of shape (R, 2)
        Blob centroid (col, row) [px].
    area_px : ndarray of shape (R,)
        Thresholded area [px^2].
    reason : tuple of str, length R
        Reason code (see ``REJECT_REASONS``).
    detail : tuple of str, length R
        Human-readable explanation with the offending numbers.
    """

    centre_px: np.ndarray
    area_px: np.ndarray
    reason: tuple
    detail: tuple

    def __len__(self):
        return len(self.reason)

    def count(self, reason: str) -> int:
        """Number of rejections with this reason code."""
        return sum(1 for r in self.reason if r == reason)


@dataclass(frozen=True)
class FrameDetections:
    """Accepted sphere shadows of one frame (M of them) and the refused ones.

    Attributes
    ----------
    centre_px : ndarray of shape (M, 2)
        Ellipse centres (col, row) [px].
    centre_corrected_px : ndarray of shape (M, 2) or None
        Deng/Clackdoyle estimate of the projected sphere centre (only when
        ``sdd_px`` was given).
    centre_cov_px2 : ndarray of shape (M, 2, 2)
        Covariance of ``centre_px`` from the edge-point scatter [px^2].
    semi_axes_px : ndarray of shape (M, 2)
        Major and minor semi-axes [px].
    angle_rad : ndarray of shape (M,)
        Angle of the major axis from +col towards +row [rad].
    n_edge_points : ndarray of shape (M,)
    fit_rms_px : ndarray of shape (M,)
        RMS distance of the edge points from the fitted ellipse [px].
    min_transmission : ndarray of shape (M,)
        Darkest normalised transmission in the shadow.
    on_background_edge : ndarray of shape (M,), bool
        The shadow's edge crosses a strong background edge (a band or step of the
        holder); its covariance includes the data-driven background-edge terms.
    rejected : RejectedCandidates
    background : float
        Open-beam level of the normalised frame (1: every shadow is divided by its local background).
    success : bool
        False only if not a single sphere was accepted.
    message : str
    nfev : int
        Number of ellipse fits performed.
    n_hot_pixels : ndarray of shape (M,), int
        Hot/dead pixels repaired within 1.5 semi-major axes + 4 px of each centre.
    hot_pixels_px : ndarray of shape (K, 2)
        (col, row) of every repaired hot/dead pixel near a shadow.
    on_corner : ndarray of shape (M,), bool
        Measured with the corner background model (two straight steps; the one-direction
        model did not hold round this shadow).
    two_models : ndarray of shape (M,), bool
        Kept by the two-model pass: no single background model held round this shadow; it is
        measured on the one-direction model and its covariance holds the difference to a
        surface model's centre and the shift from correcting the background by its misfit next
        to the shadow (``DetectionSettings.two_model_pass``).
    level_shift_px : float
        How far inside the unblurred shadow's iso-level contour the blur moved the edge level
        crossing, for the frame's median ball [px] (0 when the edge spread is not measured). The
        fitted centre belongs to that contour, a cone section whose semi-axes are
        ``semi_axes_px + level_shift_px``: what the ellipse-centre model needs (ct_core.md).
    systematic_px : ndarray of shape (M, 2) or None
        One standard deviation of a systematic error shared by every centre of the recording
        [px]: the blur correction of the frame-wide background gradient is applied at
        ``DetectionSettings.frame_gradient_share`` of its ambiguous part ``c`` (the measured edge
        spread less the detector's own bilinear sampling, ``BILINEAR_VAR_PX2``, which is always
        corrected), and the right share
        lies anywhere in [0, 1] (0 for a gain after the blur, 1 for a fluence gradient), so the
        error is ``(h - share) c`` with h uniform: sd ``c sqrt(1/12 + (share - 1/2)^2)``. Its sign
        is the same in every frame, so it does not average out: the solvers propagate it as a
        fully correlated pattern (CentreObservations.systematic_px). Zero for shadows measured by
        the corner or partial-edge models (no blur correction there); None when not measured.
    """

    centre_px: np.ndarray
    centre_corrected_px: np.ndarray | None
    centre_cov_px2: np.ndarray
    semi_axes_px: np.ndarray
    angle_rad: np.ndarray
    n_edge_points: np.ndarray
    fit_rms_px: np.ndarray
    min_transmission: np.ndarray
    on_background_edge: np.ndarray
    rejected: RejectedCandidates
    background: float
    success: bool
    message: str
    nfev: int = 0
    n_hot_pixels: np.ndarray | None = None
    hot_pixels_px: np.ndarray | None = None
    on_corner: np.ndarray | None = None
    two_models: np.ndarray | None = None
    frame_noise: float = float("nan")
    frame_direction_rad: float = float("nan")
    level_shift_px: float = 0.0
    systematic_px: np.ndarray | None = None

    def __len__(self):
        return self.centre_px.shape[0]

    @property
    def estimate(self) -> np.ndarray:
        """Alias of ``centre_px`` (OptimizeResult-like naming)."""
        return self.centre_px

    @property
    def covariance(self) -> np.ndarray:
        """Alias of ``centre_cov_px2``."""
        return self.centre_cov_px2

    @property
    def residuals(self) -> np.ndarray:
        """Alias of ``fit_rms_px``."""
        return self.fit_rms_px

    @property
    def cost(self) -> float:
        """Half the sum of squared edge residuals over all accepted fits [px^2]."""
        return 0.5 * float(np.sum(self.fit_rms_px ** 2 * self.n_edge_points))

    @property
    def centre_std_px(self) -> np.ndarray:
        """Per-axis standard uncertainty of the centre, shape (M, 2) [px]."""
        return np.sqrt(np.diagonal(self.centre_cov_px2, axis1=1, axis2=2))


# --------------------------------------------------------------------------- frame checks

#: Encodings accepted (INTERFACES.md mono16 semantics for the integer ones: raw counts, the bit
#: depth, hence the saturation level, from the encoding).
ENCODING_FULL_SCALE = {"mono16": 65535, "16UC1": 65535, "mono8": 255, "8UC1": 255}
ENCODINGS = tuple(ENCODING_FULL_SCALE) + ("32FC1",)


def to_transmission(image, encoding: str = "mono16", flat_field_counts=None,
                    expected_shape=None, dark=None) -> np.ndarray:
    """Check one frame and convert it to transmission (the flat-field stage).

    Parameters
    ----------
    image : array_like of shape (rows, cols)
        Integer encodings (``mono16``, ``16UC1``, ``mono8``, ``8UC1``): raw counts
        of that bit depth. ``32FC1``: transmission I/I0 (any float dtype).
    encoding : str
        One of ``ENCODINGS``.
    flat_field_counts : float or ndarray of shape (rows, cols), optional
        Open-beam counts (integer encodings only): a scalar (ct_instrument.yaml's
        ``flat_field_counts``) or a flat-field image. None: the frame's own median.
        A scalar above the encoding's full scale (the file's mono16 value for a
        mono8 frame) does not describe these frames and is replaced by the
        frame's median (the detector normalises locally, so only the frame
        checks use the absolute level).
    expected_shape : tuple (rows, cols), optional
        From ct_instrument.yaml; a mismatch is a ``wrong_size`` FrameError.
    dark : float or ndarray of shape (rows, cols), optional
        Dark (offset) counts subtracted from the frame and the flat field:
        ``T = (I - dark) / (flat - dark)``.

    Returns
    -------
    ndarray of shape (rows, cols), float32

    Raises
    ------
    FrameError
        Wrong dtype/encoding/size, NaN/inf, all dark, saturated, uniform, bad flat/dark.
    """
    if encoding not in ENCODINGS:
        raise FrameError("wrong_encoding", f"encoding must be one of {ENCODINGS}, got {encoding!r}")
    img = np.asarray(image)
    if img.ndim != 2:
        raise FrameError("wrong_size", f"image must be 2-D (rows, cols), got shape {img.shape}")
    if expected_shape is not None:
        exp = tuple(int(v) for v in expected_shape)
        if img.shape != exp:
            raise FrameError("wrong_size", f"image is {img.shape[0]}x{img.shape[1]} (rows x cols), "
                                           f"ct_instrument.yaml says {exp[0]}x{exp[1]}")
    if img.shape[0] < 16 or img.shape[1] < 16:
        raise FrameError("wrong_size", f"image {img.shape} is too small")
    sub = img[::8, ::8]
    if encoding != "32FC1":
        full = ENCODING_FULL_SCALE[encoding]
        want = np.uint16 if full == 65535 else np.uint8
        if img.dtype != want:
            raise FrameError("wrong_dtype", f"{encoding} frames must be {np.dtype(want).name}, got {img.dtype}")
        if np.count_nonzero(sub == full) > 0.5 * sub.size:
            raise FrameError("saturated", f"more than half of the pixels are at {full} counts (full scale)")
        d = _dark_level(dark, img.shape)
        if flat_field_counts is None or (np.ndim(flat_field_counts) == 0 and float(flat_field_counts) > full):
            i0 = float(np.median(sub)) - (float(np.median(d[::8, ::8])) if np.ndim(d) else float(d))
            if i0 <= 0.0:
                raise FrameError("all_dark", "median count is at or below the dark level and no flat field was given")
            ff = np.float32(i0)
        else:
            ff = np.asarray(flat_field_counts, dtype=np.float32)
            if ff.ndim == 0:
                if not (np.isfinite(ff) and ff > 0):
                    raise FrameError("bad_flat_field", f"flat_field_counts must be > 0, got {ff}")
            elif ff.shape != img.shape or not np.all(np.isfinite(ff)):
                raise FrameError("bad_flat_field", "flat field must be a positive scalar or a finite "
                                                   f"array of shape {img.shape}, got shape {ff.shape}")
            ff = ff - d
            if np.any(ff <= 0):
                raise FrameError("bad_flat_field", "flat field minus dark must be > 0 everywhere")
        if np.ndim(d) or d:
            num = img.astype(np.float32)
            num -= d
            trans = num / ff if np.ndim(ff) else num * np.float32(1.0 / float(ff))
        elif np.ndim(ff):
            trans = cv2.divide(img.astype(np.float32), ff)
        else:
            trans = cv2.multiply(img, 1.0 / float(ff), dtype=cv2.CV_32F)
    else:
        if not np.issubdtype(img.dtype, np.floating):
            raise FrameError("wrong_dtype", f"32FC1 frames must be floating point, got {img.dtype}")
        trans = np.ascontiguousarray(img, dtype=np.float32)
        if not np.all(np.isfinite(trans)):
            n_bad = int(np.count_nonzero(~np.isfinite(trans)))
            raise FrameError("non_finite", f"{n_bad} pixels are NaN or inf")
    tsub = trans[::8, ::8]
    med = float(np.median(tsub))
    if med < 0.02:
        raise FrameError("all_dark", f"median transmission {med:.3g} < 0.02 (beam off or shutter closed)")
    if float(np.ptp(tsub)) == 0.0 and float(np.ptp(trans)) == 0.0:
        raise FrameError("uniform", f"every pixel has the same value {med:.6g} (no signal, no noise)")
    return trans


def _dark_level(dark, shape):
    """Dark counts as float32 scalar or array, checked."""
    if dark is None:
        return np.float32(0.0)
    d = np.asarray(dark, dtype=np.float32)
    if d.ndim == 0:
        if not (np.isfinite(d) and d >= 0):
            raise FrameError("bad_flat_field", f"dark level must be finite and >= 0, got {float(d)}")
        return np.float32(d)
    if d.shape != tuple(shape) or not np.all(np.isfinite(d)):
        raise FrameError("bad_flat_field", f"dark image must be finite with shape {tuple(shape)}, got {d.shape}")
    return d


# --------------------------------------------------------------------------- helpers

def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Exact bilinear interpolation (float64 weights), points assumed inside (clipped to the
    image's last interior cell: a point outside extrapolates from it)."""
    rows, cols = img.shape
    x0 = x.astype(np.intp)          # truncation: floor for x >= 0, and the clip below makes
    y0 = y.astype(np.intp)          # the two the same for x < 0
    np.clip(x0, 0, cols - 2, out=x0)
    np.clip(y0, 0, rows - 2, out=y0)
    fx = x - x0
    fy = y - y0
    flat = img.ravel()
    i00 = y0
    i00 *= cols
    i00 += x0
    v00 = flat[i00]
    i00 += 1
    v01 = flat[i00]
    i00 += cols
    v11 = flat[i00]
    i00 -= 1
    v10 = flat[i00]
    v01 = v01 - v00                 # the same operations as v00 + fx (v01 - v00), in place
    top = fx * v01
    top += v00
    v11 = v11 - v10
    bot = fx * v11
    bot += v10
    bot -= top
    bot *= fy
    bot += top
    return bot


def _fit_one(points: np.ndarray, fitter: str):
    """Ellipse (cx, cy, a, b, angle) from points (N, 2); a >= b, angle of a [rad]."""
    pts = points.astype(np.float32).reshape(-1, 1, 2)
    if fitter == "fitEllipseAMS":
        (cx, cy), (w, h), ang = cv2.fitEllipseAMS(pts)
    elif fitter == "fitEllipseDirect":
        (cx, cy), (w, h), ang = cv2.fitEllipseDirect(pts)
    else:
        (cx, cy), (w, h), ang = cv2.fitEllipse(pts)
    ang = np.deg2rad(ang)
    a, b = 0.5 * w, 0.5 * h
    if b > a:
        a, b = b, a
        ang += 0.5 * np.pi
    out = np.array([cx, cy, a, b, ang], dtype=np.float64)
    if fitter == "geometric" and np.all(np.isfinite(out)):
        out = _geometric_refine(points, out)
    return out


def _ellipse_residuals(points: np.ndarray, p: np.ndarray):
    """Approximate orthogonal distances of points (N, 2) from ellipse p and outward normals
    (:func:`_residuals_rows` for one ellipse)."""
    d, nx, ny = _residuals_rows(points[None, :, 0], points[None, :, 1], np.asarray(p, np.float64)[None, :])
    return d[0], nx[0], ny[0]


def _geometric_refine(points: np.ndarray, p0: np.ndarray, iters: int = 6) -> np.ndarray:
    """Gauss-Newton on Sampson (first-order orthogonal) distances, numerical Jacobian."""
    p = p0.copy()
    scale = np.array([1e-4, 1e-4, 1e-4, 1e-4, 1e-5])
    for _ in range(iters):
        r0, _, _ = _ellipse_residuals(points, p)
        jac = np.empty((points.shape[0], 5))
        for k in range(5):
            q = p.copy()
            q[k] += scale[k]
            jac[:, k] = (_ellipse_residuals(points, q)[0] - r0) / scale[k]
        step, *_ = np.linalg.lstsq(jac, -r0, rcond=None)
        p = p + step
        if np.max(np.abs(step[:4])) < 1e-7:
            break
    if p[3] > p[2]:
        p[2], p[3] = p[3], p[2]
        p[4] += 0.5 * np.pi
    return p


def deng_correction(centre_px, semi_axes_px, sdd_px: float, principal_point_px) -> np.ndarray:
    """Projected sphere centre from the silhouette ellipse (Deng et al. / Clackdoyle).

    Parameters
    ----------
    centre_px : array_like of shape (M, 2)
        Ellipse centres (col, row) [px].
    semi_axes_px : array_like of shape (M, 2)
        Major, minor semi-axes [px] (only the minor axis is used).
    sdd_px : float
        Source-to-detector distance in pixels (nominal SDD / pixel pitch).
    principal_point_px : array_like of shape (2,)
        Foot of the perpendicular from the source on the detector (col, row).

    Returns
    -------
    ndarray of shape (M, 2)
        Projected sphere centres (col, row) [px]. Exact for a detector
        perpendicular to the source-principal point line.
    """
    e = np.asarray(centre_px, dtype=np.float64).reshape(-1, 2)
    ax = np.asarray(semi_axes_px, dtype=np.float64).reshape(-1, 2)
    pp = np.asarray(principal_point_px, dtype=np.float64).reshape(2)
    d = float(sdd_px)
    if not (np.isfinite(d) and d > 0):
        raise ValueError(f"sdd_px must be positive, got {sdd_px}")
    vec = e - pp
    rho_e = np.hypot(vec[:, 0], vec[:, 1])
    b = ax[:, 1]
    tau = np.arctan(rho_e / d)
    sin_beta = np.sin(np.arctan(b / d))
    for _ in range(4):     # fixed point of e = D sin t cos t / k, b = D sin(beta) / sqrt(k)
        k = np.cos(tau) ** 2 - sin_beta ** 2
        sin_beta = np.clip(b * np.sqrt(k) / d, 0.0, 0.5)
        k = np.cos(tau) ** 2 - sin_beta ** 2
        tau = 0.5 * np.arcsin(np.clip(2.0 * rho_e * k / d, -1.0, 1.0))
    rho_p = d * np.tan(tau)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = np.where(rho_e[:, None] > 0, vec / rho_e[:, None], 0.0)
    return pp + unit * rho_p[:, None]


def _check_range(diameter_px_range):
    if diameter_px_range is None:
        return None
    r = np.asarray(diameter_px_range, dtype=np.float64)
    if r.shape != (2,) or not np.all(np.isfinite(r)) or r[0] <= 0 or r[1] < r[0]:
        raise ValueError(f"diameter_px_range must be (min, max) with 0 < min <= max, got {diameter_px_range}")
    return r


# --------------------------------------------------------------------------- main entry

def detect_spheres(image, *, encoding: str = "mono16", flat_field_counts=None, expected_shape=None,
                   diameter_px_range=None, settings: DetectionSettings | None = None,
                   sdd_px: float | None = None, principal_point_px=None, dark=None,
                   timing: dict | None = None) -> FrameDetections:
    """Find and measure every sphere shadow in one projection.

    Parameters
    ----------
    image : array_like of shape (rows, cols)
        Counts (``mono16``/``16UC1`` uint16, ``mono8``/``8UC1`` uint8) or ``32FC1`` transmission.
    encoding : str
        One of ``ENCODINGS``.
    flat_field_counts : float or ndarray of shape (rows, cols), optional
        Open-beam counts (scalar or flat-field image, ct_instrument.yaml).
    expected_shape : tuple (rows, cols), optional
        Detector size from ct_instrument.yaml.
    diameter_px_range : tuple (min, max), optional
        Expected shadow diameters [px] from the nominal geometry (see
        :func:`shadow_diameter_range_px`). Without it only shape and contrast
        screen the blobs.
    settings : DetectionSettings, optional
    sdd_px : float, optional
        Nominal source-to-detector distance in pixels; enables
        ``centre_corrected_px``.
    principal_point_px : array_like of shape (2,), optional
        Defaults to the detector centre ((cols-1)/2, (rows-1)/2).
    dark : float or ndarray of shape (rows, cols), optional
        Dark (offset) counts.
    timing : dict, optional
        Filled with the CPU seconds of each stage (added to what is there): ``flat_field``,
        ``background``, ``candidates``, ``local_background``, ``edges_fit``, ``rejection``,
        ``uncertainty`` (profiling; the live node and the benchmarks use it).

    Returns
    -------
    FrameDetections

    Raises
    ------
    FrameError
        For a frame that cannot be measured (see :func:`to_transmission`).
    ValueError
        For bad arguments other than the frame.
    """
    st = settings if settings is not None else DetectionSettings()
    drange = _check_range(diameter_px_range)
    clock = _StageClock(timing)
    trans = to_transmission(image, encoding, flat_field_counts, expected_shape, dark)     # 1 flat field
    noise = _noise_level(trans)
    clock.lap("flat_field")
    bg = _segmentation_background(trans, st, drange)                                      # 2 background
    clock.lap("background")
    rej = _Rejections()
    cand = _candidates(trans, bg, st, drange, rej)                                        # 3 candidates
    cand.noise = noise
    clock.lap("candidates")
    if len(cand.index) == 0:
        return _assemble([], rej, 0, sdd_px, principal_point_px, trans.shape, np.zeros((0, 2)),
                         "no sphere shadow accepted")
    model, hot = _local_backgrounds(trans, bg, cand, st)                                  # 4 local background,
    model.frame_field = _frame_field(model, cand, trans.shape)                            # hot pixels, frame's
    clock.lap("local_background")                                                         # smooth gradient
    meas = _measure_edges_and_fit(trans, model, cand, st)                                 # 5 edges, 6 fit
    clock.lap("edges_fit")
    deferred = []
    accepted = _screen_fits(meas, cand, model, st, drange, rej, deferred=deferred)        # 7 rejection
    if deferred:                                                                          # 7b corners
        last = [] if st.two_model_pass else None
        accepted = accepted + _corner_pass(trans, cand, model, meas, deferred, st, drange, rej, last)
        if last:                                                                          # 7c two models
            accepted = accepted + _two_model_pass(trans, cand, model, meas, last, st, rej)
        accepted = sorted(accepted)
    if st.model_check_misfit is not None:                                                 # 7d second model
        _model_check(trans, cand, model, meas, accepted, st)
    clock.lap("rejection")
    accepted = _centre_uncertainty(accepted, meas, model, st)                             # 8 uncertainty
    out = _assemble(accepted, rej, meas.n_fits, sdd_px, principal_point_px, trans.shape, hot, "",
                    meas=meas, cand=cand)
    out = replace(out, frame_noise=float(noise), frame_direction_rad=float(cand.frame_direction),
                  level_shift_px=float(meas.level_shift),
                  systematic_px=_frame_systematic(accepted, meas, model, st))
    clock.lap("uncertainty")
    return out


class _StageClock:
    """Adds the CPU time since the previous lap to ``timing[stage]`` (nothing without a dict)."""

    def __init__(self, timing):
        self.t = timing
        self.c = time.process_time() if timing is not None else 0.0

    def lap(self, stage):
        if self.t is not None:
            c = time.process_time()
            self.t[stage] = self.t.get(stage, 0.0) + c - self.c
            self.c = c


class _Rejections:
    """Refused candidates, in order."""

    def __init__(self):
        self.centre, self.area, self.reason, self.detail = [], [], [], []

    def add(self, centre, area, reason, detail):
        self.centre.append(np.asarray(centre, dtype=np.float64))
        self.area.append(float(area))
        self.reason.append(reason)
        self.detail.append(detail)


def shadow_diameter_range_px(diameters_m, centres_of_m, sdd_m: float, srd_m: float, pixel_pitch_m: float):
    """Nominal (min, max) shadow diameter [px] of a reference object at a stage position.

    The object's extent along the beam is taken from the reference object itself (the
    largest distance of a sphere centre from the centroid, plus the sphere radius), so
    nothing is assumed about its size; 0.6 / 1.5 of the extreme magnifications leave room
    for an object off the axis and for an SDD/SRD that differ from the nominal ones.
    """
    d = np.asarray(diameters_m, dtype=float)
    c = np.asarray(centres_of_m, dtype=float).reshape(-1, 3)
    extent = float(np.max(np.linalg.norm(c - c.mean(axis=0), axis=1))) + 0.5 * float(d.max())
    m_hi = sdd_m / max(srd_m - extent, 0.01)
    m_lo = sdd_m / (srd_m + extent)
    return 0.6 * float(d.min()) * m_lo / pixel_pitch_m, 1.5 * float(d.max()) * m_hi / pixel_pitch_m


# --------------------------------------------------------------------------- noise, hot pixels

def _noise_level(trans) -> float:
    """Robust sd of the pixel noise at the open-beam level, from neighbouring-pixel differences."""
    d = (trans[4:-4:16, 5:-4:8] - trans[4:-4:16, 4:-5:8]).ravel()
    s = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / np.sqrt(2.0)
    return max(s, 1e-6)


_RING3 = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], np.uint8)


def _repair_hot_pixels(trans, win, yy, xx, noise, st):
    """Hot (dead) pixels in the windows round the shadows: single pixels brighter (darker) than
    all 8 neighbours by more than ``hot_pixel_sigma`` noise sd, which a detector blurred over
    ~1 px cannot make. Replaced by the mean of their neighbours, in ``trans`` and ``win``
    (in place). Returns their (col, row) positions (K, 2)."""
    if not st.hot_pixel_sigma:
        return np.zeros((0, 2))
    k = np.float32(st.hot_pixel_sigma * noise)
    cen = win[:, 1:-1, 1:-1]
    # max / min of the 8 neighbours: a dilation / erosion with a 3x3 ring of the windows stacked
    # into one image (the rows where two windows meet are not used: every interior pixel's
    # neighbours lie in its own window)
    nc_, h_, w_ = win.shape
    flat = win.reshape(nc_ * h_, w_)
    mx = cv2.dilate(flat, _RING3, borderType=cv2.BORDER_REPLICATE).reshape(win.shape)[:, 1:-1, 1:-1]
    mn = cv2.erode(flat, _RING3, borderType=cv2.BORDER_REPLICATE).reshape(win.shape)[:, 1:-1, 1:-1]
    ci, ri, cj = np.nonzero((cen > mx + k) | (cen < mn - k))
    if ci.size == 0:
        return np.zeros((0, 2))
    r = yy[ci, ri + 1, 0]
    c = xx[ci, 0, cj + 1]
    rc = np.unique(np.column_stack([r, c]), axis=0)
    if rc.shape[0] > 0.01 * win.size:          # not isolated defects: leave the frame alone
        return np.zeros((0, 2))
    rows, cols = trans.shape
    r, c = rc[:, 0], rc[:, 1]
    acc = np.zeros(r.size, np.float64)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                acc += trans[np.clip(r + dr, 0, rows - 1), np.clip(c + dc, 0, cols - 1)]
    trans[r, c] = acc / 8.0
    win[...] = trans[yy, xx]
    return np.column_stack([c, r]).astype(np.float64)


# --------------------------------------------------------------------------- stage 3: segmentation background

def _segmentation_background(trans, st, drange):
    """Background for segmentation: the pointwise minimum of morphological closings of the
    frame with line segments of ``n_orientations`` directions, longer than a shadow.

    Every closing removes each sphere shadow (shorter than the line in every direction) and
    keeps straight steps of any orientation (plate edges, field stops: a monotone profile is
    its own closing); the minimum keeps dark bands (tube walls, a plate seen edge-on) that
    are long in at least one of the directions. Computed at half resolution (area average,
    which also lowers the noise) and interpolated back. (Quarter resolution for 2048^2 frames
    was tried: 1.4x faster overall, but it accepted a plate-corner shadow 0.12 px off that the
    half-resolution background refuses, and left specks along tube walls.) uint16 (rows, cols), T x 16384."""
    if st.background_window_px is not None:
        win = int(st.background_window_px)
    elif drange is not None:
        win = int(1.5 * drange[1] * (1.0 + st.size_tolerance)) + 7
    else:
        win = 61
    rows, cols = trans.shape
    half = cv2.resize(trans, (cols // 2, rows // 2), interpolation=cv2.INTER_AREA)
    half = (np.minimum(half, np.float32(3.99)) * np.float32(16384.0)).astype(np.uint16)   # 16-bit: 2x faster
    h = max(3, win // 2) | 1
    out = None
    for k in range(int(st.n_orientations)):
        th = np.pi * k / int(st.n_orientations)
        ker = _line_kernel(h, th)
        c = cv2.morphologyEx(half, cv2.MORPH_CLOSE, ker, borderType=cv2.BORDER_REPLICATE)
        out = c if out is None else np.minimum(out, c, out=out)
    bg = cv2.resize(out, (cols, rows), interpolation=cv2.INTER_LINEAR)
    return np.maximum(bg, 1, out=bg)           # uint16, transmission x 16384


_KERNELS = {}


def _line_kernel(length, theta):
    key = (int(length), round(float(theta), 6))
    ker = _KERNELS.get(key)
    if ker is None:
        c, s = np.cos(theta), np.sin(theta)
        if abs(s) < 1e-9:
            ker = np.ones((1, length), np.uint8)
        elif abs(c) < 1e-9:
            ker = np.ones((length, 1), np.uint8)
        else:
            h = length // 2
            w_ = int(np.ceil(abs(c) * h)), int(np.ceil(abs(s) * h))
            ker = np.zeros((2 * w_[1] + 1, 2 * w_[0] + 1), np.uint8)
            cv2.line(ker, (int(round(w_[0] - c * h)), int(round(w_[1] - s * h))),
                     (int(round(w_[0] + c * h)), int(round(w_[1] + s * h))), 1, 1)
        _KERNELS[key] = ker
    return ker


# --------------------------------------------------------------------------- stage 4: candidates

def _components(mask):
    """8-connected components of a sparse binary mask: labels (rows, cols) int32, stats (K, 5)
    int64 [x, y, w, h, area] and centroids (K, 2) float64 (col, row), component k labelled k + 1.

    The same figures as ``cv2.connectedComponentsWithStats``, whose statistics pass visits every
    pixel of the frame (~4x the labelling itself here); these come from the few mask pixels."""
    n_lab, labels = cv2.connectedComponents(mask, connectivity=8, ltype=cv2.CV_32S)
    k = n_lab - 1
    if k <= 0:
        return labels, np.zeros((0, 5), np.int64), np.zeros((0, 2))
    pts = cv2.findNonZero(mask).reshape(-1, 2)            # (col, row), row-major order
    xs = pts[:, 0].astype(np.int64)
    ys = pts[:, 1].astype(np.int64)
    lab = labels[ys, xs].astype(np.int64) - 1
    area = np.bincount(lab, minlength=k)
    cents = np.column_stack([np.bincount(lab, xs.astype(np.float64), k),
                             np.bincount(lab, ys.astype(np.float64), k)]) / area[:, None]
    x0 = np.full(k, np.iinfo(np.int64).max)
    y0 = np.full(k, np.iinfo(np.int64).max)
    x1 = np.full(k, -1)
    y1 = np.full(k, -1)
    np.minimum.at(x0, lab, xs)
    np.minimum.at(y0, lab, ys)
    np.maximum.at(x1, lab, xs)
    np.maximum.at(y1, lab, ys)
    stats = np.column_stack([x0, y0, x1 - x0 + 1, y1 - y0 + 1, area]).astype(np.int64)
    return labels, stats, cents


@dataclass
class _Candidates:
    index: np.ndarray       # (C,) component index
    centre: np.ndarray      # (C, 2) centroid (col, row)
    radius: np.ndarray      # (C,) equivalent radius of the thresholded blob
    area: np.ndarray        # (C,)
    shadows: np.ndarray     # (rows, cols) uint8: 1 on compact shadows (grown by 2 px)
    noise: float = 0.0      # pixel noise sd at the open-beam level
    frame_direction: float = float("nan")   # dominant background direction (snap_sigma) [rad]


def _candidates(trans, bg, st, drange, rej):
    """Threshold frame / background, label components, screen them (size, border, shape,
    proximity). A blob refused as merged (too large, elongated, not elliptical: a sphere on a
    dark band the closings did not keep, or two shadows joined by their blurred rims) is first
    split by a binary opening with a disk of 0.8 x the smallest shadow; its pieces are screened
    like blobs (and refused if still merged)."""
    rows, cols = trans.shape
    ratio = cv2.divide(trans, bg, scale=16384.0, dtype=cv2.CV_32F)
    thr = np.float32(1.0 - st.segment_depth)
    mask = (ratio < thr).view(np.uint8)
    labels, stats, cents = _components(mask)
    if drange is not None:
        dmin = drange[0] * (1.0 - st.size_tolerance)
        dmax = drange[1] * (1.0 + st.size_tolerance)
    else:
        dmin, dmax = 4.0, np.inf
    single_area_max = np.pi * dmax ** 2 / 4.0
    area = stats[:, cv2.CC_STAT_AREA].astype(np.float64)
    d_eq = 2.0 * np.sqrt(area / np.pi)
    kd = max(3, int(0.8 * dmin)) | 1
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (kd, kd))

    # work list of blobs: (stats [x, y, w, h, area], centroid, binary blob in its box or None, piece?)
    # blobs where the beam hardly reaches (outside a field stop, < 25 % of the typical open-beam
    # level) are noise, not shadows: left out without a record
    exposed = bg[np.clip(np.rint(cents[:, 1]).astype(np.intp), 0, rows - 1),
                 np.clip(np.rint(cents[:, 0]).astype(np.intp), 0, cols - 1)] > 0.25 * float(np.median(bg[::16, ::16]))
    # (bg: uint16, transmission x 16384)
    work = [(stats[i], cents[i], None, False, i) for i in range(stats.shape[0]) if exposed[i]]
    pieces = []                  # (stats, centroid, blob) of every piece made
    split_parent = set()
    cand = []                    # (work index, centre, radius, area)
    k = 0
    while k < len(work):
        s_, (cx, cy), blob, piece, lab = work[k]
        k += 1
        x0, y0, w, h = (int(v) for v in s_[:4])
        a = float(s_[4])
        de = 2.0 * np.sqrt(a / np.pi)
        if blob is None:
            blob = labels[y0:y0 + h, x0:x0 + w] == lab + 1
        if de < dmin:
            if not piece or piece == "core":
                rej.add((cx, cy), a, "not_a_sphere_size", f"diameter {de:.1f} px < {dmin:.1f} px")
            continue
        why = None
        if de > dmax:
            why = ("overlap", f"blob area {a:.0f} px^2 exceeds one sphere ({single_area_max:.0f} px^2): "
                              "merged shadows") if a <= 3.5 * single_area_max else \
                ("not_a_sphere_size", f"blob area {a:.0f} px^2 is larger than three spheres")
        else:
            r0 = 0.5 * de
            reach = r0 + max(0.5 * r0, 4.0) + st.border_margin_px + 1.0
            touches = x0 <= 0 or y0 <= 0 or x0 + w >= cols or y0 + h >= rows
            if touches or cx - reach < 0 or cy - reach < 0 or cx + reach > cols - 1 or cy + reach > rows - 1:
                rej.add((cx, cy), a, "edge_cut", "shadow touches the image border" if touches
                        else "measuring annulus leaves the image")
                continue
            aspect = max(w, h) / max(1, min(w, h))
            if aspect > 1.6 * st.max_axis_ratio:
                why = ("overlap", f"blob bounding box aspect {aspect:.2f}: merged shadows")
            else:
                m_ratio = _moment_axis_ratio(cv2.moments(blob.view(np.uint8), binaryImage=True))
                if m_ratio > st.max_axis_ratio:
                    why = _merged_by_moments(m_ratio, de, blob, ratio[y0:y0 + h, x0:x0 + w], st)
        if why is None:
            cand.append((k - 1, (cx, cy), 0.5 * de, a))
            continue
        if piece is True and why[0] == "overlap" and st.band_core:
            core = _band_merged_core(blob, ratio[y0:y0 + h, x0:x0 + w], x0, y0, st.exclusion_px)
            if core is not None:         # a shadow with a piece of a band: screen its round core instead
                # (the proximity rule sees the core's centre and size; the shadow mask keeps the
                # whole piece, as before, so that the neighbours' backgrounds do not change)
                s0 = s_.copy()
                s0[4] = core[0][4]
                pieces[next(i for i, p in enumerate(pieces) if p is work[k - 1])] = (s0, core[1], blob, True, -1)
                work.append(core)
                continue
        if not piece and np.isfinite(dmax):
            op = cv2.morphologyEx(blob.view(np.uint8), cv2.MORPH_OPEN, disk)
            n2, lab2, st2, ce2 = cv2.connectedComponentsWithStats(op, connectivity=8)
            new = []
            for j in range(1, n2):
                if st2[j, cv2.CC_STAT_AREA] < 0.5 * np.pi * dmin ** 2 / 4.0:
                    continue
                x2, y2, w2, h2, a2 = (int(v) for v in st2[j])
                new.append((np.array([x0 + x2, y0 + y2, w2, h2, a2]), np.array([ce2[j, 0] + x0, ce2[j, 1] + y0]),
                            lab2[y2:y2 + h2, x2:x2 + w2] == j, True, -1))
            # a real split, or a single piece that lost a band: screen the pieces instead
            if len(new) >= 2 or (len(new) == 1 and new[0][0][4] < a):
                split_parent.add(lab)
                work.extend(new)
                pieces.extend(new)
                continue
        rej.add((cx, cy), a, *why)
    # proximity: penumbrae of neighbours interact; compared with every compact blob of
    # noticeable size (accepted or not, pieces instead of their parents) by the gap between the
    # threshold outlines: centre distance minus both equivalent radii for a round neighbour; for
    # an elongated one (two shadows merged into one blob, a piece with a bump: moment axis ratio
    # above max_axis_ratio and above what pixelation gives a round blob of its size) its own
    # pixels, since the equivalent circle about its centroid reaches past it across its long
    # axis (a sphere 6-9 px clear of a merged pair was refused at a circle gap of 3.4-3.9 px:
    # ct_detect.md, "Proximity to merged blobs")
    comp = [i for i in range(stats.shape[0]) if i not in split_parent]
    allc = [cents[i] for i in comp] + [p[1] for p in pieces]
    alla = [area[i] for i in comp] + [float(p[0][4]) for p in pieces]
    allc = np.array(allc, dtype=np.float64).reshape(-1, 2)
    alld = 2.0 * np.sqrt(np.array(alla, dtype=np.float64) / np.pi)
    # the neighbours: every compact shadow, as the local backgrounds mask them (up to 3.5 shadows'
    # area: merged ones too; the former rule counted blobs up to one shadow's size only, so a
    # sphere next to a merged pair was not tested at all when the expected sizes are narrow)
    if st.proximity_pixel_outline:
        others = np.nonzero((alld >= max(3.0, 0.5 * dmin)) & (np.pi * alld ** 2 / 4.0 <= 3.5 * single_area_max))[0]
    else:
        others = np.nonzero((alld >= max(3.0, 0.5 * dmin)) & (alld <= dmax))[0]
    oc, od = allc[others], alld[others]
    shape_of = {}

    def pixels(j):              # (pixel coordinates (N, 2) as col, row; elongated?) of entry j
        if j not in shape_of:
            if j < len(comp):
                i = comp[j]
                x0, y0, w, h = (int(v) for v in stats[i, :4])
                blob = labels[y0:y0 + h, x0:x0 + w] == i + 1
            else:
                s_, _, blob = pieces[j - len(comp)][:3]
                x0, y0 = int(s_[0]), int(s_[1])
            d_eq = 2.0 * np.sqrt(np.count_nonzero(blob) / np.pi)
            elong = (_moment_axis_ratio(cv2.moments(blob.view(np.uint8), binaryImage=True))
                     > max(st.max_axis_ratio, _pixelation_axis_bound(d_eq)))
            yx = np.argwhere(blob) if elong else None
            shape_of[j] = (None if yx is None else yx[:, ::-1] + [x0, y0], elong)
        return shape_of[j]

    keep = []
    for (wi, (cx, cy), r0, a) in cand:
        dist = np.hypot(oc[:, 0] - cx, oc[:, 1] - cy)
        gap = dist - r0 - 0.5 * od
        gap[dist < 1e-9] = np.inf       # itself
        for k in np.nonzero(gap < st.proximity_margin_px)[0] if st.proximity_pixel_outline else ():
            pix, elong = pixels(int(others[k]))
            if elong:                   # its nearest pixel centre, whose outline is 0.5 px further
                gap[k] = float(np.min(np.hypot(pix[:, 0] - cx, pix[:, 1] - cy))) - r0 - 0.5
        g = float(np.min(gap)) if gap.size else np.inf
        if g < st.proximity_margin_px:
            rej.add((cx, cy), a, "overlap", f"gap {max(g, 0.0):.1f} px to a neighbouring shadow "
                                            f"< {st.proximity_margin_px:.1f} px")
        else:
            keep.append((cx, cy, r0, a))
    # pixels of every compact shadow (not of bands or steps), grown by 2 px for the blurred rims:
    # the local background models leave them out
    shadows = mask.copy()
    not_shadow = set(np.nonzero(~((d_eq >= 0.5 * dmin) & (area <= 3.5 * single_area_max)))[0].tolist())
    for i in not_shadow | split_parent:
        x0, y0, w, h = (int(v) for v in stats[i, :4])
        box = shadows[y0:y0 + h, x0:x0 + w]
        box[labels[y0:y0 + h, x0:x0 + w] == i + 1] = 0
    for s_, _, blob, _, _ in pieces:
        x0, y0, w, h = (int(v) for v in s_[:4])
        shadows[y0:y0 + h, x0:x0 + w] |= blob.view(np.uint8)
    shadows = cv2.dilate(shadows, np.ones((5, 5), np.uint8))
    kp = np.array(keep, dtype=np.float64).reshape(-1, 4)
    return _Candidates(index=np.arange(kp.shape[0]), centre=kp[:, :2].copy(), radius=kp[:, 2].copy(),
                       area=kp[:, 3].copy(), shadows=shadows)


# A round blob of equivalent diameter D [px], thresholded on the pixel grid, has a binary moment axis
# ratio up to 1 + c D^-1.5 from pixelation alone; c measured over sub-pixel phases, blur sd 0.3-1.1 px
# and D = 6-16 px (tests/benchmarks/measure_ct_small_blob_moments.py, both renderers' physics): <= 3.3
# noise-free, <= 4.8 with 3 % noise. Up to this c a blob's excess is left to the depth-weighted test.
_PIXELATION_AXIS_COEF = 6.0


def _pixelation_axis_bound(d_eq):
    """Largest binary moment axis ratio pixelation gives a round blob of equivalent diameter ``d_eq`` [px]."""
    return 1.0 + _PIXELATION_AXIS_COEF * d_eq ** -1.5


def _moment_axis_ratio(mom) -> float:
    """sqrt(major / minor) eigenvalue of the second central moments (a ``cv2.moments`` dict)."""
    if mom["m00"] <= 0:
        return np.inf
    mu20, mu02, mu11 = mom["mu20"] / mom["m00"], mom["mu02"] / mom["m00"], mom["mu11"] / mom["m00"]
    tr_, dd_ = mu20 + mu02, np.sqrt(max((mu20 - mu02) ** 2 + 4 * mu11 ** 2, 0.0))
    l1, l2 = 0.5 * (tr_ + dd_), 0.5 * (tr_ - dd_)
    return float(np.sqrt(l1 / l2)) if l2 > 0 else np.inf


def _merged_by_moments(m_ratio, de, blob, ratio, st):
    """The refusal of a blob whose binary moment axis ratio exceeds ``max_axis_ratio``, or None.

    The binary moments of a small blob scatter by pixelation: which rim pixels pass the threshold
    depends on the sub-pixel phase, the blur and the noise (noise-free up to 1.16 at 6 px, 1.12 at
    7 px, 1.09 at 10 px). The moments of the depth 1 - ratio over the blob hardly do (a rim pixel
    weighs its small depth; <= 1.06 noise-free, <= 1.13 at 6 px with 3 % noise), so with
    ``grey_moment_screen`` a blob within the pixelation bound ``_PIXELATION_AXIS_COEF`` is kept
    when its depth-weighted axis ratio is within the limit. Two merged shadows give >= 1.4
    (binary) and >= 1.5 (depth) even overlapping by 2 px."""
    why = ("overlap", f"blob moment axis ratio {m_ratio:.2f} > {st.max_axis_ratio}: merged shadows")
    if not st.grey_moment_screen or m_ratio > _pixelation_axis_bound(de):
        return why
    g_ratio = _moment_axis_ratio(cv2.moments(np.where(blob, np.maximum(1.0 - ratio, 0.0), 0.0).astype(np.float32)))
    if g_ratio <= st.max_axis_ratio:
        return None
    return ("overlap", f"blob moment axis ratio {m_ratio:.2f}, depth-weighted {g_ratio:.2f} > "
                       f"{st.max_axis_ratio}: merged shadows")


def _band_merged_core(blob, ratio, x0, y0, margin):
    """The round core of a blob piece refused as merged: the largest disk inside it, if all of the
    piece beyond that disk + ``margin`` (the shadow's blurred rim, ``exclusion_px``) is shallower
    than half the disk's depth.

    A sphere shadow crossed by a thin dark band that the segmentation closings did not keep
    (a tube wall tilted between their directions) stays joined, after the opening, to a bump of
    the band; two shadows joined by their rims leave a second deep region beyond the disk.
    Returns a work item like the pieces' (stats, centroid, disk mask, "core", -1), or None."""
    pad = np.pad(blob.view(np.uint8), 1)
    dist = cv2.distanceTransform(pad, cv2.DIST_L2, 5)[1:-1, 1:-1]
    r_in = float(dist.max())
    if r_in < 2.0:
        return None
    iy, ix = np.unravel_index(int(np.argmax(dist)), dist.shape)
    yy, xx = np.mgrid[0:blob.shape[0], 0:blob.shape[1]]
    d2 = (xx - ix) ** 2 + (yy - iy) ** 2
    disk = blob & (d2 <= r_in * r_in)
    rest = blob & (d2 > (r_in + margin) ** 2)
    depth_core = 1.0 - float(ratio[disk].min())
    if np.any(rest) and 1.0 - float(ratio[rest].min()) >= 0.5 * depth_core:
        return None
    ys, xs = np.nonzero(disk)
    ya, yb, xa, xb = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    return (np.array([x0 + xa, y0 + ya, xb - xa, yb - ya, ys.size]),
            np.array([x0 + xs.mean(), y0 + ys.mean()]), disk[ya:yb, xa:xb], "core", -1)


# --------------------------------------------------------------------------- stage 4: local background

@dataclass
class _LocalBackground:
    """Per candidate: background B(u, v) = a(u) + b(u) v on a grid turned so that u runs across
    the dominant background structure (steps, bands) and v along it."""
    origin: np.ndarray      # (C, 2) grid origin (integer pixel)
    eu: np.ndarray          # (C, 2) unit vector of u in the image
    ev: np.ndarray          # (C, 2)
    umin: int               # first u of the grid (u = umin + index)
    a: np.ndarray           # (C, U)
    b: np.ndarray           # (C, U)
    edge_gradient: np.ndarray  # (C, U) relative change of a over +-2 px of u
    structure: np.ndarray   # (C,) rms misfit of the model on the background samples / noise
    coherence: np.ndarray   # (C,)
    minor: np.ndarray       # (C,) gradient energy along the structure / the noise's
    corner: tuple | None = None  # per candidate a _CornerModel whose grad marks background edges
    direction_evidence: np.ndarray | None = None  # (C,) |theta - frame's| / sd (see _blend_direction)
    ray_keep: np.ndarray | None = None  # (C, 12) rays of these 30 deg sectors used (arc pass), None: all
    frame_field: np.ndarray | None = None  # (8,) _frame_field: the frame-wide quadratic in ln B, or None


def _subset(cand, k):
    """Candidates ``k`` (index array) of ``cand``, with its shadow mask and noise (one-off measurements)."""
    return _Candidates(index=cand.index[k], centre=cand.centre[k], radius=cand.radius[k], area=cand.area[k],
                       shadows=cand.shadows, noise=cand.noise)


def _flat_background(centres, umin=-1, structure=0.0, ray_keep=None):
    """A background of 1 everywhere for shadows at ``centres`` (C, 2): for windows already divided by
    another background model (corner, surface, plane, ring-corrected lines)."""
    c = len(centres)
    n = 2 * (-umin) + 1
    return _LocalBackground(origin=np.rint(centres), eu=np.tile([1.0, 0.0], (c, 1)), ev=np.tile([0.0, 1.0], (c, 1)),
                            umin=umin, a=np.ones((c, n)), b=np.zeros((c, n)), edge_gradient=np.zeros((c, n)),
                            structure=np.full(c, structure), coherence=np.zeros(c), minor=np.zeros(c),
                            ray_keep=ray_keep)


def _local_backgrounds(trans, bg, cand, st):
    """Background of each shadow from its surroundings, with no assumption about the holder.

    The direction of the strongest structure around the shadow comes from the structure
    tensor of the frame's gradients outside every shadow; orientations within ``snap_deg`` of
    the pixel axes are snapped to them (exact pixel sampling). On a grid turned to that
    direction (u across, v along the structure) each line of constant u is fitted by a
    straight line in v through the samples outside the shadow (radius + ``exclusion_px``,
    other shadows masked, samples 4 noise sd below the first fit dropped in a second round),
    so a step or band of any orientation through the shadow, and any smooth gradient, are
    interpolated across it. Also repairs hot pixels in the windows (see
    :func:`_repair_hot_pixels`), in place."""
    c = cand.centre
    nc = c.shape[0]
    r = cand.radius
    rows, cols = trans.shape
    w_out = np.maximum(0.5 * r, 4.0)
    rex = r + st.exclusion_px
    U = int(np.ceil(np.max(r + w_out))) + 3
    V = int(np.ceil(np.max(rex + np.maximum(0.5 * r, st.background_span_px))))
    R = max(U, V) + 1
    origin = np.rint(c)
    oi = origin.astype(np.intp)
    off = np.arange(-R, R + 1)
    yy = np.clip(oi[:, 1, None, None] + off[None, :, None], 0, rows - 1)
    xx = np.clip(oi[:, 0, None, None] + off[None, None, :], 0, cols - 1)
    win = trans[yy, xx]                                            # (C, 2R+1, 2R+1) float32
    hot = _repair_hot_pixels(trans, win, yy, xx, cand.noise, st)
    shadow = cand.shadows[yy, xx]
    # orientation: structure tensor of the window's gradients off the shadows
    keep = (shadow[:, 1:-1, 1:-1] == 0)
    gx_ = (win[:, 1:-1, 2:] - win[:, 1:-1, :-2]) * keep
    gy_ = (win[:, 2:, 1:-1] - win[:, :-2, 1:-1]) * keep
    jxx = np.sum(gx_ * gx_, axis=(1, 2), dtype=np.float64)
    jyy = np.sum(gy_ * gy_, axis=(1, 2), dtype=np.float64)
    jxy = np.sum(gx_ * gy_, axis=(1, 2), dtype=np.float64)
    theta = 0.5 * np.arctan2(2 * jxy, jxx - jyy)            # direction of the strongest gradient
    root = np.sqrt((jxx - jyy) ** 2 + 4 * jxy ** 2)
    coh = root / np.maximum(jxx + jyy, 1e-30)
    # gradient energy along the structure (minor eigenvalue) over what the noise gives
    # (a central difference has variance 2 sigma^2 at the open-beam level)
    n_keep = np.maximum(np.count_nonzero(keep, axis=(1, 2)), 1)
    minor = 0.5 * (jxx + jyy - root) / (2.0 * cand.noise ** 2 * n_keep)
    snap = np.deg2rad(st.snap_deg)
    evidence = np.full(nc, np.inf)
    if st.snap_sigma and nc > 1:
        # a window whose direction is within snap_sigma sd of its own noise of the frame's
        # dominant direction (the summed tensor of every window) takes the frame's: weak
        # structure in a small window gives a noisy direction, and a grid turned by noise samples
        # a sharp band between pixels (bilinear) where the profiles see it otherwise, which
        # biases the centre. The noise of the off-diagonal term across the structure,
        # 2 s^2 J + 4 s^4 n (s^2 a pixel's variance, a central difference 2 s^2), over the
        # anisotropy gives the sd of 2 theta.
        s2n = np.asarray(cand.noise, np.float64) ** 2 * np.ones(nc)
        sd_theta = 0.5 * np.sqrt(2.0 * s2n * (jxx + jyy) + 4.0 * s2n ** 2 * n_keep) / np.maximum(root, 1e-30)
        # the frame's direction counts only when the frame has one: its own sd (the same noise
        # model over the summed tensor) below FRAME_DIRECTION_SD. A frame without background
        # structure (no holder in the beam) has a direction drawn by the noise, and snapping every
        # window to it moved centres by up to 1 sd from one estimate of it to the next (a crop of
        # the frame against the whole frame, tests/ct_imaging/test_track.py no_tube).
        jf = np.array([jxx.sum(), jyy.sum(), jxy.sum()])
        root_f = np.sqrt((jf[0] - jf[1]) ** 2 + 4 * jf[2] ** 2)
        sd_f = 0.5 * np.sqrt(2.0 * s2n[0] * (jf[0] + jf[1]) + 4.0 * s2n[0] ** 2 * n_keep.sum()) / max(root_f, 1e-30)
        tf = 0.5 * np.arctan2(2 * jf[2], jf[0] - jf[1])
        theta, evidence = _blend_direction(theta, sd_theta, tf, sd_f, st.snap_sigma, st.direction_blend)
        cand.frame_direction = float(tf) if sd_f < FRAME_DIRECTION_SD else float("nan")
    q = np.round(theta / (0.5 * np.pi)) * (0.5 * np.pi)
    snapped = np.abs(theta - q) < snap
    theta = np.where(snapped, q, theta)
    if st.fixed_orientation_deg is not None:       # for comparisons only: one direction everywhere
        theta = np.full(nc, np.deg2rad(st.fixed_orientation_deg))
        snapped = np.abs(np.sin(2 * theta)) < 1e-9
    eu = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    eu = np.where(np.abs(eu) < 1e-9, 0.0, np.where(snapped[:, None], np.rint(eu), eu))
    ev = np.stack([-eu[:, 1], eu[:, 0]], axis=1)
    us = np.arange(-U, U + 1, dtype=np.float32)
    vs = np.arange(-V, V + 1, dtype=np.float32)
    e32 = eu.astype(np.float32)
    v32 = ev.astype(np.float32)
    dxg = e32[:, 0, None, None] * us[None, :, None] + v32[:, 0, None, None] * vs[None, None, :]
    dyg = e32[:, 1, None, None] * us[None, :, None] + v32[:, 1, None, None] * vs[None, None, :]
    o32 = origin.astype(np.float32)
    px = o32[:, 0, None, None] + dxg
    py = o32[:, 1, None, None] + dyg
    inside = (px >= 0) & (px <= cols - 1) & (py >= 0) & (py <= rows - 1)
    s = np.empty(px.shape, np.float32)
    sh = np.empty(px.shape, np.uint8)
    if np.any(snapped):               # exact pixels, gathered from the windows
        k = np.nonzero(snapped)[0]
        ix = (R + np.rint(dxg[k])).astype(np.intp)
        iy = (R + np.rint(dyg[k])).astype(np.intp)
        kk = np.arange(k.size)[:, None, None]
        s[k] = win[k[kk], iy, ix]
        sh[k] = shadow[k[kk], iy, ix]
    if not np.all(snapped):
        k = np.nonzero(~snapped)[0]
        s[k] = _bilinear(trans, np.clip(px[k], 0, cols - 1), np.clip(py[k], 0, rows - 1))
        sh[k] = cand.shadows[np.clip(np.rint(py[k]).astype(np.intp), 0, rows - 1),
                             np.clip(np.rint(px[k]).astype(np.intp), 0, cols - 1)]
    dx = dxg + (o32[:, 0] - c[:, 0]).astype(np.float32)[:, None, None]
    dy = dyg + (o32[:, 1] - c[:, 1]).astype(np.float32)[:, None, None]
    noise = cand.noise
    wgt = (inside & (dx * dx + dy * dy > (rex * rex).astype(np.float32)[:, None, None]) & (sh == 0)).astype(np.float32)
    vv = vs[None, None, :]
    a, b = _line_fit(s, wgt, vv)
    fit = a[:, :, None] + b[:, :, None] * vv
    wgt *= s > fit * np.float32(1.0 - 4.0 * noise)
    a, b = _line_fit(s, wgt, vv)
    res = (s - (a[:, :, None] + b[:, :, None] * vv)) * wgt
    n_used = np.maximum(np.sum(wgt, axis=(1, 2)), 1.0)
    structure = (np.sqrt(np.sum(res * res, axis=(1, 2), dtype=np.float64) / n_used)
                 / (noise * np.maximum(np.median(a, axis=1), 1e-6)))
    ap = np.pad(a, ((0, 0), (2, 2)), mode="edge")
    grad = np.abs(ap[:, 4:] - ap[:, :-4]) / np.maximum(a, 1e-6)
    return _LocalBackground(origin=origin, eu=eu, ev=ev, umin=-U, a=a.astype(np.float64), b=b.astype(np.float64),
                            edge_gradient=grad, structure=structure, coherence=coh, minor=minor,
                            direction_evidence=evidence), hot


def _blend_direction(theta, sd_theta, tf, sd_f, k, smooth=False):
    """Window directions ``theta`` (sd ``sd_theta``) drawn towards the frame's ``tf`` (sd ``sd_f``).

    t = |theta - tf| / sd_theta (mod pi) is the evidence that a window's structure differs from
    the frame's. Default (hard): a window with t < k takes the frame's direction, if the frame has
    one (sd_f < FRAME_DIRECTION_SD), else it keeps its own. ``smooth``: the window keeps the
    weight w(t) of its own difference, 0 up to t = k / 2, 1 from 3 k / 2 on, a smooth step
    (3 x^2 - 2 x^3, x = (t - k / 2) / k) between, times ``g = 1 / (1 + (sd_f /
    FRAME_DIRECTION_SD)^4)`` for how far the frame has a direction: ``theta' = tf + (1 - (1 - w)
    g) (theta - tf)``, a continuous function of the data, |d(theta' - tf)/dt| <= 2.3 sd_theta.
    The hard rule moves a centre by ~0.4-0.6 sd where its decision flips; the smooth one moves
    every window with k / 2 < t < 3 k / 2 a little whenever t changes, which for weakly structured
    windows (sd_theta 10-20 deg) turns their grid by degrees (doc/ct_detect.md: measured worse
    between a crop and its whole frame). Returns (theta', t)."""
    d = (theta - tf + 0.5 * np.pi) % np.pi - 0.5 * np.pi
    t = np.abs(d) / np.maximum(sd_theta, 1e-30)
    if not smooth:
        return np.where((t < k) & (sd_f < FRAME_DIRECTION_SD), tf, theta), t
    x = np.clip((t - 0.5 * k) / k, 0.0, 1.0)
    w = x * x * (3.0 - 2.0 * x)
    g = 1.0 / (1.0 + (sd_f / FRAME_DIRECTION_SD) ** 4)
    return tf + (1.0 - (1.0 - w) * g) * d, t


def _line_fit(s, w, v):
    """Weighted straight line s = a + b v along the last axis; constant where one side is empty."""
    s0 = np.sum(w, axis=2)
    s1 = np.sum(w * v, axis=2)
    s2 = np.sum(w * v * v, axis=2)
    sy = np.sum(w * s, axis=2)
    syv = np.sum(w * s * v, axis=2)
    det = s0 * s2 - s1 * s1
    n_lo = np.sum(w * (v < 0), axis=2)
    n_hi = np.sum(w * (v > 0), axis=2)
    two = (n_lo >= 2) & (n_hi >= 2) & (det > 1e-9)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(two, (sy * s2 - s1 * syv) / det, sy / np.maximum(s0, 1e-12))
        b = np.where(two, (s0 * syv - s1 * sy) / det, 0.0)
    # a line with no usable sample at all: nearest usable line
    empty = s0 < 1
    if np.any(empty):
        for k in np.nonzero(empty.any(axis=1))[0]:
            good = np.nonzero(~empty[k])[0]
            if good.size == 0:
                a[k] = 1.0
                continue
            bad = np.nonzero(empty[k])[0]
            a[k, bad] = np.interp(bad, good, a[k, good])
            b[k, bad] = 0.0
    return a, b


def _background_at(model, x, y):
    """B of every candidate at image points x, y of shape (C, ...)."""
    shape = (-1,) + (1,) * (x.ndim - 1)
    ox = model.origin[:, 0].reshape(shape)
    oy = model.origin[:, 1].reshape(shape)
    eux = model.eu[:, 0].reshape(shape)
    euy = model.eu[:, 1].reshape(shape)
    dx = x - ox
    dy = y - oy
    u = dx * eux
    u += dy * euy
    v = dy * eux
    v -= dx * euy                   # (x - ox)(-euy) + (y - oy) eux
    n = model.a.shape[1]
    fu = u - model.umin
    np.clip(fu, 0.0, n - 1.000001, out=fu)
    flat_i = fu.astype(np.intp)     # fu >= 0: truncation is the floor
    f = fu
    f -= flat_i
    flat_i += np.arange(x.shape[0]).reshape(shape) * n
    a = model.a.ravel()
    b = model.b.ravel()
    g = 1 - f
    a_u = a[flat_i] * g
    b_u = b[flat_i] * g
    flat_i += 1
    a_u += a[flat_i] * f
    b_u += b[flat_i] * f
    b_u *= v
    b_u += a_u
    return b_u, u


#: variance [px^2] of the smoothing by the detector's own bilinear sampling along the rays (frac (1 - frac)
#: averaged over the sub-pixel position: 1/6). It acts on the frame as recorded, after any gain, so it
#: is part of the measured edge spread that the blur correction must undo whatever the gain's origin:
#: a gain gradient after the blur moved centres by -0.17 grad ln g px with no correction at all, for
#: blurs of 0.6 and 1.0 px alike (tests/ct_imaging/test_detect_frame_gradient.py).
BILINEAR_VAR_PX2 = 1.0 / 6.0


def _frame_field(model, cand, shape, min_quadratic: int = 12, min_plane: int = 5):
    """The frame-wide smooth part of the background: ln B at every candidate's centre (its local
    model, interpolated across the shadow) fitted by a quadratic in the image coordinates (a plane
    with fewer than ``min_quadratic`` candidates, None below ``min_plane``), robustly (Huber,
    k = 1.5 MAD sd, five reweightings) so that shadows on a holder's wall or past a plate's edge
    do not pull it. A heel, a gain map, the radial fall-off of an open beam are in it; walls and
    steps are not. Returns [x0, y0, s, p1, ..., p5] (8,): ln B = const + p1 X + p2 Y + p3 X^2 +
    p4 X Y + p5 Y^2 with X = (x - x0) / s, Y = (y - y0) / s (p3..p5 zero for a plane), or None.
    The fit is the same surface on a crop holding the same shadows (tracked detection)."""
    c = cand.centre
    n = c.shape[0]
    if n < min_plane:
        return None
    b, _ = _background_at(model, c[:, 0].reshape(-1, 1), c[:, 1].reshape(-1, 1))
    lnb = np.log(np.maximum(b[:, 0], 1e-6))
    x0, y0 = 0.5 * (shape[1] - 1), 0.5 * (shape[0] - 1)
    sc = 0.5 * max(shape)
    xn, yn = (c[:, 0] - x0) / sc, (c[:, 1] - y0) / sc
    cols = [np.ones(n), xn, yn] + ([xn * xn, xn * yn, yn * yn] if n >= min_quadratic else [])
    a = np.column_stack(cols)
    w = np.ones(n)
    p = np.zeros(a.shape[1])
    for _ in range(6):
        sw = np.sqrt(w)
        p = np.linalg.lstsq(a * sw[:, None], lnb * sw, rcond=None)[0]
        r = lnb - a @ p
        s = 1.4826 * float(np.median(np.abs(r - np.median(r))))
        k = 1.5 * max(s, 1e-9)
        w = np.minimum(1.0, k / np.maximum(np.abs(r), 1e-300))
    q = np.zeros(5)
    q[:a.shape[1] - 1] = p[1:]
    return np.concatenate([[x0, y0, sc], q])


def _frame_gradient(field, x, y):
    """Gradient (d ln B / dx, d ln B / dy) [1/px] of the frame-wide quadratic at image points x, y."""
    x0, y0, sc, p1, p2, p3, p4, p5 = field
    xn, yn = (x - x0) / sc, (y - y0) / sc
    return (p1 + 2 * p3 * xn + p4 * yn) / sc, (p2 + p4 * xn + 2 * p5 * yn) / sc


def _frame_systematic(accepted, meas, model, st):
    """(M, 2) one sd of the error the frame-wide gradient's share leaves in each accepted centre
    (FrameDetections.systematic_px): the ambiguous part of the full correction at the centre,
    (spread^2 - BILINEAR_VAR_PX2) G (a uniform gradient moves every edge point of a circle by
    s^2 n.G, hence its centre by s^2 G), times sqrt(1/12 + (share - 1/2)^2)."""
    m = len(accepted)
    out = np.zeros((m, 2))
    if not m or model.frame_field is None or not meas.spread2:
        return out
    idx = np.array([a[0] for a in accepted])
    centre = meas.fits[idx, :2]
    gx, gy = _frame_gradient(model.frame_field, centre[:, 0], centre[:, 1])
    f = max(0.0, meas.spread2 - BILINEAR_VAR_PX2) * np.sqrt(1.0 / 12.0 + (st.frame_gradient_share - 0.5) ** 2)
    out[:, 0], out[:, 1] = f * gx, f * gy
    out[np.array([i in meas.corner for i in idx], dtype=bool)] = 0.0
    return out


# --------------------------------------------------------------------------- stage 4b: corners

@dataclass
class _CornerModel:
    """Background of one shadow at a corner of two straight steps or ramps (see :func:`_fit_corner`)."""
    ok: bool
    detail: str
    y0: int = 0             # window origin (row, col) in the image
    x0: int = 0
    bg: np.ndarray = None   # (h, w) background B in the window
    grad: np.ndarray = None  # (h, w) relative change of B over 4 px (|grad log B| * 4); 1e3 in step zones
    ratio: float = np.nan   # rms misfit in the annulus / pixel noise there
    n: int = 0              # annulus samples used
    q: np.ndarray = None    # (14,) line parameters and amplitudes
    cov_q: np.ndarray = None  # (14, 14) their covariance from the annulus fit
    xy: tuple = None        # window coordinates relative to the candidate centre
    sector_res: np.ndarray = None  # (12,) mean log residual of the inner annulus ring per 30 deg sector


def _corner_design(p, x, y):
    """Columns [1, x, y, S1, S2, S1 S2] of the log-background for line parameters
    p = (theta1, d1, log sigma1, log W1, theta2, d2, log sigma2, log W2) (or a batch of them,
    shape (m, 8): the result gets a leading axis m). S_k is a linear ramp of width W_k across
    line k (a plate's side face seen obliquely: its thickness, hence its log-attenuation, grows
    linearly) blurred by a Gaussian of sd sigma_k; W -> 0 gives a blurred step."""
    from scipy.special import ndtr  # noqa: PLC0415  (only corner shadows need it)
    p = np.asarray(p, dtype=np.float64)
    pb = p.reshape(-1, 8)[:, :, None]
    shape = np.shape(x)
    x, y = np.ravel(x), np.ravel(y)
    s = []
    for k in (0, 4):
        sig = np.exp(np.clip(pb[:, k + 2], -3.0, 3.0))           # blur 0.05 to 20 px
        wid = np.exp(np.clip(pb[:, k + 3], -3.0, 4.0))           # ramp 0.05 to 55 px
        t = np.cos(pb[:, k]) * x + np.sin(pb[:, k]) * y - pb[:, k + 1]

        def g(u):               # integral of the blurred step
            z = u / sig
            return u * ndtr(z) + sig * np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi)
        s.append((g(t + 0.5 * wid) - g(t - 0.5 * wid)) / wid)
    one = np.ones_like(s[0])
    A = np.stack([one, one * x, one * y, s[0], s[1], s[0] * s[1]], axis=-1).reshape((-1,) + shape + (6,))
    return A if p.ndim == 2 else A[0]


def _vp_residuals(P, x, y, l):
    """Residuals (m, n) of the variable-projection fit for a batch of line parameters P (m, 6)."""
    A = _corner_design(P, x, y)
    ata = np.einsum("mni,mnj->mij", A, A) + 1e-12 * np.eye(6)
    coef = np.linalg.solve(ata, np.einsum("mni,n->mi", A, l)[..., None])[..., 0]
    return np.einsum("mni,mi->mn", A, coef) - l


def _lm_lines(p0, x, y, l, iters=25, give_up=np.inf):
    """Levenberg-Marquardt on the eight line parameters: forward-difference Jacobian and four
    damping factors per iteration, each evaluated as one batch; stops when the cost falls by
    less than 1e-4 relative, or after 5 iterations if the rms residual is still above
    ``give_up`` (the model will not pass its check)."""
    h = np.array([1e-4, 1e-3, 1e-3, 1e-3, 1e-4, 1e-3, 1e-3, 1e-3])
    p = np.asarray(p0, dtype=np.float64)
    r = _vp_residuals(p[None], x, y, l)[0]
    cost = float(r @ r)
    lam = 1e-3
    damp = np.array([0.1, 1.0, 10.0, 100.0])
    for _ in range(iters):
        J = (_vp_residuals(p[None] + np.diag(h), x, y, l) - r).T / h        # (n, 6)
        H = J.T @ J
        g = J.T @ r
        D = np.diag(np.maximum(np.diag(H), 1e-12))
        steps = np.linalg.solve(H[None] + (lam * damp)[:, None, None] * D[None] + 1e-12 * np.eye(p.size),
                                np.broadcast_to(-g, (4, p.size))[..., None])[..., 0]
        R = _vp_residuals(p[None] + steps, x, y, l)
        costs = np.einsum("mn,mn->m", R, R)
        j = int(np.argmin(costs))
        if not costs[j] < cost:
            lam *= 1000.0
            if lam > 1e8:
                break
            continue
        done = cost - costs[j] < 1e-4 * cost
        p, r, cost, lam = p + steps[j], R[j], float(costs[j]), max(lam * damp[j] * 0.3, 1e-7)
        if done or (_ >= 4 and np.sqrt(cost / l.size) > give_up):
            break
    return p


def _annulus(trans, cand, c, st):
    """The background annulus of candidate ``c`` shared by the corner model and the model check:
    radius + ``exclusion_px`` to that + max(radius, 8) px, other shadows masked. Returns
    ((y0, y1, x0, x1) window in the image, window of T (float64), X, Y (pixel offsets from the
    candidate's centre), use (bool, the annulus samples), rin, R (the window's half size))."""
    rows, cols = trans.shape
    cx, cy = cand.centre[c]
    r = float(cand.radius[c])
    rin = r + st.exclusion_px
    rout = rin + max(r, 8.0)
    R = int(np.ceil(rout)) + 1
    y0, x0 = max(int(round(cy)) - R, 0), max(int(round(cx)) - R, 0)
    y1, x1 = min(int(round(cy)) + R + 1, rows), min(int(round(cx)) + R + 1, cols)
    win = trans[y0:y1, x0:x1].astype(np.float64)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    X, Y = xx - cx, yy - cy
    rho = np.hypot(X, Y)
    use = (rho > rin) & (rho < rout) & (cand.shadows[y0:y1, x0:x1] == 0) & (win > 1e-6)
    return (y0, y1, x0, x1), win, X, Y, use, rin, R


def _fit_corner(trans, cand, c, theta1, st):
    """Log-background of candidate ``c`` as a plane plus two straight blurred ramps (steps of
    any width, :func:`_corner_design`) and their product (a plate or holder corner: the region
    inside both), fitted to the annulus between ``radius + exclusion_px`` and ``2 radius +
    exclusion_px`` (other shadows masked) by variable projection: the eight line parameters by
    :func:`_lm_lines` on at most 200 evenly spread samples, the six amplitudes linearly for
    each. The lines are started from the strongest gradient across ``theta1`` (the
    one-direction model's structure) and the structure tensor of the gradients away from it.

    The model's own check: the rms misfit on all annulus samples against the pixel noise there
    (robust, from differences of neighbouring annulus pixels), returned in ``ratio``. Also
    returned: the covariance of all 14 parameters (s^2 (J^T J)^-1) and the mean residual of the
    inner ring per sector, which :func:`_corner_pass` propagates to the centre."""
    (y0, y1, x0, x1), win, X, Y, use, rin, _ = _annulus(trans, cand, c, st)
    n = int(use.sum())
    if n < 100:
        return _CornerModel(False, f"only {n} background samples round the shadow")
    L = np.log(np.where(win > 1e-6, win, 1e-6))
    # noise in the annulus: neighbouring-pixel differences of log T, both pixels in the annulus
    dh = (L[:, 1:] - L[:, :-1])[use[:, 1:] & use[:, :-1]]
    dv = (L[1:, :] - L[:-1, :])[use[1:, :] & use[:-1, :]]
    d = np.concatenate([dh, dv])
    noise = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / np.sqrt(2.0)
    xs, ys, ls = X[use], Y[use], L[use]
    # start: step 1 across theta1 where the gradient across it is strongest
    gy, gx = np.gradient(L)
    n1 = np.array([np.cos(theta1), np.sin(theta1)])
    g1 = np.abs(gx * n1[0] + gy * n1[1]) * use
    u1 = X * n1[0] + Y * n1[1]
    d1 = float(u1.ravel()[np.argmax(g1)])
    far = use & (np.abs(u1 - d1) > 4.0)
    jxx, jyy, jxy = np.sum(gx * gx * far), np.sum(gy * gy * far), np.sum(gx * gy * far)
    theta2 = 0.5 * np.arctan2(2 * jxy, jxx - jyy)
    n2 = np.array([np.cos(theta2), np.sin(theta2)])
    g2 = np.abs(gx * n2[0] + gy * n2[1]) * far
    d2 = float((X * n2[0] + Y * n2[1]).ravel()[np.argmax(g2)])

    # the line parameters from at most 200 evenly spread samples (speed; the amplitudes and the
    # misfit below use them all)
    step = max(1, int(np.ceil(xs.size / 200)))
    xf, yf, lf = xs[::step], ys[::step], ls[::step]

    try:
        lim = np.inf if st.max_corner_misfit is None else 1.3 * st.max_corner_misfit * noise
        p = _lm_lines([theta1, d1, -0.4, 0.0, theta2, d2, -0.4, 0.0], xf, yf, lf, give_up=lim)
    except np.linalg.LinAlgError as e:      # pragma: no cover - defensive
        return _CornerModel(False, f"corner fit failed: {e}")
    A = _corner_design(p, xs, ys)
    coef, *_ = np.linalg.lstsq(A, ls, rcond=None)
    res = A @ coef - ls
    rms = float(np.sqrt(np.mean(res ** 2)))
    ratio = rms / max(noise, 1e-9)
    if st.max_corner_misfit is not None and not ratio <= st.max_corner_misfit:
        return _CornerModel(True, "", ratio=ratio, n=n)          # refused by the caller: no more work
    # the misfit next to the shadow: mean residual of the inner ring (4 px) in 12 sectors
    ang = np.arctan2(ys, xs)
    sec = _sector_of(ang)
    inner = np.hypot(xs, ys) < rin + 4.0
    sector_res = np.array([float(np.mean(res[(sec == k) & inner])) if np.any((sec == k) & inner) else 0.0
                           for k in range(12)])
    logb = _corner_design(p, X.astype(np.float64), Y.astype(np.float64)) @ coef
    gyb, gxb = np.gradient(logb)
    grad = 4.0 * np.hypot(gxb, gyb)
    # the transition zone of each ramp (half its width + 2 blur sd + 1 px each side) counts as a
    # background edge wherever the step is more than 10 noise sd high: edge points there carry
    # the model's error near the lines, which the background-edge terms (cluster-robust and
    # refit-without) take from the data
    for k, (amp1, amp2) in enumerate(((coef[3], coef[3] + coef[5]), (coef[4], coef[4] + coef[5]))):
        if max(abs(amp1), abs(amp2)) > 10.0 * noise:
            j = 4 * k
            w = 2.0 * np.exp(np.clip(p[j + 2], -3.0, 3.0)) + 0.5 * np.exp(np.clip(p[j + 3], -3.0, 4.0))
            zone = np.abs(np.cos(p[j]) * X + np.sin(p[j]) * Y - p[j + 1]) < w + 1.0
            grad = np.where(zone, np.maximum(grad, 1e3), grad)
    # covariance of all twelve parameters: s^2 (J^T J)^-1, J the Jacobian of the log-model on
    # every annulus sample (the amplitudes' columns are the design itself)
    h = np.array([1e-4, 1e-3, 1e-3, 1e-3, 1e-4, 1e-3, 1e-3, 1e-3])
    jn = ((_corner_design(p[None] + np.diag(h), xs, ys) @ coef) - (A @ coef)[None]) / h[:, None]
    J = np.column_stack([jn.T, A])
    cov_q = rms ** 2 * np.linalg.pinv(J.T @ J)
    return _CornerModel(True, "", y0, x0, np.exp(logb), grad, ratio, n, np.concatenate([p, coef]), cov_q,
                        (X.astype(np.float64), Y.astype(np.float64)), sector_res)

def _sector_of(angle):
    """The 30 deg sector (0..11, centred as in :func:`_sector_interp`) of ``angle`` in [-pi, pi] [rad]."""
    return np.floor((angle + np.pi) / (2 * np.pi) * 12).astype(np.intp) % 12


def _sector_means(sec, values):
    """(12,) mean of ``values`` in each sector ``sec`` (0 where a sector holds none)."""
    n = np.bincount(sec, minlength=12)
    return np.where(n > 0, np.bincount(sec, values, minlength=12) / np.maximum(n, 1), 0.0)


def _sector_interp(angle, per_sector):
    """Values given per 30 deg sector (12, centred at -pi + (k + 0.5) pi / 6) interpolated
    periodically at ``angle`` [rad]."""
    sc = (np.arange(12) + 0.5) * (np.pi / 6) - np.pi
    return np.interp(angle, np.concatenate([sc - 2 * np.pi, sc, sc + 2 * np.pi]), np.tile(per_sector, 3))


def _adopt(meas, c, smeas, extra):
    """Candidate ``c`` of ``meas`` takes the single-candidate measurement ``smeas`` (a corner or
    partial-edge model's) with the extra centre covariance ``extra``."""
    meas.extra_cov[c] = extra
    for f in ("ok", "fits", "n_pts", "rms", "s2", "sums", "qmin", "edge_frac", "edge_shift"):
        getattr(meas, f)[c] = getattr(smeas, f)[0]
    meas.normals[c] = smeas.normals[0]
    meas.n_fits += smeas.n_fits
    meas.corner.add(c)


def _corner_pass(trans, cand, model, meas, deferred, st, drange, rej, last=None):
    """Measure the shadows the one-direction background refused (``deferred`` from
    :func:`_screen_fits`) with the corner model (:func:`_fit_corner`): where its misfit on the
    annulus is within ``max_corner_misfit`` x the noise there, the window is divided by it, the
    usual local background (now of a flat window), edges and fit run on it, and the ordinary
    screens (size, shape, contrast, darkness) apply, and the proximity rule against any pixel
    darker than ``segment_depth`` under the model (a neighbour merged with a band was no
    candidate). The measurement replaces the candidate's row of ``meas``; its covariance gets
    the corner model's own uncertainty (``meas.extra_cov``): the centre measured again with the
    model moved by one sd along each principal direction of its parameters' covariance, and
    with the background corrected by the inner ring's sector residuals (the misfit next to the
    shadow), each change's outer product added. Returns the accepted candidates; refused ones
    are ``background_structure`` with both models' figures (or ``overlap`` etc.), or, when a
    list ``last`` is given, go to it as (c, centre, area, reasons) for :func:`_two_model_pass`."""
    out = []

    def refuse(c, where, a, why):
        if last is None:
            rej.add(where, a, "background_structure", why)
        else:
            last.append((c, where, a, why))

    depth_all = -np.log(np.clip(meas.qmin, 1e-6, None))
    depth_ref = float(np.median(depth_all[meas.ok])) if np.any(meas.ok) else np.nan
    for c, where, a, detail in deferred:
        if st.max_corner_misfit is None:
            refuse(c, where, a, detail)
            continue
        theta1 = float(np.arctan2(model.eu[c, 1], model.eu[c, 0]))
        cm = _fit_corner(trans, cand, c, theta1, st)
        if not cm.ok or not cm.ratio <= st.max_corner_misfit:
            why = cm.detail if not cm.ok else (f"misfit {cm.ratio:.2f} x the annulus noise > "
                                               f"{st.max_corner_misfit}")
            why = f"{detail}; corner model of two steps: {why}"
            if st.arc_pass:
                arc = _arc_measure(trans, cand, c, meas, st, drange, depth_ref, rej)
                if arc is None:
                    out.append(c)
                    continue
                if not arc:                # refused by an ordinary screen (recorded there)
                    continue
                why += f"; partial edge: {arc}"
            refuse(c, where, a, why)
            continue
        h, w = cm.bg.shape
        sl = (slice(cm.y0, cm.y0 + h), slice(cm.x0, cm.x0 + w))
        saved = trans[sl].copy()
        k = np.array([c])
        sub = _subset(cand, k)

        def measure(bg):
            if not (np.all(np.isfinite(bg)) and np.min(bg) > 1e-6):
                return None, None          # a perturbed model that overflows: not measurable
            try:
                trans[sl] = (saved / bg).astype(trans.dtype)
                sm_, _ = _local_backgrounds(trans, None, sub, st)
                sm_.corner = (cm,)
                return sm_, _measure_edges_and_fit(trans, sm_, sub, st)
            finally:
                trans[sl] = saved

        sm, smeas = measure(cm.bg)
        if smeas is None:
            refuse(c, where, a, f"{detail}; corner model of two steps: not finite")
            continue
        if not _screen_fits(smeas, sub, sm, st, drange, rej, depth_ref=depth_ref, structure=False):
            continue
        # the proximity rule against any shadow (also one merged with a band, which was no
        # candidate): no pixels darker than segment_depth under the corner model within
        # proximity_margin_px outside this shadow's threshold outline (about 1 px outside the
        # edge; the ring starts at 2 px, where this shadow's own blurred edge is above that level)
        fc = smeas.fits[0]
        rf = float(np.sqrt(fc[2] * fc[3]))
        rho = np.hypot(cm.xy[0] + cand.centre[c, 0] - fc[0], cm.xy[1] + cand.centre[c, 1] - fc[1])
        ring = (rho > rf + 2.0) & (rho < rf + 1.0 + st.proximity_margin_px)
        near = ring & (saved < cm.bg * (1.0 - st.segment_depth))
        if np.count_nonzero(near) >= 3:
            rej.add(where, a, "overlap", f"another shadow within {st.proximity_margin_px} px "
                                         "(corner model)")
            continue
        # the corner model's own uncertainty, propagated: the centre measured again with the
        # model moved by one sd along each principal direction of its parameters' covariance
        # (a direction whose one-sd move gives no measurable shadow: the model is not determined
        # well enough to measure on, the shadow stays refused)
        lam, vec = np.linalg.eigh(cm.cov_q)
        extra = np.zeros((2, 2))
        undetermined = not np.all(np.isfinite(lam))
        for li, vi in zip(lam, vec.T):
            if undetermined:
                break
            if not li > 0:
                continue
            q = cm.q + np.sqrt(li) * vi
            with np.errstate(over="ignore", invalid="ignore"):
                bq = np.exp(_corner_design(q[:8], *cm.xy) @ q[8:])
            _, mi = measure(bq)
            if mi is None or not mi.ok[0]:
                undetermined = True
                break
            dc = mi.fits[0, :2] - smeas.fits[0, :2]
            extra += np.outer(dc, dc)
        if undetermined:
            why = (f"{detail}; corner model of two steps: not determined "
                   "(a one-sd change of its parameters leaves no measurable shadow)")
            if st.arc_pass:
                arc = _arc_measure(trans, cand, c, meas, st, drange, depth_ref, rej)
                if arc is None:
                    out.append(c)
                    continue
                if not arc:
                    continue
                why += f"; partial edge: {arc}"
            refuse(c, where, a, why)
            continue
        # and the model's misfit next to the shadow: the centre measured again with the
        # background corrected by the inner ring's mean residual per sector (interpolated in angle)
        f = _sector_interp(np.arctan2(cm.xy[1], cm.xy[0]), cm.sector_res)
        _, mi = measure(cm.bg * np.exp(-f))
        if mi is not None and mi.ok[0]:
            dc = mi.fits[0, :2] - smeas.fits[0, :2]
            extra += np.outer(dc, dc)
        _adopt(meas, c, smeas, extra)
        out.append(c)
    return out


def _model_check(trans, cand, model, meas, accepted, st):
    """A second background model where the first one misfits: for each accepted shadow measured
    with the one-direction model whose misfit on its background samples is above
    ``model_check_misfit`` x the frame's median, log T is fitted on the annulus between
    ``radius + exclusion_px`` and ``2 radius + exclusion_px`` (other shadows masked) by a surface of
    degree ``model_check_degree`` in image coordinates, the shadow is measured again with that
    surface as its background, and the outer product of the two centres' difference is added to
    the centre's covariance (``meas.extra_cov``): where two plausible models of the background
    disagree, the centre is known no better than their difference. Neither model holds
    everywhere: the lines follow a sharp band or step that no low-order surface fits; the surface
    follows a background that bends round the shadow (a plate's oblique edge near its corner, a
    band turning into the tube's end rim), which straight lines along the structure miss under
    the shadow by 2-5 % of the background. On the holder frames of
    ``validate_ct_detect_holders.py`` (seeds 1-3) the shadows above 1.5 x the median misfit held
    10 of the 11 centres more than 4 sd off (0.04-0.17 px; z rms 3-5, against 1.2 below 1.5 x),
    the eleventh at 1.27 x: hence the default 1.25 (on upright-tube frames about one shadow in 12
    frames is checked; doc/ct_detect.md, "A second background model").
    A surface measurement that fails adds the shadow's own radius^2 / 4: kept and counted, but it
    weighs nothing in a fit. The flagged shadows are measured together, in batches whose windows
    do not overlap."""
    if len(cand.index) < 3:
        return
    misfit = model.structure / max(float(np.median(model.structure)), 1e-9)
    todo = [c for c in accepted if c not in meas.corner and c not in meas.checked
            and misfit[c] > st.model_check_misfit]
    for c, dc in _surface_shifts(trans, cand, model, meas, todo, st).items():
        if dc is None:
            meas.extra_cov[c] = meas.extra_cov[c] + np.eye(2) * (0.5 * float(cand.radius[c])) ** 2
        else:
            meas.extra_cov[c] = meas.extra_cov[c] + np.outer(dc, dc)


def _surface_shifts(trans, cand, model, meas, todo, st):
    """For each candidate of ``todo``: its centre measured with a surface of degree
    ``model_check_degree`` in image coordinates, fitted to log T on its annulus (:func:`_annulus`),
    as the background, minus its centre in ``meas``. Returns {c: (2,) shift, or None where the
    surface has too few samples or the measurement fails}. The windows are measured together,
    in batches that do not overlap."""
    out = {}
    deg = int(st.model_check_degree)
    wins = []
    for c in todo:
        box, win, X, Y, use, _, R = _annulus(trans, cand, c, st)
        X, Y = X / R, Y / R
        terms = [X ** i * Y ** j for i in range(deg + 1) for j in range(deg + 1 - i)]
        if np.count_nonzero(use) < 4 * len(terms):
            out[c] = None
            continue
        L = np.log(np.where(win > 1e-6, win, 1e-6))
        coef, *_ = np.linalg.lstsq(np.stack([t[use] for t in terms], axis=1), L[use], rcond=None)
        wins.append((c, box, np.exp(sum(cf * t for cf, t in zip(coef, terms)))))
    while wins:                        # batches of windows that do not overlap
        batch, rest = [], []
        for w in wins:
            y0, y1, x0, x1 = w[1]
            if any(y0 < b[1][1] and b[1][0] < y1 and x0 < b[1][3] and b[1][2] < x1 for b in batch):
                rest.append(w)
            else:
                batch.append(w)
        wins = rest
        k = np.array([w[0] for w in batch])
        saved = [trans[w[1][0]:w[1][1], w[1][2]:w[1][3]].copy() for w in batch]
        sub = _subset(cand, k)
        flat = _flat_background(cand.centre[k], umin=model.umin, structure=1.0)
        try:
            for w, sv in zip(batch, saved):
                trans[w[1][0]:w[1][1], w[1][2]:w[1][3]] = (sv / w[2]).astype(trans.dtype)
            smeas = _measure_edges_and_fit(trans, flat, sub, st)
        finally:
            for w, sv in zip(batch, saved):
                trans[w[1][0]:w[1][1], w[1][2]:w[1][3]] = sv
        for j, c in enumerate(k):
            out[int(c)] = smeas.fits[j, :2] - meas.fits[c, :2] if smeas.ok[j] else None
    return out


def _two_model_pass(trans, cand, model, meas, last, st, rej):
    """The last resort for shadows no single background model holds round (``last``: refused by
    the one-direction model's structure screens, the corner model and the partial edge, as
    (c, centre, area, reasons)). Such a shadow is kept on its one-direction measurement when (1)
    no pixel within ``proximity_margin_px`` outside its outline is darker than ``segment_depth``
    under the one-direction background (a neighbour merged with the structure, which the
    candidates' proximity rule cannot see) and (2) the surface of the model check measures it
    too (:func:`_surface_shifts`). Its covariance gets the outer products of the two centres'
    difference and of the centre's shift when the one-direction background is corrected by its
    own misfit next to the shadow (:func:`_ring_shift`): at the tube's end rim both models err
    alike, and their difference alone left row z rms 1.6 on independent recordings (with the
    second term 1.06; holder frames: 23 kept, errors 0.002-0.12 px, |z| <= 1.9; doc/ct_detect.md,
    "The two-model pass"). Returns the kept candidates; the others are ``background_structure``
    with every model's reason."""
    out, keep = [], []
    rows, cols = trans.shape
    margin = float(st.proximity_margin_px)
    for c, where, a, why in last:
        fc = meas.fits[c]
        rf = float(np.sqrt(fc[2] * fc[3]))
        if not (meas.ok[c] and np.isfinite(rf)):
            rej.add(where, a, "background_structure", why)
            continue
        R = int(np.ceil(rf + 2.0 + margin))
        y0, x0 = max(int(round(fc[1])) - R, 0), max(int(round(fc[0])) - R, 0)
        y1, x1 = min(int(round(fc[1])) + R + 1, rows), min(int(round(fc[0])) + R + 1, cols)
        yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float64)
        B = _background_at(_one_background(model, c), xx[None], yy[None])[0][0]
        rho = np.hypot(xx - fc[0], yy - fc[1])
        ring = (rho > rf + 2.0) & (rho < rf + 1.0 + margin)
        if np.count_nonzero(ring & (trans[y0:y1, x0:x1] < B * (1.0 - st.segment_depth))) >= 3:
            rej.add(where, a, "background_structure", f"{why}; two models: dark pixels within {margin} px "
                                                      "outside the shadow under the one-direction background")
            continue
        keep.append((c, where, a, why))
    shifts = _surface_shifts(trans, cand, model, meas, [k[0] for k in keep], st)
    for c, where, a, why in keep:
        dc = shifts[c]
        if dc is None:
            rej.add(where, a, "background_structure", f"{why}; two models: the surface measurement failed")
            continue
        dr = _ring_shift(trans, cand, model, c, st)
        if dr is None:
            rej.add(where, a, "background_structure", f"{why}; two models: the ring-corrected measurement failed")
            continue
        meas.extra_cov[c] = meas.extra_cov[c] + np.outer(dc, dc) + np.outer(dr, dr)
        meas.checked.add(c)
        out.append(c)
    return out


def _one_background(model, c):
    """The one-direction background model of candidate ``c`` alone (for :func:`_background_at`)."""
    return _LocalBackground(origin=model.origin[c:c + 1], eu=model.eu[c:c + 1], ev=model.ev[c:c + 1],
                            umin=model.umin, a=model.a[c:c + 1], b=model.b[c:c + 1],
                            edge_gradient=model.edge_gradient[c:c + 1], structure=model.structure[c:c + 1],
                            coherence=model.coherence[c:c + 1], minor=model.minor[c:c + 1])


def _ring_shift(trans, cand, model, c, st):
    """How far the centre of candidate ``c`` moves when its one-direction background is corrected
    by that model's misfit next to the shadow: the mean log residual of the annulus' inner 2 px
    ring per 30 deg sector (interpolated in angle), as the corner and partial-edge passes measure
    theirs. Both centres are measured on the window divided by the background (flat model), so
    the shift is the correction's alone. Returns the (2,) shift, or None if either fails."""
    box, win, X, Y, use, rin, _ = _annulus(trans, cand, c, st)
    y0, y1, x0, x1 = box
    cx, cy = cand.centre[c]
    B = _background_at(_one_background(model, c), (X + cx)[None], (Y + cy)[None])[0][0]
    ok = use & (B > 1e-6)
    inner = ok & (np.hypot(X, Y) < rin + 2.0)
    ang = np.arctan2(Y, X)
    sec = _sector_of(ang)
    res = np.log(np.where(ok, win, 1.0)) - np.log(np.where(ok, B, 1.0))
    f = _sector_interp(ang, _sector_means(sec[inner], res[inner]))
    k1 = np.array([c])
    sub = _subset(cand, k1)
    flat = _flat_background(cand.centre[k1])
    saved = trans[y0:y1, x0:x1].copy()
    Bs = np.maximum(B, 1e-6)
    fits = []
    try:
        for bg in (Bs, Bs * np.exp(f)):
            trans[y0:y1, x0:x1] = (saved / bg).astype(trans.dtype)
            m = _measure_edges_and_fit(trans, flat, sub, st)
            if not m.ok[0]:
                return None
            fits.append(m.fits[0, :2])
    finally:
        trans[y0:y1, x0:x1] = saved
    return fits[1] - fits[0]


def _arc_measure(trans, cand, c, meas, st, drange, depth_ref, rej):
    """Measure candidate ``c`` on the part of its edge whose surroundings a plane fits.

    A plane of log T is fitted to a narrow annulus (``radius + exclusion_px`` to that + max(4,
    radius / 2) px; other shadows masked); the 12 sectors of 30 deg are scored by their rms
    misfit over the pixel noise there (robust, from neighbouring-pixel differences), and the
    worst sector above ``max_arc_sector_misfit`` is dropped and the plane refitted, until every
    kept sector fits (at least ``min_arc_sectors`` kept). The window is divided by the plane and
    the edges are measured as usual (flat background) on the rays of the kept sectors only.
    Uncertainty added to the edge-scatter one (``meas.extra_cov``): the part of the centre's
    variance that the other ellipse parameters take on a partial edge (the 5-parameter fit's
    centre block over the 2-parameter one, near-circle Jacobian), and the plane's own (the
    centre measured again with the plane moved by one sd along each principal direction of its
    covariance). Returns None when accepted (``meas`` row replaced), "" when refused by an
    ordinary screen (recorded in ``rej``), else the reason text."""
    rows, cols = trans.shape
    cx, cy = cand.centre[c]
    r = float(cand.radius[c])
    rin = r + st.exclusion_px
    rout = rin + max(4.0, 0.5 * r)
    R = int(np.ceil(rout)) + 1
    y0, x0 = max(int(round(cy)) - R, 0), max(int(round(cx)) - R, 0)
    y1, x1 = min(int(round(cy)) + R + 1, rows), min(int(round(cx)) + R + 1, cols)
    sl = (slice(y0, y1), slice(x0, x1))
    saved = trans[sl].copy()
    win = saved.astype(np.float64)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    X, Y = xx - cx, yy - cy
    rho = np.hypot(X, Y)
    use = (rho > rin) & (rho < rout) & (cand.shadows[sl] == 0) & (win > 1e-6)
    if np.count_nonzero(use) < 60:
        return f"only {np.count_nonzero(use)} background samples round the shadow"
    L = np.log(np.where(win > 1e-6, win, 1e-6))
    dh = (L[:, 1:] - L[:, :-1])[use[:, 1:] & use[:, :-1]]
    dv = (L[1:, :] - L[:-1, :])[use[1:, :] & use[:-1, :]]
    d = np.concatenate([dh, dv])
    noise = max(1.4826 * float(np.median(np.abs(d - np.median(d)))) / np.sqrt(2.0), 1e-9)
    xs, ys, ls = X[use], Y[use], L[use]
    sec = _sector_of(np.arctan2(ys, xs))
    A = np.column_stack([np.ones_like(xs), xs, ys])
    good = np.bincount(sec, minlength=12) >= 3
    if np.count_nonzero(good) < st.min_arc_sectors:
        return "too few sectors with background samples"
    while True:
        sel = good[sec]
        coef, *_ = np.linalg.lstsq(A[sel], ls[sel], rcond=None)
        res = ls - A @ coef
        m = np.sqrt(np.bincount(sec, res * res, minlength=12) / np.maximum(np.bincount(sec, minlength=12), 1)) / noise
        mg = np.where(good, m, -np.inf)
        k = int(np.argmax(mg))
        if mg[k] <= st.max_arc_sector_misfit:
            break
        good[k] = False
        if np.count_nonzero(good) < st.min_arc_sectors:
            return (f"a plane fits only {np.count_nonzero(good)} of 12 sectors round it (< {st.min_arc_sectors}; "
                    f"misfit up to {float(np.max(m)):.1f} x the noise)")
    # a structure that passes through or under the shadow crosses the annulus twice: the dropped
    # sectors then form more than one run, and a plane cannot carry it across the shadow
    n_runs = int(np.count_nonzero(good & ~np.roll(good, 1))) if not np.all(good) else 0
    if n_runs > 1:
        return f"the sectors a plane does not fit form {n_runs} separate arcs (a structure across the shadow)"
    sel = good[sec]
    s2p = float(np.sum(res[sel] ** 2)) / max(int(np.count_nonzero(sel)) - 3, 1)
    cov_p = s2p * np.linalg.pinv(A[sel].T @ A[sel])
    k1 = np.array([c])
    sub = _subset(cand, k1)
    flat = _flat_background(cand.centre[k1], ray_keep=good[None, :])

    def measure(q):
        bg = np.exp(q[0] + q[1] * X + q[2] * Y)
        try:
            trans[sl] = (saved / bg).astype(trans.dtype)
            return bg, _measure_edges_and_fit(trans, flat, sub, st)
        finally:
            trans[sl] = saved

    bg, smeas = measure(coef)
    if not smeas.ok[0]:
        return f"partial edge fit failed: {smeas.why[0]}"
    if not _screen_fits(smeas, sub, flat, st, drange, rej, depth_ref=depth_ref, structure=False):
        return ""
    fc = smeas.fits[0]
    rf = float(np.sqrt(fc[2] * fc[3]))
    rr = np.hypot(X + cx - fc[0], Y + cy - fc[1])
    ring = (rr > rf + 2.0) & (rr < rf + 1.0 + st.proximity_margin_px)
    if np.count_nonzero(ring & (saved < bg * (1.0 - st.segment_depth))) >= 3:
        return f"dark pixels within {st.proximity_margin_px} px outside the shadow under the plane"
    # partial edge: the centre block of the 5-parameter (near-circle) fit over the 2-parameter one
    nr = int(st.n_rays)
    phi = (np.arange(nr) + 0.5) * (2 * np.pi / nr)
    kp = _ray_mask(flat, phi)[0]
    ph = phi[kp]
    J = np.column_stack([np.cos(ph), np.sin(ph), np.ones_like(ph), np.cos(2 * ph), np.sin(2 * ph)])
    infl = max(1.0, smeas.n_pts[0] / (np.pi * rf))
    scale = infl * float(smeas.s2[0]) * nr / max(int(smeas.n_pts[0]), 1) * (ph.size / nr)
    extra = scale * (np.linalg.pinv(J.T @ J)[:2, :2] - np.linalg.pinv(J[:, :2].T @ J[:, :2]))
    lam, vec = np.linalg.eigh(0.5 * (extra + extra.T))
    extra = (vec * np.maximum(lam, 0.0)) @ vec.T
    # the plane's own uncertainty
    lam, vec = np.linalg.eigh(cov_p)
    for li, vi in zip(lam, vec.T):
        if not li > 0:
            continue
        _, mi = measure(coef + np.sqrt(li) * vi)
        if not mi.ok[0]:
            return "not determined (a one-sd change of the plane leaves no measurable shadow)"
        dc = mi.fits[0, :2] - smeas.fits[0, :2]
        extra += np.outer(dc, dc)
    # and the plane's misfit next to the shadow: the centre measured again with the plane
    # corrected by the inner ring's (2 px) mean residual per kept sector (interpolated in angle)
    inner = sel & (np.hypot(xs, ys) < rin + 2.0)
    f = _sector_interp(np.arctan2(Y, X), np.where(good, _sector_means(sec[inner], res[inner]), 0.0))
    try:
        trans[sl] = (saved / (bg * np.exp(f))).astype(trans.dtype)
        mi = _measure_edges_and_fit(trans, flat, sub, st)
    finally:
        trans[sl] = saved
    if mi.ok[0]:
        dc = mi.fits[0, :2] - smeas.fits[0, :2]
        extra += np.outer(dc, dc)
    _adopt(meas, c, smeas, extra)
    return None


# --------------------------------------------------------------------------- stage 6-7: edges and fits

@dataclass
class _Measurement:
    ok: np.ndarray
    why: list
    fits: np.ndarray        # (C, 5)
    n_pts: np.ndarray
    rms: np.ndarray
    s2: np.ndarray          # (C,) dof-corrected edge variance
    normals: list           # per candidate (nx, ny, d, on_edge) arrays of the final fit
    sums: np.ndarray        # (C, 3) sum of nx^2, nx ny, ny^2 over each final fit's points
    qmin: np.ndarray
    edge_frac: np.ndarray   # fraction of edge points on a strong background edge
    n_fits: int
    edge_shift: np.ndarray  # (C, 2) centre minus the centre fitted without background-edge points
    extra_cov: np.ndarray = None  # (C, 2, 2) added to the centre covariance (corner model's own)
    corner: set = None      # candidates measured with the corner model
    checked: set = None     # candidates kept by the two-model pass (their covariance has its term)
    level_shift: float = 0.0  # the blur's inward shift of the level crossing [px] (_edge_spread2)
    spread2: float = 0.0      # edge spread variance used for the blur correction [px^2]


def _edge_points(trans, model, centre, radius, st, first, level, want_edge=True, spread2=None):
    """Sub-pixel edge points along rays (vectorised over candidates).

    Pass 1: ``n_rays/2`` rays over the whole edge zone, which also measure the inner shadow
    level (the iso-level is half way between the local background, 1, and that level);
    later passes: ``n_rays`` rays on a narrow band round the previous fit. Returns
    (ex, ey, valid, level, qmin, on_edge (C, R) bool, n_rays)."""
    nc = centre.shape[0]
    nr = max(16, int(st.n_rays) // 2) if (first and st.n_passes > 1) else int(st.n_rays)
    phi = (np.arange(nr) + 0.5) * (2 * np.pi / nr)
    cphi, sphi = np.cos(phi), np.sin(phi)
    if first:
        ns = int(st.n_samples)
        w_out = np.maximum(0.5 * radius, 4.0)
        w_in = np.minimum(w_out, 0.6 * radius)
    else:
        ns = max(8, int(st.n_samples) // 2)
        w_out = np.minimum(np.maximum(0.25 * radius, 3.0), 0.5 * radius)
        w_in = w_out
    t = np.linspace(0.0, 1.0, ns)
    r_s = (radius - w_in)[:, None] + (w_in + w_out)[:, None] * t[None, :]
    xs = centre[:, 0, None, None] + cphi[None, :, None] * r_s[:, None, :]
    ys = centre[:, 1, None, None] + sphi[None, :, None] * r_s[:, None, :]
    prof = _bilinear(trans, xs, ys)
    bgl, _ = _background_at(model, xs, ys)
    q = prof / bgl
    qmin = None
    if first:
        n_in = max(2, ns // 10)
        q_in = np.median(q[:, :, :n_in].reshape(nc, -1), axis=1)
        qmin = np.minimum(np.min(q[:, :, :n_in], axis=(1, 2)), q_in)
        level = 1.0 - st.edge_level * (1.0 - q_in)
    below = q < level[:, None, None]
    last = ns - 1 - np.argmax(below[:, :, ::-1], axis=2)
    valid = below.any(axis=2) & (last < ns - 1) & (last > 0)
    k = np.clip(last, 0, ns - 2)
    q0 = np.take_along_axis(q, k[..., None], axis=2)[..., 0]
    q1 = np.take_along_axis(q, (k + 1)[..., None], axis=2)[..., 0]
    dq = q1 - q0
    valid &= dq > 0
    keep = _ray_mask(model, phi)
    if keep is not None:
        valid &= keep
    frac = np.where(valid, (level[:, None] - q0) / np.where(dq > 0, dq, 1.0), 0.0)
    dr = (w_in + w_out) / (ns - 1)
    r_edge = r_s[np.arange(nc)[:, None], k] + frac * dr[:, None]
    level_shift = None
    if first and spread2 is None:
        spread2, level_shift = _edge_spread2(dq / dr[:, None], level, valid, q_in, r_s[:, n_in // 2], radius, dr, st)
    if spread2:
        # the detector blurs the product shadow x background; dividing by the (blurred)
        # background leaves the shadow moved by -spread^2 grad ln B (first order in the
        # background's gradient): put each edge point back along its ray
        ex0 = centre[:, 0, None] + cphi[None, :] * r_edge
        ey0 = centre[:, 1, None] + sphi[None, :] * r_edge
        bp, _ = _background_at(model, ex0 + cphi[None, :], ey0 + sphi[None, :])
        bm, _ = _background_at(model, ex0 - cphi[None, :], ey0 - sphi[None, :])
        with np.errstate(divide="ignore", invalid="ignore"):
            glog = 0.5 * np.log(np.maximum(bp, 1e-6) / np.maximum(bm, 1e-6))
        glog = np.where(np.isfinite(glog), glog, 0.0)
        if model.frame_field is not None and st.frame_gradient_share != 1.0:
            # the frame-wide smooth part only by its share (DetectionSettings.frame_gradient_share);
            # the share of the spread that is this detector's own bilinear sampling (after any
            # gain) is corrected in full
            gx, gy = _frame_gradient(model.frame_field, ex0, ey0)
            amb = (1.0 - st.frame_gradient_share) * max(0.0, 1.0 - BILINEAR_VAR_PX2 / spread2)
            glog = glog - amb * (cphi[None, :] * gx + sphi[None, :] * gy)
        r_edge = r_edge + spread2 * glog
    ex = centre[:, 0, None] + cphi[None, :] * r_edge
    ey = centre[:, 1, None] + sphi[None, :] * r_edge
    # edge points where the background itself changes fast across the structure (> gradient
    # over 4 px): a band or step edge, whose sub-pixel mixing with the shadow no division undoes
    on_edge = None
    if want_edge:
        ox, oy = model.origin[:, 0, None], model.origin[:, 1, None]
        u = (ex - ox) * model.eu[:, 0, None] + (ey - oy) * model.eu[:, 1, None]
        n = model.a.shape[1]
        iu = np.clip(np.rint(u - model.umin).astype(np.intp), 0, n - 1)
        g = np.take_along_axis(model.edge_gradient, iu, axis=1)
        if model.corner is not None:      # corner shadows: the two-step model's own gradient
            for j, cm in enumerate(model.corner):
                if cm is not None:
                    g[j] = _bilinear(cm.grad, np.clip(ex[j] - cm.x0, 0, cm.grad.shape[1] - 1),
                                     np.clip(ey[j] - cm.y0, 0, cm.grad.shape[0] - 1))
        on_edge = valid & (g > st.background_edge_gradient)
    return ex, ey, valid, level, qmin, on_edge, nr, spread2, level_shift


def _ray_mask(model, phi):
    """(C, nr) rays kept (their 30 deg sector in ``model.ray_keep``), or None (all)."""
    if model.ray_keep is None:
        return None
    return np.asarray(model.ray_keep, bool)[:, _sector_of(np.where(phi > np.pi, phi - 2 * np.pi, phi))]


def _edge_spread2(slope, level, valid, q_in, r_in, radius, dr, st):
    """(variance [px^2] of the detector's edge spread (blur and pixel aperture together) from the
    shadows' own edges, or ``st.edge_spread_px`` squared when set (0 switches the correction off);
    the level shift [px]).

    A step of height h blurred by a Gaussian of sd s rises at h / (s sqrt(2 pi)) at its half-way
    point; the median over every ray of the frame of that "apparent" s (robust to band edges and
    neighbours) also holds the sphere's own soft edge (chord 2 sqrt(R^2 - r^2) of a homogeneous
    ball). That part is taken out with the frame's median ball: attenuation per px from the
    inner shadow level ``q_in`` at ``r_in``, radius ``radius``; the 1-D profile is blurred for a
    grid of s and the apparent s of each (its slope taken over the rays' sample spacing ``dr``,
    as measured) is matched to the measured one.

    The level shift: how far inside the unblurred shadow's iso-level contour the blurred shadow
    crosses the same level, for the frame's median ball at the matched spread (0 where no spread
    is matched). Every iso-level contour of a ball is a cone section; the blur moves the crossing
    inward by about the same number of pixels all round, which shrinks the fitted axes but leaves
    the centre where that cone's section has it, so the section's semi-minor axis is the fitted
    one plus this shift (ct_core.md, "z_R lean")."""
    if st.edge_spread_px is not None:
        return float(st.edge_spread_px) ** 2, 0.0
    h = (1.0 - level) / st.edge_level                    # shadow depth of each candidate
    with np.errstate(divide="ignore", invalid="ignore"):
        s = h[:, None] / (np.sqrt(2.0 * np.pi) * slope)
    good = valid & np.isfinite(s) & (s > 0)
    if np.count_nonzero(good) < 16:
        return 0.0, 0.0
    s_app = float(np.median(s[good]))
    rows_ = good.any(axis=1)
    R = float(np.median(radius[rows_]))
    chord = 2.0 * np.sqrt(np.maximum(radius ** 2 - r_in ** 2, 1e-9))
    with np.errstate(divide="ignore", invalid="ignore"):
        mu = -np.log(np.clip(q_in, 1e-6, 1.0)) / chord
    mu = float(np.median(mu[rows_]))
    f_in = float(np.median(r_in[rows_] / radius[rows_]))
    h_dr = 0.5 * float(np.median(dr[rows_]))
    if not (R > 2.0 and mu > 0 and np.isfinite(mu)):
        return s_app ** 2, 0.0
    # 1-D model of the ray profile near the edge, blurred (by FFT) for a grid of s
    dx = 0.02
    x = np.arange(-R * (1.0 - f_in) - 2.0, 10.0, dx)      # distance outside the edge [px]
    r = R + x
    prof = np.exp(-2.0 * mu * np.sqrt(np.clip(R * R - r * r, 0.0, None)))
    n = 1 << int(np.ceil(np.log2(x.size + 1200)))
    pad = np.full(n, 1.0)
    pad[:x.size] = prof
    pad[n - 600:] = prof[0]                           # the shadow side continued (circular FFT)
    f = np.fft.rfftfreq(n, dx)
    sig = np.linspace(0.05, 3.0, 60)
    b_all = np.fft.irfft(np.fft.rfft(pad)[None, :] * np.exp(-2.0 * (np.pi * f[None, :] * sig[:, None]) ** 2),
                         n, axis=1)[:, :x.size]
    # every blur at once: the inner level, the last rising crossing of the iso-level, the slope there
    qi = _interp_rows(np.full(sig.size, R * (f_in - 1.0)), x, b_all)
    lev = 1.0 - st.edge_level * (1.0 - qi)
    cross = (b_all[:, :-1] < lev[:, None]) & (b_all[:, 1:] >= lev[:, None])
    kc = x.size - 2 - np.argmax(cross[:, ::-1], axis=1)      # grid cell of each blur's last crossing
    xc = x[kc]
    sl = (_interp_rows(xc + h_dr, x, b_all) - _interp_rows(xc - h_dr, x, b_all)) / (2.0 * h_dr)
    with np.errstate(divide="ignore", invalid="ignore"):
        app = np.where(cross.any(axis=1), (1.0 - qi) / (np.sqrt(2.0 * np.pi) * sl), np.nan)
    # a soft ball edge makes the apparent s fall with small blurs before it rises: only the
    # rising branch identifies s; below its minimum the shadows cannot tell the blur (returns 0,
    # the correction off, e.g. weakly absorbing balls 20 px across)
    ok = np.isfinite(app)
    if np.count_nonzero(ok) < 2:
        return s_app ** 2, 0.0
    a_ok, s_ok = app[ok], sig[ok]
    i0 = int(np.argmin(a_ok))
    a_ok, s_ok = np.maximum.accumulate(a_ok[i0:]), s_ok[i0:]
    if s_app <= a_ok[0] or a_ok.size < 2:
        return 0.0, 0.0
    s_fit = float(np.interp(s_app, a_ok, s_ok))
    # the crossing to a fraction of the grid step, and the unblurred ball's crossing of the same level
    b0, b1 = b_all[np.arange(sig.size), kc], b_all[np.arange(sig.size), kc + 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        xc_f = xc + np.clip((lev - b0) / (b1 - b0), 0.0, 1.0) * dx
        x_iso = np.sqrt(np.clip(R * R - (np.log(np.clip(lev, 1e-9, 1.0)) / (2.0 * mu)) ** 2, 0.0, None)) - R
    shift = x_iso - xc_f
    return s_fit ** 2, float(np.interp(s_fit, sig[ok], shift[ok]))



def _interp_rows(xq, xp, fp):
    """``np.interp(xq[k], xp, fp[k])`` for every row k of ``fp`` (K, N) at once (the same formula;
    ``xp`` increasing)."""
    n = xp.size
    j = np.clip(np.searchsorted(xp, xq, side="right") - 1, 0, n - 2)
    rows = np.arange(fp.shape[0])
    lo, hi = fp[rows, j], fp[rows, j + 1]
    out = (hi - lo) / (xp[j + 1] - xp[j]) * (xq - xp[j]) + lo
    out = np.where(xq == xp[j], lo, out)
    return np.where(xq < xp[0], fp[:, 0], np.where(xq >= xp[-1], fp[:, -1], out))


def _fit_rows(ex, ey, sel, rows_, fitter):
    """Ellipse fits of the selected edge points of the given candidates: (len(rows_), 5) with
    NaN rows where OpenCV failed, and the error messages by row. The same numbers as
    :func:`_fit_one` (float32 points to OpenCV), with the per-call overhead taken out."""
    out = np.full((len(rows_), 5), np.nan)
    err = {}
    if fitter == "geometric":
        for j, c in enumerate(rows_):
            v = sel[c]
            try:
                out[j] = _fit_one(np.column_stack([ex[c, v], ey[c, v]]), fitter)
            except cv2.error as exc:
                err[j] = str(exc)
        return out, err
    fit = {"fitEllipseAMS": cv2.fitEllipseAMS, "fitEllipseDirect": cv2.fitEllipseDirect}.get(fitter, cv2.fitEllipse)
    p32 = np.empty(ex.shape + (2,), np.float32)
    p32[..., 0] = ex
    p32[..., 1] = ey
    half_pi = 0.5 * np.pi
    for j, c in enumerate(rows_):
        try:
            (cx, cy), (w, h), ang = fit(p32[c][sel[c]])
        except cv2.error as exc:
            err[j] = str(exc)
            continue
        ang = np.deg2rad(ang)
        a, b = 0.5 * w, 0.5 * h
        if b > a:
            a, b = b, a
            ang += half_pi
        out[j] = (cx, cy, a, b, ang)
    return out, err


def _residuals_rows(ex, ey, fits):
    """Approximate orthogonal (Sampson: F / |grad F|, F = (x/a)^2 + (y/b)^2 - 1) distances of every
    candidate's points (C, R) from its own ellipse fit (C, 5: cx, cy, a, b, angle), and the outward
    normals in image coordinates."""
    cx, cy, a, b, ang = (fits[:, k, None] for k in range(5))
    c, s = np.cos(ang), np.sin(ang)
    dx, dy = ex - cx, ey - cy
    xp = c * dx + s * dy
    yp = -s * dx + c * dy
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        f = (xp / a) ** 2 + (yp / b) ** 2 - 1.0
        gx, gy = 2 * xp / a ** 2, 2 * yp / b ** 2
        gn = np.hypot(gx, gy)
        gn = np.where(gn > 0, gn, 1.0)
        d = f / gn
        nx = (c * gx - s * gy) / gn
        ny = (s * gx + c * gy) / gn
    return d, nx, ny


def _measure_edges_and_fit(trans, model, cand, st):
    """Edge points and ellipse fits, ``n_passes`` passes, each re-centred on the previous fit;
    the last pass removes outliers (5 robust sd, at least 0.1 px) once and refits.

    Vectorised over candidates: only the OpenCV fits run one candidate at a time."""
    nc = cand.centre.shape[0]
    centre = cand.centre.copy()
    radius = cand.radius.copy()
    ok = np.ones(nc, bool)
    why = [""] * nc
    fits = np.full((nc, 5), np.nan)
    n_pts = np.zeros(nc, int)
    rms = np.full(nc, np.nan)
    s2 = np.full(nc, np.nan)
    normals = [None] * nc
    sums = np.zeros((nc, 3))
    shift = np.zeros((nc, 2))
    edge_frac = np.zeros(nc)
    level = qmin = spread2 = None
    level_shift = 0.0
    n_fits = 0

    def _fail(rows_, msg_of):
        for c in rows_:
            ok[c] = False
            why[c] = msg_of(c)

    for pas in range(int(st.n_passes)):
        first = pas == 0
        last_pass = pas == int(st.n_passes) - 1
        ex, ey, valid, level, qm, on_edge, nr, spread2, lsh = _edge_points(
            trans, model, centre, radius, st, first, level, want_edge=last_pass, spread2=spread2)
        if first:
            qmin = qm
            level_shift = 0.0 if lsh is None else lsh
        if last_pass:
            edge_frac = np.count_nonzero(on_edge, axis=1) / np.maximum(np.count_nonzero(valid, axis=1), 1)
        n_valid = np.count_nonzero(valid, axis=1)
        keep = _ray_mask(model, (np.arange(nr) + 0.5) * (2 * np.pi / nr))
        n_rays_used = np.count_nonzero(keep, axis=1) if keep is not None else np.full(nc, nr)
        few = ok & (n_valid < st.min_edge_fraction * n_rays_used)
        _fail(np.nonzero(few)[0], lambda c: f"only {n_valid[c]} of {nr} rays found an edge")
        rows_ = np.nonzero(ok)[0]
        p, err = _fit_rows(ex, ey, valid, rows_, st.ellipse_fitter)
        n_fits += len(rows_) - len(err)
        if last_pass and len(rows_):
            # outliers beyond 5 robust sd (at least 0.1 px) removed once, then refitted
            sel = valid[rows_].copy()
            d, _, _ = _residuals_rows(ex[rows_], ey[rows_], p)
            ad = np.where(sel, np.abs(d), 0.0)
            sig = 1.2533 * ad.sum(axis=1) / np.maximum(sel.sum(axis=1), 1)
            good = sel & (ad <= np.maximum(5.0 * sig, 0.1)[:, None])
            n_good = good.sum(axis=1)
            redo = np.nonzero((n_good < sel.sum(axis=1)) & (n_good >= st.min_edge_fraction * n_rays_used[rows_])
                              & np.all(np.isfinite(p), axis=1))[0]
            redo = np.array([j for j in redo if j not in err], dtype=np.intp)
            if redo.size:
                sel[redo] = good[redo]
                full = np.zeros_like(valid)
                full[rows_[redo]] = good[redo]
                p2, err2 = _fit_rows(ex, ey, full, rows_[redo], st.ellipse_fitter)
                n_fits += redo.size - len(err2)
                p[redo] = p2
                for j, e in err2.items():
                    err[int(redo[j])] = e
        for j, e in err.items():
            ok[rows_[j]] = False
            why[rows_[j]] = f"ellipse fit failed: {e}"
        bad = np.array([j not in err and not (np.all(np.isfinite(p[j])) and p[j, 3] > 0)
                        for j in range(len(rows_))], bool)
        _fail(rows_[bad], lambda c: "ellipse fit returned a degenerate ellipse")
        keep = np.array([j not in err for j in range(len(rows_))], bool) & ~bad
        fits[rows_[keep]] = p[keep]
        if last_pass and len(rows_):
            kk = np.nonzero(keep)[0]
            cc = rows_[kk]
            sel = sel[kk]
            d, nx, ny = _residuals_rows(ex[cc], ey[cc], p[kk])
            n = sel.sum(axis=1)
            dd = np.where(sel, d, 0.0)
            ssq = np.einsum("ij,ij->i", dd, dd)
            n_pts[cc] = n
            s2[cc] = ssq / np.maximum(1, n - 5)
            rms[cc] = np.sqrt(ssq / n)
            oe_all = on_edge[cc] & sel
            nxs, nys = np.where(sel, nx, 0.0), np.where(sel, ny, 0.0)
            sums[cc] = np.column_stack([np.einsum("ij,ij->i", nxs, nxs), np.einsum("ij,ij->i", nxs, nys),
                                        np.einsum("ij,ij->i", nys, nys)])
            for j in np.nonzero(oe_all.any(axis=1))[0]:      # the cluster terms need the points
                v = sel[j]
                normals[cc[j]] = (nx[j, v], ny[j, v], d[j, v], oe_all[j, v])
            if st.background_edge_refit:
                # the same fit without the points on a background edge: the difference is the
                # data's own estimate of what the band or step does to this centre
                n_oe = oe_all.sum(axis=1)
                rf = np.nonzero((n_oe > 0) & (n - n_oe >= np.maximum(8, 0.5 * n)))[0]
                if rf.size:
                    off = np.zeros_like(valid)
                    off[cc[rf]] = sel[rf] & ~oe_all[rf]
                    p3, err3 = _fit_rows(ex, ey, off, cc[rf], st.ellipse_fitter)
                    n_fits += rf.size - len(err3)
                    fin = np.all(np.isfinite(p3), axis=1)
                    shift[cc[rf[fin]]] = p[kk[rf[fin]], :2] - p3[fin, :2]
        centre = np.where(ok[:, None], fits[:, :2], centre)
        radius = np.where(ok, np.sqrt(np.abs(fits[:, 2] * fits[:, 3])), radius)
    return _Measurement(ok=ok, why=why, fits=fits, n_pts=n_pts, rms=rms, s2=s2, normals=normals, sums=sums,
                        qmin=qmin, edge_frac=edge_frac, n_fits=n_fits, edge_shift=shift,
                        corner=set(), checked=set(), extra_cov=np.zeros((nc, 2, 2)), level_shift=level_shift,
                        spread2=float(spread2 or 0.0))


# --------------------------------------------------------------------------- stage 8-9: rejection, uncertainty

def _screen_fits(meas, cand, model, st, drange, rej, deferred=None, depth_ref=None, structure=True):
    """Post-fit screening; returns the indices (into the candidates) of accepted shadows.

    ``deferred``: a list to which ``background_structure`` refusals go as (c, centre, area,
    detail) instead of ``rej`` (the corner model may still measure them). ``depth_ref``: the
    frame's median optical depth (default: from ``meas``). ``structure=False`` skips the
    one-direction model's structure checks (the corner pass has its own)."""
    if drange is not None:
        dmin = drange[0] * (1.0 - st.size_tolerance)
        dmax = drange[1] * (1.0 + st.size_tolerance)
    ok = meas.ok
    # misfit of the background model relative to the frame's typical one (noise, compression)
    misfit = model.structure / max(float(np.median(model.structure)), 1e-9)
    cross = model.minor / max(float(np.median(model.minor)), 1e-9)
    depth_all = -np.log(np.clip(meas.qmin, 1e-6, None))
    if depth_ref is None:
        depth_ref = float(np.median(depth_all[ok])) if np.any(ok) else np.nan
    n_ok = np.count_nonzero(ok) if structure else 3
    out = []
    for c in range(len(cand.index)):
        where, a = cand.centre[c], cand.area[c]
        if not ok[c]:
            rej.add(where, a, "fit_failed", meas.why[c])
            continue
        p = meas.fits[c]
        ratio = p[2] / p[3]
        contrast = 1.0 - meas.qmin[c]
        if contrast < st.min_contrast:
            rej.add(where, a, "not_a_sphere_contrast", f"shadow depth {contrast:.3f} < {st.min_contrast}")
            continue
        if ratio > st.max_axis_ratio:
            rej.add(where, a, "overlap", f"axis ratio {ratio:.3f} > {st.max_axis_ratio}: elongated (merged) shadow")
            continue
        if meas.rms[c] > st.max_fit_rms_px:
            rej.add(where, a, "not_a_sphere_shape", f"edge RMS {meas.rms[c]:.3f} px > {st.max_fit_rms_px} px: "
                                                    "not elliptical")
            continue
        if drange is not None:
            dfit = 2.0 * np.sqrt(p[2] * p[3])
            if not (dmin <= dfit <= dmax):
                rej.add(where, a, "not_a_sphere_size", f"fitted diameter {dfit:.1f} px outside "
                                                       f"[{dmin:.1f}, {dmax:.1f}]")
                continue
        if (st.overlap_darkness is not None and np.isfinite(depth_ref) and n_ok >= 3
                and depth_all[c] > st.overlap_darkness * depth_ref):
            rej.add(where, a, "overlap", f"shadow optical depth {depth_all[c]:.2f} > {st.overlap_darkness} x "
                                         f"median {depth_ref:.2f}: spheres in line")
            continue
        if not structure:
            out.append(c)
            continue
        to = (lambda w, ar, why, d: deferred.append((c, w, ar, d))) if deferred is not None else rej.add
        if cross[c] > st.max_cross_structure:
            to(where, a, "background_structure",
                    f"background changes along its main structure too ({cross[c]:.1f} x the frame's median "
                    f"> {st.max_cross_structure}): a corner of two steps or bands, no background model holds")
            continue
        if misfit[c] > st.max_background_misfit:
            to(where, a, "background_structure",
                    f"background round the shadow misfits a straight structure {misfit[c]:.1f} x as much as the "
                    f"frame's median shadow (> {st.max_background_misfit}): a corner or curved step")
            continue
        out.append(c)
    return out


def _centre_uncertainty(accepted, meas, model, st):
    """Centre covariance ``f s^2 (sum n n^T)^-1`` per accepted shadow (s the edge RMS,
    f = max(1, n / (pi r)) for neighbouring rays sharing pixels), plus
    ``background_edge_sigma_px`` in quadrature across the structure for shadows whose edge
    crosses a background edge, plus ``meas.extra_cov`` (the corner model's propagated
    uncertainty). Returns a list of (c, cov, on_edge)."""
    out = []
    if not accepted:
        return out
    acc = np.asarray(accepted, dtype=np.intp)
    sxx, sxy, syy = meas.sums[acc].T
    det_ = sxx * syy - sxy * sxy
    p = meas.fits[acc]
    infl = np.maximum(1.0, meas.n_pts[acc] / (np.pi * np.sqrt(p[:, 2] * p[:, 3])))
    with np.errstate(divide="ignore", invalid="ignore"):
        ainv = np.stack([np.stack([syy, -sxy], -1), np.stack([-sxy, sxx], -1)], -2) / det_[:, None, None]
    cov_all = (infl * meas.s2[acc])[:, None, None] * ainv + meas.extra_cov[acc]
    on_all = (meas.edge_frac[acc] > st.background_edge_min_fraction) & (det_ > 0)
    cov_all[det_ <= 0] = np.nan
    for j, c in enumerate(accepted):
        cov = cov_all[j]
        if not on_all[j]:
            out.append((c, cov, False))
            continue
        if st.background_edge_clusters and meas.normals[c] is not None:
            # edge points on a background edge (band or step) err together: each run of them is
            # one cluster of a cluster-robust (sandwich) covariance, from their own residuals
            nx, ny, d, oe = meas.normals[c]
            m = np.zeros((2, 2))
            for g in _runs(oe):
                sg = np.array([np.dot(nx[g], d[g]), np.dot(ny[g], d[g])])
                m += np.outer(sg, sg)
            cov = cov + st.background_edge_clusters * (ainv[j] @ m @ ainv[j])
        if st.background_edge_refit:
            cov = cov + np.outer(meas.edge_shift[c], meas.edge_shift[c])
        if st.background_edge_sigma_px:
            cov = cov + st.background_edge_sigma_px ** 2 * np.outer(model.eu[c], model.eu[c])
        out.append((c, cov, True))
    return out


def _runs(flags):
    """Index arrays of the runs of True in a cyclic boolean sequence (points in ray order)."""
    f = np.asarray(flags, bool)
    n = f.size
    if n == 0 or not f.any():
        return []
    if f.all():
        return [np.arange(n)]
    start = int(np.argmin(f))                 # rotate so the sequence starts on a False
    idx = np.roll(np.arange(n), -start)
    ff = f[idx].astype(np.int8)
    edges = np.diff(np.concatenate(([0], ff, [0])))
    lo = np.nonzero(edges == 1)[0]
    hi = np.nonzero(edges == -1)[0]
    return [idx[a:b] for a, b in zip(lo, hi)]


def _assemble(accepted, rej, n_fits, sdd_px, pp, shape, hot, message, meas=None, cand=None, model=None):
    m = len(accepted)
    corner = meas.corner if meas is not None else set()
    checked = meas.checked if meas is not None else set()
    on_edge = np.zeros(m, dtype=bool)
    if m:
        idx = np.array([a[0] for a in accepted])
        fits = meas.fits[idx]
        centre = fits[:, :2].copy()
        axes = fits[:, 2:4].copy()
        ang = np.mod(fits[:, 4], np.pi)
        npts = meas.n_pts[idx].astype(int)
        rms = meas.rms[idx]
        cov = np.array([a[1] for a in accepted])
        qmin = meas.qmin[idx]
        on_edge = np.array([a[2] for a in accepted], dtype=bool) if len(accepted[0]) > 2 else on_edge
    else:
        centre = np.zeros((0, 2))
        axes = np.zeros((0, 2))
        ang = np.zeros(0)
        npts = np.zeros(0, int)
        rms = np.zeros(0)
        cov = np.zeros((0, 2, 2))
        qmin = np.zeros(0)
    n_hot = np.zeros(m, dtype=int)
    if m and len(hot):
        d = np.linalg.norm(hot[None, :, :] - centre[:, None, :], axis=2)
        n_hot = np.count_nonzero(d < 1.5 * axes[:, :1] + 4.0, axis=1)
    corrected = None
    if sdd_px is not None:
        if pp is None:
            pp = ((shape[1] - 1) / 2.0, (shape[0] - 1) / 2.0)
        corrected = deng_correction(centre, axes, sdd_px, pp) if m else np.zeros((0, 2))
    rejected = RejectedCandidates(
        centre_px=np.array(rej.centre, dtype=np.float64).reshape(-1, 2),
        area_px=np.array(rej.area, dtype=np.float64),
        reason=tuple(rej.reason), detail=tuple(rej.detail))
    if not message:
        counts = {r: rejected.count(r) for r in REJECT_REASONS if rejected.count(r)}
        message = f"{m} spheres accepted, {len(rejected)} rejected" + (f" {counts}" if counts else "")
        if len(hot):
            message += f"; {len(hot)} hot/dead pixels repaired"
    return FrameDetections(
        centre_px=centre, centre_corrected_px=corrected, centre_cov_px2=cov, semi_axes_px=axes,
        angle_rad=ang, n_edge_points=npts, fit_rms_px=rms, min_transmission=qmin, on_background_edge=on_edge,
        rejected=rejected, background=1.0, success=m > 0, message=message, nfev=int(n_fits),
        n_hot_pixels=n_hot, hot_pixels_px=hot,
        on_corner=np.array([a[0] in corner for a in accepted], dtype=bool),
        two_models=np.array([a[0] in checked for a in accepted], dtype=bool))


# --------------------------------------------------------------------------- baselines

def baseline_detect(image, *, method: str = "contour_ellipse", encoding: str = "mono16",
                    flat_field_counts=None, min_area_px: float = 20.0, level: float = 0.5):
    """The obvious alternative pipelines, for comparison only (no rejection logic).

    Parameters
    ----------
    image : array_like of shape (rows, cols)
    method : {"contour_ellipse", "centroid"}
        ``contour_ellipse``: threshold at ``level`` of the shadow depth,
        ``connectedComponentsWithStats``, outer contour of each component
        (``findContours``), ``cv2.fitEllipse``. ``centroid``: intensity
        (1 - T / b) weighted centroid over each component's bounding box
        grown by 3 px.
    encoding, flat_field_counts : see :func:`detect_spheres`.
    min_area_px : float
        Components smaller than this are ignored.
    level : float
        Threshold as a fraction of the shadow depth from the background for
        ``contour_ellipse`` (the threshold is ``b (1 - level * 0.6)``, 0.6
        being a typical steel-sphere depth) and the segmentation for
        ``centroid`` (``b (1 - 0.1)``).

    Returns
    -------
    ndarray of shape (M, 2)
        Centres (col, row) [px].
    """
    trans = to_transmission(image, encoding, flat_field_counts)
    rows, cols = trans.shape
    bg = float(np.median(trans[::8, ::8]))
    if method == "contour_ellipse":
        thr = bg * (1.0 - level * 0.6)
    elif method == "centroid":
        thr = bg * 0.9
    else:
        raise ValueError(f"unknown method {method!r}")
    mask = (trans < np.float32(thr)).view(np.uint8)
    n, labels, stats, cents = cv2.connectedComponentsWithStats(mask, connectivity=8)
    out = []
    for i in range(1, n):
        x0, y0, w, h, a = (int(v) for v in stats[i])
        if a < min_area_px:
            continue
        if method == "contour_ellipse":
            roi = (labels[y0:y0 + h, x0:x0 + w] == i).astype(np.uint8)
            contours, _ = cv2.findContours(roi, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            cnt = max(contours, key=len)
            if len(cnt) < 5:
                continue
            (cx, cy), _, _ = cv2.fitEllipse(cnt)
            out.append((cx + x0, cy + y0))
        else:
            xa, ya = max(0, x0 - 3), max(0, y0 - 3)
            xb, yb = min(cols, x0 + w + 3), min(rows, y0 + h + 3)
            wgt = np.clip(1.0 - trans[ya:yb, xa:xb].astype(np.float64) / bg, 0.0, None)
            s = wgt.sum()
            gy, gx = np.mgrid[ya:yb, xa:xb]
            out.append(((wgt * gx).sum() / s, (wgt * gy).sum() / s))
    return np.array(out, dtype=np.float64).reshape(-1, 2)
