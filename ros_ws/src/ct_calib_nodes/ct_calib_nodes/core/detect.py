"""Sub-pixel detection of sphere shadows in CT projections.

One pure function, :func:`detect_spheres`, turns one projection (``mono16``
counts or ``32FC1`` transmission, see INTERFACES.md) into the ellipse centres
of every sphere shadow it can measure, plus the list of candidates it refused
and why. It keeps no state, so a bad frame raises :class:`FrameError` for that
frame only and the rest of a run is unaffected.

Pipeline (numbers are the defaults of :class:`DetectionSettings`)
------------------------------------------------------------------
1. Frame checks and conversion to transmission ``T = I / I0`` (float32; the
   photon noise of a 50000-count frame is 4.5e-3 in T, far above float32
   resolution). Bad frames -> :class:`FrameError` with a ``reason``.
2. Background: the frame is divided by a vertical morphological closing of
   itself (see ``DetectionSettings.vertical_background``), which keeps the
   carbon-fibre tube's dark tangential bands and removes the spheres, so the
   normalised open-beam level is b ~ 1. Segmentation: pixels with
   ``T < b * (1 - 0.10)`` are shadow. At 50000 counts the noise is
   about 0.0045 b, so the threshold sits ~22 sigma below the background and
   noise never makes a blob. 8-connected components with OpenCV.
3. Candidate screening, each refusal recorded with a reason code:
   ``edge_cut`` (shadow or its measuring annulus leaves the image),
   ``not_a_sphere_size`` (far smaller than the expected diameter, or larger
   than three merged spheres: tube wall, dirt), ``not_a_sphere_contrast``
   (too shallow), ``overlap`` (blob too large for one sphere, too elongated,
   not elliptical, darker than one sphere can be, or a neighbour so close that
   the shadows' penumbrae touch), ``fit_failed``, ``background_structure``
   (the tube's end rim meets a wall band across the shadow). Overlaps are
   rejected, never split (the paper's automated overlap rejection). Shadows
   straddling the end rim get a repaired background; shadows on a wall-band
   edge are flagged and carry extra column uncertainty (settings).
4. Sub-pixel edges: ``n_rays`` radial profiles from the blob centre, sampled
   by exact (float64 weight) bilinear interpolation, normalised by a local
   planar background fitted on the outer ring (so flat-field gradients do not
   shift the edge), and cut at the iso-level ``1 - 0.5 (1 - q_in)`` half way
   between the local background and the inner shadow. Every iso-transmission
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
6. Centre uncertainty: ``f sigma_edge^2 (sum_i n_i n_i^T)^-1`` with ``n_i`` the
   edge normals, ``sigma_edge`` the fit RMS (degrees-of-freedom corrected) and
   ``f = max(1, n / (pi r))`` for the correlation of neighbouring rays, which
   sample shared pixels. It covers the photon noise only; the measured spread
   on rendered frames is still ~1.3x larger (doc/ct_detect.md).
7. Optional Deng / Clackdoyle correction from the ellipse centre to the
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

from dataclasses import dataclass

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
    border_margin_px : float
        Shadows whose measuring annulus comes closer than this to the image
        border are ``edge_cut``.
    vertical_background : bool
        Divide the frame by its background estimated with a vertical
        morphological closing (1x3 vertical box blur, then a 1 x L line), which removes
        every dark feature shorter than L rows (the spheres) and keeps features
        that are long along the rotation axis: the carbon-fibre tube, whose
        tangential walls cast dark bands (T ~ 0.7) right where the spheres at
        the sides of the object project. Without it about half of helix49's
        spheres merge with the tube bands. Assumes the object is roughly
        upright (tube axis within a few degrees of the image columns).
    background_window_px : int or None
        L; None: ``2 * max diameter + 9`` px (61 px without a diameter range).
    repair_horizontal_steps : bool
        With ``vertical_background``: where a roughly horizontal background
        step (the tube's end rim) crosses a shadow, replace the closing's
        background under it by a horizontal interpolation (the closing puts
        the step at the shadow's border: row bias up to 0.1 px without this).
    background_edge_gradient, background_edge_min_fraction, background_edge_sigma_px : float
        A shadow more than ``min_fraction`` of whose edge points lie where the
        background changes by more than ``gradient`` (relative) over 4 columns
        (a tube-wall band edge) gets ``sigma_px`` added in quadrature to its
        column uncertainty [px]. The inner edge of a wall band is a sub-pixel
        cusp; averaging the product of shadow and band over a pixel (and the
        detector blur) mixes them, which no division by a background undoes.
        Calibrated on 1989 rendered detections (helix49 + tube, k = 1 and the
        last position, seeds 5, 6, 11, 12): column rms 0.0143 px on the 537
        flagged shadows (reported 0.0064) vs 0.0059 px on the others; 0.012 px
        makes the mean squared column z-score 1. 0 disables.
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
    vertical_background: bool = True
    background_window_px: int | None = None
    repair_horizontal_steps: bool = True
    background_edge_gradient: float = 0.04
    background_edge_min_fraction: float = 0.05
    background_edge_sigma_px: float = 0.012

    def __post_init__(self):
        if self.ellipse_fitter not in ("fitEllipse", "fitEllipseAMS", "fitEllipseDirect", "geometric"):
            raise ValueError(f"unknown ellipse_fitter {self.ellipse_fitter!r}")
        if not 0.0 < self.segment_depth < 1.0:
            raise ValueError("segment_depth must be in (0, 1)")
        if not 0.0 < self.edge_level < 1.0:
            raise ValueError("edge_level must be in (0, 1)")
        if int(self.n_rays) < 8 or int(self.n_samples) < 8:
            raise ValueError("n_rays and n_samples must be >= 8")
        if not (self.background_edge_gradient > 0 and 0 <= self.background_edge_min_fraction < 1
                and self.background_edge_sigma_px >= 0):
            raise ValueError("background_edge_gradient must be > 0, background_edge_min_fraction in [0, 1) "
                             "and background_edge_sigma_px >= 0")
        if int(self.n_passes) < 1:
            raise ValueError("n_passes must be >= 1")


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
        The shadow's edge crosses a strong vertical background edge (a tube
        wall band); its column variance includes ``background_edge_sigma_px``.
    rejected : RejectedCandidates
    background : float
        Open-beam transmission level of the frame.
    success : bool
        False only if not a single sphere was accepted.
    message : str
    nfev : int
        Number of ellipse fits performed.
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

def to_transmission(image, encoding: str = "mono16", flat_field_counts=None,
                    expected_shape=None, _convert: bool = True) -> np.ndarray | None:
    """Check one frame and convert it to transmission.

    Parameters
    ----------
    image : array_like of shape (rows, cols)
        ``mono16``: unsigned 16-bit counts. ``32FC1``: transmission I/I0 (any
        float dtype).
    encoding : {"mono16", "32FC1"}
    flat_field_counts : float or ndarray of shape (rows, cols), optional
        Open-beam counts (``mono16`` only). None: the frame's own median.
    expected_shape : tuple (rows, cols), optional
        From ct_instrument.yaml; a mismatch is a ``wrong_size`` FrameError.

    Returns
    -------
    ndarray of shape (rows, cols), float32

    Raises
    ------
    FrameError
        Wrong dtype/encoding/size, NaN/inf, all dark, saturated, uniform.
    """
    if encoding not in ("mono16", "32FC1"):
        raise FrameError("wrong_encoding", f"encoding must be 'mono16' or '32FC1', got {encoding!r}")
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
    if encoding == "mono16":
        if img.dtype != np.uint16:
            raise FrameError("wrong_dtype", f"mono16 frames must be uint16, got {img.dtype}")
        if np.count_nonzero(sub == 65535) > 0.5 * sub.size:
            raise FrameError("saturated", "more than half of the pixels are at 65535 counts")
        if flat_field_counts is None or (not _convert and np.ndim(flat_field_counts) == 0):
            if flat_field_counts is None:
                i0 = float(np.median(sub))
                if i0 <= 0.0:
                    raise FrameError("all_dark", "median count is 0 and no flat field was given")
            else:
                i0 = float(flat_field_counts)
                if not (np.isfinite(i0) and i0 > 0):
                    raise FrameError("bad_flat_field", f"flat_field_counts must be > 0, got {i0}")
            if not _convert:
                med = float(np.median(sub)) / i0
                if med < 0.02:
                    raise FrameError("all_dark", f"median transmission {med:.3g} < 0.02 (beam off or shutter closed)")
                if int(sub.max()) == int(sub.min()) and int(img.max()) == int(img.min()):
                    raise FrameError("uniform", f"every pixel has the same value {int(img.flat[0])} "
                                                "(no signal, no noise)")
                return None
            trans = img.astype(np.float32) * np.float32(1.0 / i0)
        else:
            ff = np.asarray(flat_field_counts, dtype=np.float64)
            if ff.ndim == 0:
                if not (np.isfinite(ff) and ff > 0):
                    raise FrameError("bad_flat_field", f"flat_field_counts must be > 0, got {ff}")
                trans = img.astype(np.float32) * np.float32(1.0 / float(ff))
            else:
                if ff.shape != img.shape or not np.all(np.isfinite(ff)) or np.any(ff <= 0):
                    raise FrameError("bad_flat_field", "flat field must be a positive scalar or a finite "
                                                       f"positive array of shape {img.shape}")
                trans = (img.astype(np.float32) / ff.astype(np.float32))
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


# --------------------------------------------------------------------------- helpers

def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Exact bilinear interpolation (float64 weights), points assumed inside."""
    rows, cols = img.shape
    x0 = np.floor(x).astype(np.intp)
    y0 = np.floor(y).astype(np.intp)
    np.clip(x0, 0, cols - 2, out=x0)
    np.clip(y0, 0, rows - 2, out=y0)
    fx = x - x0
    fy = y - y0
    flat = img.ravel()
    i00 = y0 * cols + x0
    v00 = flat[i00]
    v01 = flat[i00 + 1]
    v10 = flat[i00 + cols]
    v11 = flat[i00 + cols + 1]
    top = v00 + fx * (v01 - v00)
    bot = v10 + fx * (v11 - v10)
    return top + fy * (bot - top)


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
    """Approximate orthogonal distances of points (N, 2) from ellipse p and outward normals."""
    cx, cy, a, b, ang = p
    c, s = np.cos(ang), np.sin(ang)
    dx, dy = points[:, 0] - cx, points[:, 1] - cy
    xp = c * dx + s * dy
    yp = -s * dx + c * dy
    # gradient of F = (x/a)^2 + (y/b)^2 - 1; Sampson distance F / |grad F|
    f = (xp / a) ** 2 + (yp / b) ** 2 - 1.0
    gx, gy = 2 * xp / a ** 2, 2 * yp / b ** 2
    gn = np.hypot(gx, gy)
    gn = np.where(gn > 0, gn, 1.0)
    d = f / gn
    # outward normal in image coordinates
    nx = (c * gx - s * gy) / gn
    ny = (s * gx + c * gy) / gn
    return d, nx, ny


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
                   sdd_px: float | None = None, principal_point_px=None) -> FrameDetections:
    """Find and measure every sphere shadow in one projection.

    Parameters
    ----------
    image : array_like of shape (rows, cols)
        ``mono16`` uint16 counts or ``32FC1`` transmission.
    encoding : {"mono16", "32FC1"}
    flat_field_counts : float or ndarray of shape (rows, cols), optional
        Open-beam counts for ``mono16`` (ct_instrument.yaml).
    expected_shape : tuple (rows, cols), optional
        Detector size from ct_instrument.yaml.
    diameter_px_range : tuple (min, max), optional
        Expected shadow diameters [px] from the nominal geometry (sphere
        diameter x magnification range / pixel pitch). Without it only shape
        and contrast screen the blobs.
    settings : DetectionSettings, optional
    sdd_px : float, optional
        Nominal source-to-detector distance in pixels; enables
        ``centre_corrected_px``.
    principal_point_px : array_like of shape (2,), optional
        Defaults to the detector centre ((cols-1)/2, (rows-1)/2).

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
    fast16 = (st.vertical_background and encoding == "mono16"
              and (flat_field_counts is None or np.ndim(flat_field_counts) == 0))
    trans = to_transmission(image, encoding, flat_field_counts, expected_shape, _convert=not fast16)
    rows, cols = np.asarray(image).shape
    bg = float(np.median(trans[::8, ::8])) if trans is not None else 1.0
    if st.vertical_background:
        if st.background_window_px is not None:
            win = int(st.background_window_px)
        elif drange is not None:
            win = int(2.0 * drange[1] * (1.0 + st.size_tolerance)) + 9
        else:
            win = 61
        win += 1 - win % 2
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (1, win))
        # morphology on 16-bit integers is ~2x faster than on float32 in OpenCV
        raw = np.asarray(image)
        if fast16:
            bg16 = cv2.morphologyEx(cv2.blur(raw, (1, 3)), cv2.MORPH_CLOSE, kernel)
            np.maximum(bg16, 1, out=bg16)
            trans = cv2.divide(raw, bg16, dtype=cv2.CV_32F)
        else:
            u16 = (np.minimum(trans, np.float32(3.99)) * np.float32(16384.0)).astype(np.uint16)
            bg16 = cv2.morphologyEx(cv2.blur(u16, (1, 3)), cv2.MORPH_CLOSE, kernel)
            np.maximum(bg16, 1, out=bg16)
            trans = cv2.divide(trans, bg16.astype(np.float32), scale=16384.0, dtype=cv2.CV_32F)
        bg = 1.0
    thr = np.float32(bg * (1.0 - st.segment_depth))
    mask = (trans < thr).view(np.uint8)
    n_lab, labels, stats, cents = cv2.connectedComponentsWithStats(mask, connectivity=8)
    stats = stats[1:]
    cents = cents[1:].astype(np.float64)

    rej_c, rej_a, rej_r, rej_d = [], [], [], []

    def reject(i, reason, detail):
        rej_c.append(cents[i])
        rej_a.append(float(stats[i, cv2.CC_STAT_AREA]))
        rej_r.append(reason)
        rej_d.append(detail)

    area = stats[:, cv2.CC_STAT_AREA].astype(np.float64)
    d_eq = 2.0 * np.sqrt(area / np.pi)
    if drange is not None:
        dmin = drange[0] * (1.0 - st.size_tolerance)
        dmax = drange[1] * (1.0 + st.size_tolerance)
    else:
        dmin, dmax = 4.0, np.inf
    single_area_max = np.pi * dmax ** 2 / 4.0

    # --- cheap screening on component statistics
    cand = []
    for i in range(stats.shape[0]):
        x0, y0, w, h = (int(v) for v in stats[i, :4])
        if d_eq[i] < dmin:
            reject(i, "not_a_sphere_size", f"diameter {d_eq[i]:.1f} px < {dmin:.1f} px")
            continue
        if d_eq[i] > dmax:
            if area[i] <= 3.5 * single_area_max:
                reject(i, "overlap", f"blob area {area[i]:.0f} px^2 exceeds one sphere "
                                     f"({single_area_max:.0f} px^2): merged shadows")
            else:
                reject(i, "not_a_sphere_size", f"blob area {area[i]:.0f} px^2 is larger than three spheres")
            continue
        r0 = 0.5 * d_eq[i]
        reach = r0 + max(0.5 * r0, 4.0) + st.border_margin_px + 1.0
        cx, cy = cents[i]
        touches = x0 <= 0 or y0 <= 0 or x0 + w >= cols or y0 + h >= rows
        if touches or cx - reach < 0 or cy - reach < 0 or cx + reach > cols - 1 or cy + reach > rows - 1:
            reject(i, "edge_cut", "shadow touches the image border" if touches
                   else "measuring annulus leaves the image")
            continue
        aspect = max(w, h) / max(1, min(w, h))
        if aspect > 1.6 * st.max_axis_ratio:
            reject(i, "overlap", f"blob bounding box aspect {aspect:.2f}: merged shadows")
            continue
        # second moments of the blob: axis ratio and filling of its moment ellipse
        mom = cv2.moments((labels[y0:y0 + h, x0:x0 + w] == i + 1).view(np.uint8), binaryImage=True)
        mu20, mu02, mu11 = mom["mu20"] / mom["m00"], mom["mu02"] / mom["m00"], mom["mu11"] / mom["m00"]
        tr_, dd_ = mu20 + mu02, np.sqrt(max((mu20 - mu02) ** 2 + 4 * mu11 ** 2, 0.0))
        l1, l2 = 0.5 * (tr_ + dd_), 0.5 * (tr_ - dd_)
        m_ratio = np.sqrt(l1 / l2) if l2 > 0 else np.inf
        if m_ratio > st.max_axis_ratio:
            reject(i, "overlap", f"blob moment axis ratio {m_ratio:.2f} > {st.max_axis_ratio}: merged shadows")
            continue
        cand.append(i)

    # --- proximity: penumbrae of neighbours interact. Compared against every
    # blob of noticeable size, including rejected ones (a merged pair or the
    # tube's band still casts its shadow), by the distance to its bounding box.
    if cand:
        others = np.nonzero(d_eq >= max(3.0, 0.5 * dmin))[0]
        x0b = stats[others, 0].astype(np.float64) - 0.5
        y0b = stats[others, 1].astype(np.float64) - 0.5
        x1b = x0b + stats[others, 2]
        y1b = y0b + stats[others, 3]
        wb, hb = stats[others, 2], stats[others, 3]
        roundish = (d_eq[others] <= dmax) & (np.maximum(wb, hb) <= 1.3 * np.minimum(wb, hb))
        keep = []
        for i in cand:
            cx, cy = cents[i]
            gx = np.maximum(np.maximum(x0b - cx, cx - x1b), 0.0)
            gy = np.maximum(np.maximum(y0b - cy, cy - y1b), 0.0)
            gap = np.hypot(gx, gy) - 0.5 * d_eq[i]
            # round single-sphere blobs: centre distance minus both radii
            gap = np.where(roundish, np.hypot(cents[others, 0] - cx, cents[others, 1] - cy)
                           - 0.5 * d_eq[i] - 0.5 * d_eq[others], gap)
            gap[others == i] = np.inf
            k = int(np.argmin(gap))
            if gap[k] < st.proximity_margin_px:
                reject(i, "overlap", f"gap {max(gap[k], 0.0):.1f} px to a neighbouring shadow "
                                     f"< {st.proximity_margin_px:.1f} px")
            else:
                keep.append(i)
        cand = keep

    if st.vertical_background and st.repair_horizontal_steps and cand:
        corners = _repair_horizontal_steps(trans, bg16, stats, cand, rows, cols)
        for i in corners:
            reject(i, "background_structure", "a horizontal background step (tube end rim) meets a stronger "
                                              "vertical one (wall band) across the shadow: no background fits")
        dropped = set(corners)
        cand = [i for i in cand if i not in dropped]

    n_fits = 0
    if not cand:
        return _assemble([], rej_c, rej_a, rej_r, rej_d, bg, n_fits, sdd_px, principal_point_px, trans.shape,
                         "no sphere shadow accepted")

    # --- sub-pixel edges along rays (vectorised over candidates)
    cand = np.array(cand)
    nc = len(cand)
    centre = cents[cand].copy()
    radius = 0.5 * d_eq[cand]
    ok = np.ones(nc, bool)
    fits = np.full((nc, 5), np.nan)
    n_pts = np.zeros(nc, int)
    rms = np.full(nc, np.nan)
    cov = np.full((nc, 2, 2), np.nan)
    why = [""] * nc
    level = None
    edge_frac = np.zeros(nc)
    for pas in range(int(st.n_passes)):
        first = pas == 0
        # pass 1: coarse rays over the whole edge zone, also measures the local
        # background plane and the iso-level; later passes: full ray count on a
        # narrow band round the previous fit, re-using background and level.
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
        r_s = (radius - w_in)[:, None] + (w_in + w_out)[:, None] * t[None, :]           # (C, S)
        dxs = cphi[None, :, None] * r_s[:, None, :]                                      # (C, R, S)
        dys = sphi[None, :, None] * r_s[:, None, :]
        prof = _bilinear(trans, centre[:, 0, None, None] + dxs, centre[:, 1, None, None] + dys)
        if first:
            # local planar background from the outer 20 % of each profile
            n_out = max(3, ns // 5)
            ob = prof[:, :, -n_out:]
            oxs = dxs[:, :, -n_out:]
            oys = dys[:, :, -n_out:]
            b0 = np.median(ob.reshape(nc, -1), axis=1)
            # ring samples darkened by a neighbour's tail do not enter the plane
            wr = (ob > b0[:, None, None] * (1.0 - 0.5 * st.segment_depth)).astype(np.float64)
            res0 = (ob - b0[:, None, None]) * wr
            bx = np.sum(res0 * oxs, axis=(1, 2)) / np.maximum(np.sum(wr * oxs ** 2, axis=(1, 2)), 1e-9)
            by = np.sum(res0 * oys, axis=(1, 2)) / np.maximum(np.sum(wr * oys ** 2, axis=(1, 2)), 1e-9)
            bg_origin = centre.copy()
        offx = centre[:, 0] - bg_origin[:, 0]
        offy = centre[:, 1] - bg_origin[:, 1]
        bgl = ((b0 + bx * offx + by * offy)[:, None, None] + bx[:, None, None] * dxs
               + by[:, None, None] * dys)
        q = prof / bgl
        if first:
            n_in = max(2, ns // 10)
            q_in = np.median(q[:, :, :n_in].reshape(nc, -1), axis=1)
            qmin = np.minimum(np.min(q[:, :, :n_in], axis=(1, 2)), q_in)
            level = 1.0 - st.edge_level * (1.0 - q_in)
        below = q < level[:, None, None]
        # outermost sample below the level, crossing to the next one outward
        last = ns - 1 - np.argmax(below[:, :, ::-1], axis=2)
        valid = below.any(axis=2) & (last < ns - 1) & (last > 0)
        k = np.clip(last, 0, ns - 2)
        q0 = np.take_along_axis(q, k[..., None], axis=2)[..., 0]
        q1 = np.take_along_axis(q, (k + 1)[..., None], axis=2)[..., 0]
        dq = q1 - q0
        valid &= dq > 0
        frac = np.where(valid, (level[:, None] - q0) / np.where(dq > 0, dq, 1.0), 0.0)
        dr = (w_in + w_out) / (ns - 1)
        r_edge = r_s[np.arange(nc)[:, None], k] + frac * dr[:, None]
        ex = centre[:, 0, None] + cphi[None, :] * r_edge
        ey = centre[:, 1, None] + sphi[None, :] * r_edge
        if st.vertical_background and pas == int(st.n_passes) - 1:
            # edge points where the background itself changes fast across columns (a tube-wall
            # band edge): pixel averaging and blur mix shadow and band multiplicatively, which
            # dividing by the background cannot undo, so those centres carry extra column variance
            xi = np.clip(np.rint(ex).astype(np.intp), 2, cols - 3)
            yi = np.clip(np.rint(ey).astype(np.intp), 0, rows - 1)
            gb = np.abs(bg16[yi, xi + 2].astype(np.float32) - bg16[yi, xi - 2].astype(np.float32))
            strong = valid & (gb > st.background_edge_gradient * np.maximum(bg16[yi, xi].astype(np.float32), 1.0))
            edge_frac = np.count_nonzero(strong, axis=1) / np.maximum(np.count_nonzero(valid, axis=1), 1)
        for c in range(nc):
            if not ok[c]:
                continue
            v = valid[c]
            if np.count_nonzero(v) < st.min_edge_fraction * nr:
                ok[c] = False
                why[c] = f"only {np.count_nonzero(v)} of {nr} rays found an edge"
                continue
            pts = np.stack([ex[c, v], ey[c, v]], axis=1)
            last_pass = pas == int(st.n_passes) - 1
            try:
                p = _fit_one(pts, st.ellipse_fitter)
                n_fits += 1
                if not last_pass:       # intermediate passes only re-centre the rays
                    if np.all(np.isfinite(p)) and p[3] > 0:
                        fits[c] = p
                    else:
                        ok[c] = False
                        why[c] = "ellipse fit returned a degenerate ellipse"
                    continue
                d, nx, ny = _ellipse_residuals(pts, p)
                # one round of outlier removal (5 x robust sigma, at least 0.1 px)
                sig = 1.2533 * np.mean(np.abs(d))
                good = np.abs(d) <= max(5.0 * sig, 0.1)
                if not good.all() and np.count_nonzero(good) >= st.min_edge_fraction * nr:
                    pts = pts[good]
                    p = _fit_one(pts, st.ellipse_fitter)
                    n_fits += 1
                    d, nx, ny = _ellipse_residuals(pts, p)
            except cv2.error as exc:
                ok[c] = False
                why[c] = f"ellipse fit failed: {exc}"
                continue
            if not np.all(np.isfinite(p)) or p[3] <= 0:
                ok[c] = False
                why[c] = "ellipse fit returned a degenerate ellipse"
                continue
            fits[c] = p
            n_pts[c] = len(pts)
            dof = max(1, len(pts) - 5)
            s2 = float(np.dot(d, d)) / dof
            rms[c] = np.sqrt(np.mean(d ** 2))
            sxx, sxy, syy = np.dot(nx, nx), np.dot(nx, ny), np.dot(ny, ny)
            det_ = sxx * syy - sxy * sxy
            # neighbouring rays share pixels: about one independent edge sample
            # per 2 px of perimeter (pi r), so inflate by n / (pi r) when larger
            infl = max(1.0, len(pts) / (np.pi * np.sqrt(p[2] * p[3])))
            cov[c] = (infl * s2 / det_) * np.array([[syy, -sxy], [-sxy, sxx]]) if det_ > 0 else np.nan
        centre = np.where(ok[:, None], fits[:, :2], centre)
        radius = np.where(ok, np.sqrt(np.abs(fits[:, 2] * fits[:, 3])), radius)

    # --- post-fit screening
    accepted = []
    depth_all = -np.log(np.clip(qmin, 1e-6, None))
    depth_ref = float(np.median(depth_all[ok])) if np.any(ok) else np.nan
    for c, i in enumerate(cand):
        if not ok[c]:
            reject(i, "fit_failed", why[c])
            continue
        p = fits[c]
        ratio = p[2] / p[3]
        contrast = 1.0 - qmin[c]
        if contrast < st.min_contrast:
            reject(i, "not_a_sphere_contrast", f"shadow depth {contrast:.3f} < {st.min_contrast}")
            continue
        if ratio > st.max_axis_ratio:
            reject(i, "overlap", f"axis ratio {ratio:.3f} > {st.max_axis_ratio}: elongated (merged) shadow")
            continue
        if rms[c] > st.max_fit_rms_px:
            reject(i, "not_a_sphere_shape", f"edge RMS {rms[c]:.3f} px > {st.max_fit_rms_px} px: not elliptical")
            continue
        if drange is not None:
            dfit = 2.0 * np.sqrt(p[2] * p[3])
            if not (dmin <= dfit <= dmax):
                reject(i, "not_a_sphere_size", f"fitted diameter {dfit:.1f} px outside [{dmin:.1f}, {dmax:.1f}]")
                continue
        if (st.overlap_darkness is not None and np.isfinite(depth_ref) and np.count_nonzero(ok) >= 3
                and depth_all[c] > st.overlap_darkness * depth_ref):
            reject(i, "overlap", f"shadow optical depth {depth_all[c]:.2f} > {st.overlap_darkness} x median "
                                 f"{depth_ref:.2f}: spheres in line")
            continue
        on_edge = bool(edge_frac[c] > st.background_edge_min_fraction)
        cv = cov[c].copy()
        if on_edge:
            cv[0, 0] += st.background_edge_sigma_px ** 2
        accepted.append((c, fits[c], n_pts[c], rms[c], cv, qmin[c], on_edge))
    return _assemble(accepted, rej_c, rej_a, rej_r, rej_d, bg, n_fits, sdd_px, principal_point_px,
                     trans.shape, "")


def _repair_horizontal_steps(trans, bg16, stats, cand, rows, cols, min_step=0.01):
    """Repair the vertical-closing background under shadows that straddle a horizontal step.

    The vertical closing fills each sphere shadow from above and below. When a roughly
    horizontal background step (the tube's end rim, ~2-3 %) crosses the shadow, it cannot know
    where inside the shadow the step lies and puts it at the shadow's border, so part of the
    shadow is normalised by the wrong level: a row bias of 0.04-0.10 px. Where the closing's
    background above and below a shadow differ by more than ``min_step`` (relative) AND by more
    than its left and right sides do (a vertical tube-band edge is the closing's own case), the
    background in the shadow's box is replaced by the row-by-row linear interpolation between
    the closing's values in the columns just left and right of the box (exact there: those
    columns do not cross the shadow) and that box of ``trans`` is renormalised, in place.
    Returns the candidates where a horizontal step meets a stronger vertical one (a corner of
    rim and band), for which no background model holds.
    """
    corners = []
    for i in cand:
        x0, y0, w, h = (int(v) for v in stats[i, :4])
        m = max(3, int(0.3 * max(w, h)) + 1)
        ya, yb = y0 - m, y0 + h + m
        xl, xr = x0 - m, x0 + w + m - 1
        if ya < 0 or xl < 0 or yb > rows or xr >= cols:
            continue
        above = float(np.mean(bg16[ya:y0, x0:x0 + w]))
        below = float(np.mean(bg16[y0 + h:yb, x0:x0 + w]))
        if abs(above - below) <= min_step * max(above, below, 1.0):
            continue
        old = bg16[ya:yb, xl:xr + 1].astype(np.float32)
        left, right = old[:, :1], old[:, -1:]
        if abs(float(left.mean()) - float(right.mean())) >= abs(above - below):
            # a step above/below AND a stronger one left/right: the corner of the end rim and a
            # wall band; neither the closing nor the interpolation holds (row errors ~0.1 px)
            corners.append(i)
            continue
        f = np.linspace(0.0, 1.0, xr - xl + 1, dtype=np.float32)[None, :]
        trans[ya:yb, xl:xr + 1] *= old / np.maximum(left + (right - left) * f, 1.0)
    return corners


def _assemble(accepted, rej_c, rej_a, rej_r, rej_d, bg, n_fits, sdd_px, pp, shape, message):
    m = len(accepted)
    if m:
        fits = np.array([a[1] for a in accepted])
        centre = fits[:, :2].copy()
        axes = fits[:, 2:4].copy()
        ang = np.mod(fits[:, 4], np.pi)
        npts = np.array([a[2] for a in accepted], dtype=int)
        rms = np.array([a[3] for a in accepted])
        cov = np.array([a[4] for a in accepted])
        qmin = np.array([a[5] for a in accepted])
        on_edge = np.array([a[6] for a in accepted], dtype=bool)
    else:
        centre = np.zeros((0, 2))
        axes = np.zeros((0, 2))
        ang = np.zeros(0)
        npts = np.zeros(0, int)
        rms = np.zeros(0)
        cov = np.zeros((0, 2, 2))
        qmin = np.zeros(0)
        on_edge = np.zeros(0, dtype=bool)
    corrected = None
    if sdd_px is not None:
        if pp is None:
            pp = ((shape[1] - 1) / 2.0, (shape[0] - 1) / 2.0)
        corrected = deng_correction(centre, axes, sdd_px, pp) if m else np.zeros((0, 2))
    rejected = RejectedCandidates(
        centre_px=np.array(rej_c, dtype=np.float64).reshape(-1, 2),
        area_px=np.array(rej_a, dtype=np.float64),
        reason=tuple(rej_r), detail=tuple(rej_d))
    if not message:
        counts = {r: rejected.count(r) for r in REJECT_REASONS if rejected.count(r)}
        message = f"{m} spheres accepted, {len(rejected)} rejected" + (f" {counts}" if counts else "")
    return FrameDetections(
        centre_px=centre, centre_corrected_px=corrected, centre_cov_px2=cov, semi_axes_px=axes,
        angle_rad=ang, n_edge_points=npts, fit_rms_px=rms, min_transmission=qmin, on_background_edge=on_edge,
        rejected=rejected,
        background=float(bg), success=m > 0, message=message, nfev=int(n_fits))


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
