"""Holders other than the carbon tube, non-uniform flat fields and 8-bit lossy frames.

Renderer options for testing the detector on frames like real X-ray images
(issue 14 item 3): reference spheres on an acrylic plate with its edges
through the field, a detector gain that is not uniform (anode heel effect,
vignetting of an image intensifier, a circular field stop) and 8-bit frames
that went through JPEG compression.

- :class:`PlateHolder`: a rectangular slab (e.g. PMMA) in the object frame
  {OF}; it turns with the object. Pass it to ``render.render_projection(...,
  holders=(plate,))``: its exact chord length enters every ray's line
  integral like the spheres' (sub-sampled with them near the spheres, and on
  the rest of the frame at ``tube_oversample`` with a 4x4 re-trace of every
  pixel next to a holder edge).
- :func:`plate_object`: spheres glued on one face of such a plate (a grid,
  some hanging over the plate's edge).
- :class:`FlatField`: a gain map ``g(col, row)`` (heel gradient, radial
  vignetting, circular field stop) and :func:`finish_frame`, which applies it
  to a noiseless rendered transmission, adds counting noise and encodes the
  frame as ``mono16``, ``mono8`` or 8-bit JPEG (decoded again, as a recorder
  that stored JPEG would hand it on).

A tube at any tilt needs no holder here: it is the default object (``helix49``
with its tube) turned about the beam by the static parameter rho_Z
(``w[12]``). That covers rendering and detection; the identity search of a
leaning object (tilted away from the rotation axis by more than about 2 deg)
is another matter: it is refused there rather than searched (ct_detect.md,
"Independent renderer check").

No solver or detector imports this module.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .phantom import ReferenceObject

# PMMA, mu/rho(100 keV) = 0.1654 cm^2/g (NIST XCOM, polymethyl methacrylate), density
# 1.19 g/cm^3 -> 0.197 /cm = 19.7 /m.
MU_PMMA_100KEV_PER_M = 19.7


@dataclass(frozen=True)
class PlateHolder:
    """A rectangular slab in {OF}.

    Attributes
    ----------
    centre_of_m : tuple of 3 floats
        Centre of the slab [m].
    normal_of : tuple of 3 floats
        Normal of its large faces (normalised here).
    edge_angle_rad : float
        Turn of the slab's edges about the normal [rad] (0: the first edge
        direction is the normal crossed with +Y of {OF}, or with +X if the
        normal is along Y).
    size_m : tuple of 2 floats
        Edge lengths [m] (first, second edge direction).
    thickness_m : float
    mu_per_m : float
        Linear attenuation [1/m]; default PMMA at ~100 keV.
    """

    centre_of_m: tuple = (0.0, 0.0, 0.0)
    normal_of: tuple = (0.0, 0.0, 1.0)
    edge_angle_rad: float = 0.0
    size_m: tuple = (0.09, 0.09)
    thickness_m: float = 0.005
    mu_per_m: float = MU_PMMA_100KEV_PER_M

    def __post_init__(self):
        n = np.asarray(self.normal_of, dtype=float)
        c = np.asarray(self.centre_of_m, dtype=float)
        s = np.asarray(self.size_m, dtype=float)
        if n.shape != (3,) or c.shape != (3,) or s.shape != (2,) or not (
                np.all(np.isfinite(n)) and np.all(np.isfinite(c)) and np.all(np.isfinite(s))):
            raise ValueError("centre_of_m and normal_of need 3 finite values, size_m 2")
        if np.linalg.norm(n) == 0 or np.any(s <= 0) or not self.thickness_m > 0 or not self.mu_per_m >= 0:
            raise ValueError("normal_of must be non-zero, size_m and thickness_m > 0, mu_per_m >= 0")
        object.__setattr__(self, "normal_of", tuple(n / np.linalg.norm(n)))

    def axes_of(self) -> np.ndarray:
        """(3, 3): rows = first edge direction, second edge direction, normal (unit, in {OF})."""
        n = np.asarray(self.normal_of)
        ref = np.array([0.0, 1.0, 0.0]) if abs(n[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
        e1 = np.cross(n, ref)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        c, s = np.cos(self.edge_angle_rad), np.sin(self.edge_angle_rad)
        return np.array([c * e1 + s * e2, -s * e1 + c * e2, n])

    def anchor_points_of(self) -> np.ndarray:
        """(4, 3): centre and centre + each unit axis, to be carried into {DF} by the renderer."""
        c = np.asarray(self.centre_of_m, dtype=float)
        return np.vstack([c, c + self.axes_of()])

    def placed(self, points_df: np.ndarray) -> "PlacedSlab":
        """The slab in {DF} from its four anchor points after the rigid placement."""
        c = points_df[0]
        axes = points_df[1:4] - c
        half = np.array([0.5 * self.size_m[0], 0.5 * self.size_m[1], 0.5 * self.thickness_m])
        return PlacedSlab(c, axes, half, float(self.mu_per_m))


@dataclass(frozen=True)
class PlacedSlab:
    """A slab in {DF}: centre (3,), unit axes (3, 3) as rows, half extents (3,), mu [1/m]."""

    centre: np.ndarray
    axes: np.ndarray
    half: np.ndarray
    mu: float

    def line_integral(self, source_df_m, x_m, y_m) -> np.ndarray:
        """mu x chord length [1] of the rays S -> (x, y, 0) through the slab."""
        s = np.asarray(source_df_m, dtype=float)
        gx = x_m - s[0]
        gy = y_m - s[1]
        gz = -s[2]
        lo = np.zeros(np.shape(gx))
        hi = np.ones(np.shape(gx))
        d = s - self.centre
        for k in range(3):
            e = self.axes[k]
            p = float(d @ e)
            q = e[0] * gx + e[1] * gy + e[2] * gz
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (-self.half[k] - p) / q
                t2 = (self.half[k] - p) / q
            par = np.abs(q) < 1e-15
            inside = abs(p) <= self.half[k]
            lo = np.maximum(lo, np.where(par, 0.0 if inside else np.inf, np.minimum(t1, t2)))
            hi = np.minimum(hi, np.where(par, 1.0 if inside else -np.inf, np.maximum(t1, t2)))
        return self.mu * np.maximum(hi - lo, 0.0) * np.sqrt(gx * gx + gy * gy + gz * gz)


def plate_object(n_side: int = 5, pitch_m: float = 0.016, diameter_m: float = 0.003,
                 plate: PlateHolder | None = None, overhang: bool = True) -> tuple[ReferenceObject, PlateHolder]:
    """Steel spheres glued on the +normal face of an acrylic plate, and the plate.

    An ``n_side`` x ``n_side`` grid at ``pitch_m`` centred on the plate; the plate
    (default 70 x 58 mm, 5 mm thick, normal along +Z of {OF}, edges turned by
    12 deg) is smaller than the grid's extent in one direction when ``overhang``,
    so the plate's edges run through the shadows of the outer spheres.

    Returns
    -------
    (ReferenceObject, PlateHolder)
    """
    if plate is None:
        plate = PlateHolder(size_m=(0.070, 0.058) if overhang else (0.09, 0.09), thickness_m=0.005,
                            edge_angle_rad=np.deg2rad(12.0))
    ax = plate.axes_of()
    g = (np.arange(n_side) - 0.5 * (n_side - 1)) * pitch_m
    u, v = np.meshgrid(g, g)
    lift = 0.5 * plate.thickness_m + 0.5 * diameter_m
    c = (np.asarray(plate.centre_of_m)[None, :] + u.reshape(-1, 1) * ax[0] + v.reshape(-1, 1) * ax[1]
         + lift * ax[2])
    # a slight irregularity so no two rows of shadows line up exactly
    c += 0.0007 * np.sin(np.arange(c.shape[0])[:, None] * np.array([1.3, 2.1, 0.0]))
    ref = ReferenceObject(name=f"plate{n_side * n_side}", ids=np.arange(1, c.shape[0] + 1), centres_of_m=c,
                          diameters_m=np.full(c.shape[0], diameter_m), material="steel", tube=None)
    return ref, plate


# --------------------------------------------------------------------------- renderer hook

def trace_background(line_integral, detector, k1: float, oversample: int, sample_points, effects=(),
                     source_df_m=None, refine_oversample: int = 4, jump: float = 1e-3):
    """Transmission of the holders (and tube) over the whole detector, for the renderer.

    Traced at ``oversample``; every pixel whose line integral differs from a
    4-neighbour's by more than ``jump`` (a holder edge) is traced again at
    ``refine_oversample`` so that edges are pixel-integrated, not aliased.

    Returns (trans (rows, cols) float32, number of rays).
    """
    os_ = int(oversample)
    xs, ys = sample_points(detector, 0, detector.cols - 1, 0, detector.rows - 1, os_, k1, effects, source_df_m)
    line = line_integral(xs, ys)
    if os_ > 1:
        line = line.reshape(detector.rows, os_, detector.cols, os_)
    n_rays = line.size
    trans = np.exp(-line)
    if os_ > 1:
        trans = trans.mean(axis=(1, 3))
        line = line.mean(axis=(1, 3))
    edge = np.zeros(line.shape, bool)
    dv = np.abs(np.diff(line, axis=0)) > jump
    dh = np.abs(np.diff(line, axis=1)) > jump
    edge[1:] |= dv
    edge[:-1] |= dv
    edge[:, 1:] |= dh
    edge[:, :-1] |= dh
    ro = int(refine_oversample)
    if ro > os_ and edge.any():
        r, c = np.nonzero(edge)
        sub = (np.arange(ro) + 0.5) / ro - 0.5
        cc = (c[:, None, None] + sub[None, None, :]) + np.zeros((1, ro, 1))
        rr = (r[:, None, None] + sub[None, :, None]) + np.zeros((1, 1, ro))
        x, y = detector.metric_from_pixels(cc, rr)
        if effects:   # the same landing points as render._sample_points
            from .render_effects import landing_from_recorded  # noqa: PLC0415
            xy = landing_from_recorded(effects, np.stack([x, y], axis=-1), source_df_m)
            x, y = xy[..., 0], xy[..., 1]
        if k1 != 0.0:
            from .render import undistort  # noqa: PLC0415
            xy = undistort(np.stack([x, y], axis=-1), k1)
            x, y = xy[..., 0], xy[..., 1]
        tt = np.exp(-line_integral(x, y)).mean(axis=(1, 2))
        trans[r, c] = tt
        n_rays += tt.size * ro * ro
    return trans.astype(np.float32), int(n_rays)


# --------------------------------------------------------------------------- flat fields and encodings

@dataclass(frozen=True)
class FlatField:
    """Detector gain g(col, row) relative to the mean open beam (multiplies I0).

    Attributes
    ----------
    heel : float
        Relative change of the gain across the frame along ``heel_angle_rad``
        (anode heel effect): g varies linearly by ``+-heel/2`` from edge to edge.
    heel_angle_rad : float
        Direction of the heel gradient in the image (0 = +col, pi/2 = +row).
    vignetting : float
        Relative loss at the frame's corner radius: ``1 - v (rho / rho_corner)^2``
        (image-intensifier vignetting), about ``vignetting_centre_px``.
    vignetting_centre_px : tuple or None
        Centre of the vignetting and the field stop (col, row); None = frame centre.
    field_stop_radius_px : float or None
        Radius of a circular field stop; outside it the gain is ``field_stop_level``.
    field_stop_edge_px : float
        Width (sigma) of the stop's blurred edge [px].
    field_stop_level : float
    """

    heel: float = 0.0
    heel_angle_rad: float = 0.0
    vignetting: float = 0.0
    vignetting_centre_px: tuple | None = None
    field_stop_radius_px: float | None = None
    field_stop_edge_px: float = 2.0
    field_stop_level: float = 0.03

    def gain(self, rows: int, cols: int) -> np.ndarray:
        """(rows, cols) float32 gain map."""
        r, c = np.mgrid[0:rows, 0:cols].astype(np.float64)
        g = np.ones((rows, cols))
        if self.heel:
            u = ((c - 0.5 * (cols - 1)) * np.cos(self.heel_angle_rad)
                 + (r - 0.5 * (rows - 1)) * np.sin(self.heel_angle_rad))
            g *= 1.0 + self.heel * u / max(cols, rows)
        cc, rc = (0.5 * (cols - 1), 0.5 * (rows - 1)) if self.vignetting_centre_px is None \
            else self.vignetting_centre_px
        rho = np.hypot(c - cc, r - rc)
        if self.vignetting:
            g *= 1.0 - self.vignetting * (rho / np.hypot(0.5 * cols, 0.5 * rows)) ** 2
        if self.field_stop_radius_px is not None:
            from scipy.special import ndtr  # noqa: PLC0415
            inside = ndtr((self.field_stop_radius_px - rho) / max(self.field_stop_edge_px, 1e-6))
            g *= self.field_stop_level + (1.0 - self.field_stop_level) * inside
        return g.astype(np.float32)


def finish_frame(trans, *, i0: float = 50000.0, flat: FlatField | None = None,
                 rng: np.random.Generator | None = None, output: str = "mono16",
                 gray_open: float = 220.0, jpeg_quality: int = 90) -> np.ndarray:
    """Gain map, counting noise and encoding of a noiseless (blurred) transmission image.

    Parameters
    ----------
    trans : ndarray (rows, cols)
        Rendered with ``RenderSettings(poisson=False)``, ``output="transmission"``.
    i0 : float
        Open-beam quanta per pixel (the noise level); mono16 counts are quanta.
    flat : FlatField, optional
    rng : numpy Generator (None: no noise)
    output : {"mono16", "mono8", "jpeg8"}
        ``mono8``: quanta scaled so the mean open beam is ``gray_open`` grey levels,
        rounded and clipped to 0..255. ``jpeg8``: the same, JPEG-encoded at
        ``jpeg_quality`` with OpenCV and decoded again.

    Returns
    -------
    ndarray (rows, cols): uint16 (mono16) or uint8.
    """
    from .render import _counting_noise  # noqa: PLC0415

    t = np.asarray(trans, dtype=np.float32)
    lam = t * np.float32(i0)
    if flat is not None:
        lam = lam * flat.gain(*t.shape)
    q = _counting_noise(lam, rng, 1000.0) if rng is not None else lam.astype(np.float64)
    if output == "mono16":
        return np.clip(np.rint(q), 0, 65535).astype(np.uint16)
    if output not in ("mono8", "jpeg8"):
        raise ValueError(f"output must be mono16, mono8 or jpeg8, got {output!r}")
    g8 = np.clip(np.rint(q * (gray_open / i0)), 0, 255).astype(np.uint8)
    if output == "mono8":
        return g8
    ok, buf = cv2.imencode(".jpg", g8, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
