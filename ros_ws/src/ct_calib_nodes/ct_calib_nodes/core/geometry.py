"""Forward projection model of a cone-beam CT (Ferrucci et al. 2020).

This module is the single definition of the geometry that the renderer, the
solvers, the exporters and the tests share. It is value-only (no Jacobians);
the solvers build their derivatives on top of it and are tested against it.

Frames (see ../shared/INTERFACES.md and the paper, section 2):

{SRF}  source / rotation-axis frame. Origin at the focal spot, +Y along the
       rotation axis (up), +Z from the focal spot through the rotation axis,
       which it meets orthogonally at R = (0, 0, z_R). +X = Y x Z.
{DF}   detector frame. Origin at the detector's geometric centre, +X along
       the detector rows (image columns grow along +X), +Y along the
       detector columns (image rows grow along -Y), +Z the detector normal
       pointing away from the source.
{OF}   object frame of the reference object (sphere centres from the CMM).

Image coordinates follow OpenCV: pixel (col c, row r) is centred at (c, r);
the detector's geometric centre is ((cols - 1) / 2, (rows - 1) / 2).

Static parameters w (13, eq. 3), in this order:
    z_R, x_D, y_D, z_D  [m]     stage position on Z, detector centre in {SRF}
    theta, phi, eta     [rad]   detector angles, R_det = Rz(eta) Ry(phi) Rx(theta)
    x_P, y_P, z_P       [m]     {OF} origin in {SRF} at alpha = 0 (eq. 1)
    rho_X, rho_Y, rho_Z [rad]   {OF} orientation, R_obj = Ry(rho_Y) Rz(rho_Z) Rx(rho_X)

Error motions of stage position k (6, eqs 8-11), in {DF}:
    dx_R, dy_R, dz_R          [m]    displacement of the stage point R_k - R_1
    gamma_X, gamma_Y, gamma_Z [rad]  axis rotation, Rx(gX) Ry(gY) Rz(gZ)

Note on eq. 10: the extracted text reads T(R_k) Rot(gamma) T(-R_k) applied to
the k = 1 sphere centres, which would leave the object behind when the stage
moves. The physically consistent reading, used here, carries the object with
the stage and turns it about the new stage point:
    C_{i,1,k} = R_k + Rot(gamma_k) (C_{i,1,1} - R_1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STATIC_PARAM_NAMES = (
    "z_R", "x_D", "y_D", "z_D", "theta", "phi", "eta",
    "x_P", "y_P", "z_P", "rho_X", "rho_Y", "rho_Z",
)
STATIC_PARAM_UNITS = ("m",) * 4 + ("rad",) * 3 + ("m",) * 3 + ("rad",) * 3
MOTION_PARAM_NAMES = ("dx_R", "dy_R", "dz_R", "gamma_X", "gamma_Y", "gamma_Z")
MOTION_PARAM_UNITS = ("m",) * 3 + ("rad",) * 3


@dataclass(frozen=True)
class DetectorSpec:
    """Pixel grid of a flat-panel detector.

    Attributes
    ----------
    cols, rows : int
        Image width and height in pixels.
    pixel_pitch_m : float
        Side of a square pixel [m].
    """

    cols: int
    rows: int
    pixel_pitch_m: float

    def __post_init__(self):
        if int(self.cols) <= 0 or int(self.rows) <= 0:
            raise ValueError(f"detector size must be positive, got {self.cols}x{self.rows}")
        if not (np.isfinite(self.pixel_pitch_m) and self.pixel_pitch_m > 0):
            raise ValueError(f"pixel_pitch_m must be positive, got {self.pixel_pitch_m}")

    @property
    def centre_px(self) -> tuple[float, float]:
        """Geometric centre (col, row) of the detector in pixels."""
        return (self.cols - 1) / 2.0, (self.rows - 1) / 2.0

    def pixels_from_metric(self, u_m, v_m):
        """Detector-plane coordinates (u along +X_DF, v along +Y_DF) [m] -> (col, row) [px]."""
        c0, r0 = self.centre_px
        return c0 + np.asarray(u_m) / self.pixel_pitch_m, r0 - np.asarray(v_m) / self.pixel_pitch_m

    def metric_from_pixels(self, col_px, row_px):
        """(col, row) [px] -> detector-plane (u, v) [m] in {DF}."""
        c0, r0 = self.centre_px
        return (np.asarray(col_px) - c0) * self.pixel_pitch_m, (r0 - np.asarray(row_px)) * self.pixel_pitch_m


def rot_x(a: float) -> np.ndarray:
    """Rotation matrix (3, 3) about X by angle a [rad] (right-hand rule)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Rotation matrix (3, 3) about Y by angle a [rad] (right-hand rule)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    """Rotation matrix (3, 3) about Z by angle a [rad] (right-hand rule)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_axis_angle(axis, angles_rad) -> np.ndarray:
    """Rodrigues rotation matrices about a unit axis.

    Parameters
    ----------
    axis : array_like of shape (3,)
        Rotation axis (normalised here).
    angles_rad : array_like of shape (N,) or scalar
        Rotation angles [rad].

    Returns
    -------
    ndarray of shape (N, 3, 3) (or (3, 3) for a scalar angle)
    """
    e = np.asarray(axis, dtype=float)
    e = e / np.linalg.norm(e)
    a = np.asarray(angles_rad, dtype=float)
    scalar = a.ndim == 0
    a = np.atleast_1d(a)
    c, s = np.cos(a)[:, None, None], np.sin(a)[:, None, None]
    k = np.array([[0.0, -e[2], e[1]], [e[2], 0.0, -e[0]], [-e[1], e[0], 0.0]])
    out = c * np.eye(3) + s * k + (1.0 - c) * np.outer(e, e)
    return out[0] if scalar else out


def detector_rotation(theta: float, phi: float, eta: float) -> np.ndarray:
    """Columns are the {DF} axes u, v, n expressed in {SRF}: Rz(eta) Ry(phi) Rx(theta)."""
    return rot_z(eta) @ rot_y(phi) @ rot_x(theta)


def object_rotation(rho_x: float, rho_y: float, rho_z: float) -> np.ndarray:
    """Orientation of {OF} in {SRF} at alpha = 0 (eq. 1): Ry(rho_Y) Rz(rho_Z) Rx(rho_X)."""
    return rot_y(rho_y) @ rot_z(rho_z) @ rot_x(rho_x)


def motion_rotation(gamma_x: float, gamma_y: float, gamma_z: float) -> np.ndarray:
    """Stage-axis rotation of eqs 9-10: Rx(gamma_X) Ry(gamma_Y) Rz(gamma_Z)."""
    return rot_x(gamma_x) @ rot_y(gamma_y) @ rot_z(gamma_z)


def _check_static(w) -> np.ndarray:
    w = np.asarray(w, dtype=float)
    if w.shape != (13,):
        raise ValueError(f"static parameters must have shape (13,), got {w.shape}")
    if not np.all(np.isfinite(w)):
        raise ValueError("static parameters contain NaN or inf")
    return w


def _check_motion(motion) -> np.ndarray:
    m = np.asarray(motion, dtype=float)
    if m.shape != (6,):
        raise ValueError(f"motion must have shape (6,) ({', '.join(MOTION_PARAM_NAMES)}), got {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError("motion contains NaN or inf")
    return m


def _check_points(p, name="centres_of_m") -> np.ndarray:
    p = np.asarray(p, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} contains NaN or inf")
    return p


def sphere_centres_srf(w, centres_of_m, alpha_rad) -> np.ndarray:
    """Sphere centres in {SRF} at the given rotary angles (eqs 1-2).

    Parameters
    ----------
    w : array_like of shape (13,)
        Static parameters (see module docstring).
    centres_of_m : array_like of shape (N, 3)
        Sphere centres in {OF} [m].
    alpha_rad : array_like of shape (M,)
        Rotary angles [rad].

    Returns
    -------
    ndarray of shape (M, N, 3)
    """
    w = _check_static(w)
    c_of = _check_points(centres_of_m)
    z_r = w[0]
    c1 = c_of @ object_rotation(w[10], w[11], w[12]).T + w[7:10]
    rot = rot_axis_angle([0.0, 1.0, 0.0], np.atleast_1d(alpha_rad))
    r = np.array([0.0, 0.0, z_r])
    return np.einsum("mij,nj->mni", rot, c1 - r) + r


def cylinder_about_y(centres_of_m, tol_m: float | None = None, rel_tol: float | None = None):
    """Do the centres lie on one cylinder about the object's Y axis (as helix49's do)?

    Returns (radius [m], heights (N,) [m], azimuths (N,) [rad], atan2(z, x)) when there are at least 6
    centres and every one's distance from the Y axis is within the tolerance of the median distance:
    ``tol_m`` [m] if given, else ``rel_tol`` times that median; None otherwise. The one test shared by
    the identity search (which needs the cylinder to search leaning poses) and the location classes
    (which need it to say where a sphere sits relative to the object's axis)."""
    c = _check_points(centres_of_m)
    rad = np.hypot(c[:, 0], c[:, 2])
    r = float(np.median(rad))
    tol = tol_m if tol_m is not None else (rel_tol if rel_tol is not None else 0.0) * r
    if len(c) < 6 or not r > 0 or float(np.max(np.abs(rad - r))) > tol:
        return None
    return r, c[:, 1].copy(), np.arctan2(c[:, 2], c[:, 0])


def project_srf(w, points_srf_m, detector: DetectorSpec) -> np.ndarray:
    """Central projection of {SRF} points from the focal spot onto the detector (App. A).

    Parameters
    ----------
    w : array_like of shape (13,)
    points_srf_m : array_like of shape (..., 3)
    detector : DetectorSpec

    Returns
    -------
    ndarray of shape (..., 2)
        (col, row) image coordinates [px].
    """
    w = _check_static(w)
    p = np.asarray(points_srf_m, dtype=float)
    rmat = detector_rotation(w[4], w[5], w[6])
    d = w[1:4]
    u_hat, v_hat, n_hat = rmat[:, 0], rmat[:, 1], rmat[:, 2]
    t = (n_hat @ d) / (p @ n_hat)
    hit = p * t[..., None] - d
    col, row = detector.pixels_from_metric(hit @ u_hat, hit @ v_hat)
    return np.stack([col, row], axis=-1)


def forward_srf(w, centres_of_m, alpha_rad, detector: DetectorSpec) -> np.ndarray:
    """Modelled centre projections at stage position k = 1, shape (M, N, 2) [px]."""
    return project_srf(w, sphere_centres_srf(w, centres_of_m, alpha_rad), detector)


@dataclass(frozen=True)
class DetectorFrameGeometry:
    """The k = 1 geometry expressed in {DF} (eqs 4-7).

    Attributes
    ----------
    source_df_m : ndarray of shape (3,)
        Focal spot S in {DF} [m] (eq. 4), held fixed over stage positions.
    stage_df_m : ndarray of shape (3,)
        Stage point R_1 in {DF} [m] (eq. 5).
    axis_df : ndarray of shape (3,)
        Unit rotation axis r_1 in {DF} (eq. 6).
    centres_df_m : ndarray of shape (N, 3)
        Sphere centres at alpha = 0, k = 1 in {DF} [m] (eq. 7).
    """

    source_df_m: np.ndarray
    stage_df_m: np.ndarray
    axis_df: np.ndarray
    centres_df_m: np.ndarray


def static_to_detector_frame(w, centres_of_m) -> DetectorFrameGeometry:
    """Convert a static solution in {SRF} to {DF} (section 3.2, eqs 4-7)."""
    w = _check_static(w)
    c_of = _check_points(centres_of_m)
    rmat = detector_rotation(w[4], w[5], w[6])
    d = w[1:4]
    to_df = lambda p: (np.asarray(p) - d) @ rmat  # R^-1 T(-D) p, row vectors
    c1_srf = sphere_centres_srf(w, c_of, [0.0])[0]
    return DetectorFrameGeometry(
        source_df_m=to_df(np.zeros(3)),
        stage_df_m=to_df(np.array([0.0, 0.0, w[0]])),
        axis_df=rmat.T @ np.array([0.0, 1.0, 0.0]),
        centres_df_m=to_df(c1_srf),
    )


def sphere_centres_df(geom: DetectorFrameGeometry, motion, alpha_rad) -> np.ndarray:
    """Sphere centres in {DF} at stage position k and rotary angles alpha (eqs 8-11).

    Parameters
    ----------
    geom : DetectorFrameGeometry
        The k = 1 geometry.
    motion : array_like of shape (6,)
        dx_R, dy_R, dz_R [m], gamma_X, gamma_Y, gamma_Z [rad] of position k
        relative to k = 1 (zeros give k = 1).
    alpha_rad : array_like of shape (M,)

    Returns
    -------
    ndarray of shape (M, N, 3) [m]
    """
    m = _check_motion(motion)
    g = motion_rotation(m[3], m[4], m[5])
    r_k = geom.stage_df_m + m[:3]                      # eq. 8
    axis_k = g @ geom.axis_df                          # eq. 9
    c1k = (geom.centres_df_m - geom.stage_df_m) @ g.T + r_k   # eq. 10 (see note)
    rot = rot_axis_angle(axis_k, np.atleast_1d(alpha_rad))
    return np.einsum("mij,nj->mni", rot, c1k - r_k) + r_k     # eq. 11


def project_df(source_df_m, points_df_m, detector: DetectorSpec) -> np.ndarray:
    """Central projection from the source onto the plane z = 0 of {DF} (App. B).

    Parameters
    ----------
    source_df_m : array_like of shape (3,)
    points_df_m : array_like of shape (..., 3)
    detector : DetectorSpec

    Returns
    -------
    ndarray of shape (..., 2) (col, row) [px]
    """
    s = np.asarray(source_df_m, dtype=float)
    p = np.asarray(points_df_m, dtype=float)
    t = -s[2] / (p[..., 2] - s[2])
    x = s[0] + t * (p[..., 0] - s[0])
    y = s[1] + t * (p[..., 1] - s[1])
    col, row = detector.pixels_from_metric(x, y)
    return np.stack([col, row], axis=-1)


def forward_df(geom: DetectorFrameGeometry, motion, alpha_rad, detector: DetectorSpec) -> np.ndarray:
    """Modelled centre projections at stage position k, shape (M, N, 2) [px]."""
    return project_df(geom.source_df_m, sphere_centres_df(geom, motion, alpha_rad), detector)


def silhouette_ellipses(source_df_m, centres_df_m, radii_m):
    """Exact shadow ellipses of spheres seen from a point source on the plane z = 0.

    The tangent cone from S to a sphere (C, r) is
    ``((q . a)^2 - cos^2(beta) |q|^2 = 0`` with ``q = X - S``, ``a = (C - S)/|C - S|``,
    ``sin(beta) = r / |C - S|``; on z = 0 it is a conic in (x, y) whose centre
    and axes are returned.

    Parameters
    ----------
    source_df_m : array_like of shape (3,)
    centres_df_m : array_like of shape (N, 3)
    radii_m : array_like of shape (N,)

    Returns
    -------
    centre_m : ndarray of shape (N, 2)
        Ellipse centre (x, y) in the detector plane [m].
    semi_axes_m : ndarray of shape (N, 2)
        Semi-major, semi-minor axis [m].
    """
    s = np.asarray(source_df_m, dtype=float)
    c = np.asarray(centres_df_m, dtype=float)
    r = np.asarray(radii_m, dtype=float)
    d = c - s
    dist = np.linalg.norm(d, axis=1)
    if np.any(dist <= r):
        raise ValueError("focal spot inside a sphere")
    a = d / dist[:, None]
    cos2 = 1.0 - (r / dist) ** 2
    p = np.array([[1.0, 0.0, -s[0]], [0.0, 1.0, -s[1]], [0.0, 0.0, -s[2]]])
    m = a[:, :, None] * a[:, None, :] - cos2[:, None, None] * np.eye(3)
    q = np.einsum("ji,njk,kl->nil", p, m, p)
    a2 = q[:, :2, :2]
    b = q[:, :2, 2]
    centre = -np.linalg.solve(a2, b[:, :, None])[:, :, 0]
    f0 = q[:, 2, 2] + np.einsum("ni,ni->n", b, centre)
    ev = np.linalg.eigvalsh(a2)                  # ascending, both < 0 for an ellipse
    if np.any(ev >= 0) or np.any(f0 <= 0):
        raise ValueError("a sphere's shadow on the detector plane is not an ellipse")
    axes = np.sqrt(-f0[:, None] / ev)            # ev[0] most negative -> minor axis
    return centre, axes[:, ::-1].copy()
