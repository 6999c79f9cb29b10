"""Fits of measured points: plane, squares / rectangles, circles, dot grids, the part pose.

Points are (N, 3) in one frame (stage or tracker) with covariances (N, 3, 3). Shapes are fitted
in the plane of the points: coordinates (N, 2) on an orthonormal in-plane basis (e1, e2) whose e1
follows a hint (the part's +x axis as far as it is known). Every fit is weighted least squares
with the point covariances projected on the residual's direction; the reported covariance is
(J^T W J)^-1 from the point covariances alone, and chi2/dof says whether the scatter agrees
with them (form deviations of a real part would raise it).

Rotations: `fixed_angles(R)` gives [tx, ty, tz] with R = Rz(tz) Ry(ty) Rx(tx) (INTERFACES.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from .camera import check_points


class FitError(ValueError):
    """Too few or degenerate points for a fit; the message says which."""


def fixed_angles(R) -> np.ndarray:
    """[tx, ty, tz] (rad) of R = Rz(tz) Ry(ty) Rx(tx)."""
    R = np.asarray(R, float)
    ty = -np.arcsin(np.clip(R[2, 0], -1.0, 1.0))
    tx = np.arctan2(R[2, 1], R[2, 2])
    tz = np.arctan2(R[1, 0], R[0, 0])
    return np.array([tx, ty, tz])


def from_fixed_angles(a) -> np.ndarray:
    tx, ty, tz = a
    cx, sx, cy, sy, cz, sz = np.cos(tx), np.sin(tx), np.cos(ty), np.sin(ty), np.cos(tz), np.sin(tz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def _covs(covs, n):
    if covs is None:
        return np.repeat(np.eye(3)[None] * 1e-12, n, 0)
    c = np.asarray(covs, float)
    if c.shape != (n, 3, 3) or not np.all(np.isfinite(c)):
        raise ValueError(f"covariances: expected a finite array of shape ({n}, 3, 3), got {c.shape}")
    return c


@dataclass(frozen=True)
class PlaneFit:
    point: np.ndarray          # (3,) centroid
    normal: np.ndarray         # (3,) unit, oriented to +z of the frame hint
    e1: np.ndarray             # (3,) in-plane basis
    e2: np.ndarray
    residuals: np.ndarray      # (N,) signed distances, m
    flatness: float            # max - min residual, m
    rms: float
    n: int

    @property
    def R(self) -> np.ndarray:
        return np.column_stack([self.e1, self.e2, self.normal])

    def to_2d(self, points) -> np.ndarray:
        p = np.atleast_2d(np.asarray(points, float)) - self.point
        return np.column_stack([p @ self.e1, p @ self.e2])

    def to_3d(self, xy) -> np.ndarray:
        xy = np.atleast_2d(np.asarray(xy, float))
        return self.point + xy[:, :1] * self.e1 + xy[:, 1:2] * self.e2

    def cov_2d(self, covs) -> np.ndarray:
        B = np.column_stack([self.e1, self.e2])
        return np.einsum("ia,nij,jb->nab", B, np.asarray(covs, float), B)


def fit_plane(points, *, up=(0.0, 0.0, 1.0), x_hint=(1.0, 0.0, 0.0)) -> PlaneFit:
    """Least-squares plane (orthogonal distances) through points (N, 3), N >= 3 not collinear.
    The normal points to the side of `up`; e1 is `x_hint` projected into the plane."""
    p = check_points(points, "points")
    if len(p) < 3:
        raise FitError(f"plane: needs at least 3 points, got {len(p)}")
    c = p.mean(0)
    _, s, vt = np.linalg.svd(p - c, full_matrices=False)
    if s[1] < 1e-9 * max(s[0], 1e-30) or s[1] < 1e-9:
        raise FitError("plane: the points are collinear")
    n = vt[2]
    if n @ np.asarray(up, float) < 0:
        n = -n
    e1 = np.asarray(x_hint, float) - (np.asarray(x_hint, float) @ n) * n
    if np.linalg.norm(e1) < 1e-6:
        e1 = vt[0]
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    r = (p - c) @ n
    return PlaneFit(c, n, e1, e2, r, float(r.max() - r.min()), float(np.sqrt(np.mean(r * r))), len(p))


@dataclass(frozen=True)
class ShapeFit:
    type: str                  # square | rectangle | circle
    center: np.ndarray         # (2,) in the plane coordinates
    angle: float               # rad, in-plane (squares / rectangles), 0 for circles
    size: np.ndarray           # square: (s1, s2) sides; rectangle (sx, sy); circle (diameter,)
    cov: np.ndarray            # covariance of the parameters (see `names`)
    names: tuple
    residuals: np.ndarray      # (N,) free-fit residuals, m, + outward
    dev_ideal: np.ndarray      # (N,) deviations from the NOMINAL shape at the fitted centre / angle
    chi2_dof: float

    @property
    def form_rms(self) -> float:
        return float(np.sqrt(np.mean(self.residuals ** 2)))

    @property
    def form_max(self) -> float:
        return float(np.max(np.abs(self.residuals)))

    def u(self, name) -> float:
        i = self.names.index(name)
        return float(np.sqrt(max(self.cov[i, i], 0.0)))


_SIDE_N = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])


def fit_rectangle(xy, sides, *, cov2d=None, nominal=None, angle0=0.0, square=False) -> ShapeFit:
    """Rectangle (or square) from edge points xy (N, 2) with known side index 0..3 (+x, +y, -x,
    -y of the shape frame). Parameters cx, cy, angle, hx, hy (half sizes). nominal: (sx, sy)
    for the deviations from the ideal shape."""
    xy = check_points(xy, "xy", 2)
    sides = np.asarray(sides, int)
    if sides.shape != (len(xy),) or np.any((sides < 0) | (sides > 3)):
        raise ValueError("sides: one index 0..3 per point")
    for s in range(4):
        if np.count_nonzero(sides == s) < (2 if s in (0, 1) else 1):
            raise FitError(f"rectangle: side {s} has {np.count_nonzero(sides == s)} points "
                           "(sides 0 and 1 need 2 for the angle, every side at least 1)")
    cov2d = np.repeat(np.eye(2)[None] * 1e-12, len(xy), 0) if cov2d is None else np.asarray(cov2d, float)

    def normals(a):
        c, s = np.cos(a), np.sin(a)
        R = np.array([[c, -s], [s, c]])
        return _SIDE_N[sides] @ R.T

    def resid(x, w=True):
        cx, cy, a, hx, hy = x
        n = normals(a)
        h = np.where(sides % 2 == 0, hx, hy)
        r = np.einsum("ij,ij->i", n, xy - [cx, cy]) - h
        if not w:
            return r
        var = np.einsum("ni,nij,nj->n", n, cov2d, n)
        return r / np.sqrt(var)

    c0 = xy.mean(0)
    h0 = np.array([np.abs(xy[sides % 2 == 0, 0] - c0[0]).mean(), np.abs(xy[sides % 2 == 1, 1] - c0[1]).mean()])
    x0 = np.array([c0[0], c0[1], angle0, h0[0], h0[1]])
    sol = least_squares(resid, x0, method="lm", xtol=1e-15, ftol=1e-15)
    J = sol.jac
    cov = np.linalg.pinv(J.T @ J)
    cx, cy, a, hx, hy = sol.x
    if hx < 0 or hy < 0:
        raise FitError("rectangle: fit did not converge to positive sizes")
    r = resid(sol.x, False)
    dof = max(len(xy) - 5, 1)
    names = ("cx", "cy", "angle", "sx", "sy", "size")
    Tf = np.zeros((6, 5))
    Tf[:3, :3] = np.eye(3)
    Tf[3, 3] = Tf[4, 4] = 2.0
    Tf[5, 3] = Tf[5, 4] = 1.0              # mean side = hx + hy
    full = Tf @ cov @ Tf.T
    if nominal is not None:
        hn = np.where(sides % 2 == 0, nominal[0] / 2, nominal[1] / 2)
        n = normals(a)
        dev = np.einsum("ij,ij->i", n, xy - [cx, cy]) - hn
    else:
        dev = r
    return ShapeFit("square" if square else "rectangle", np.array([cx, cy]), float(a),
                    np.array([2 * hx, 2 * hy]), full, names, r, dev, float(np.sum(sol.fun ** 2) / dof))


def fit_circle(xy, *, cov2d=None, nominal_diameter=None) -> ShapeFit:
    """Circle from rim points xy (N >= 3, 2): centre, diameter (geometric weighted LS)."""
    xy = check_points(xy, "xy", 2)
    if len(xy) < 3:
        raise FitError(f"circle: needs at least 3 points, got {len(xy)}")
    cov2d = np.repeat(np.eye(2)[None] * 1e-12, len(xy), 0) if cov2d is None else np.asarray(cov2d, float)
    # algebraic start (Kasa)
    A = np.column_stack([2 * xy, np.ones(len(xy))])
    b = (xy ** 2).sum(1)
    s, *_ = np.linalg.lstsq(A, b, rcond=None)
    r0 = np.sqrt(max(s[2] + s[0] ** 2 + s[1] ** 2, 1e-18))

    def resid(x, w=True):
        d = xy - x[:2]
        rho = np.hypot(d[:, 0], d[:, 1])
        r = rho - x[2]
        if not w:
            return r
        u = d / rho[:, None]
        return r / np.sqrt(np.einsum("ni,nij,nj->n", u, cov2d, u))

    sol = least_squares(resid, np.array([s[0], s[1], r0]), method="lm", xtol=1e-15, ftol=1e-15)
    cov = np.linalg.pinv(sol.jac.T @ sol.jac)
    T = np.diag([1.0, 1.0, 2.0])
    r = resid(sol.x, False)
    d = xy - sol.x[:2]
    dev = np.hypot(d[:, 0], d[:, 1]) - (nominal_diameter / 2 if nominal_diameter else sol.x[2])
    dof = max(len(xy) - 3, 1)
    return ShapeFit("circle", sol.x[:2].copy(), 0.0, np.array([2 * sol.x[2]]), T @ cov @ T.T,
                    ("cx", "cy", "diameter"), r, dev, float(np.sum(sol.fun ** 2) / dof))


def grid_spacings(centres, rc, pitch, max_pitches=4, cov2d=None) -> list[dict]:
    """Distances between dots of one row or one column, per separation 1..max_pitches pitches
    (the paper's Fig. 16): [{nominal, k, mean, sd, n, values, u_mean}]. centres (N, 2), rc (N, 2)."""
    c = check_points(centres, "centres", 2)
    rc = np.asarray(rc, int)
    out = []
    for k in range(1, max_pitches + 1):
        vals, var = [], []
        for i in range(len(c)):
            for j in range(len(c)):
                same_row = rc[i, 0] == rc[j, 0] and rc[j, 1] - rc[i, 1] == k
                same_col = rc[i, 1] == rc[j, 1] and rc[j, 0] - rc[i, 0] == k
                if same_row or same_col:
                    d = c[j] - c[i]
                    L = float(np.hypot(*d))
                    vals.append(L)
                    if cov2d is not None:
                        u = d / L
                        var.append(float(u @ (cov2d[i] + cov2d[j]) @ u))
        if not vals:
            continue
        v = np.array(vals)
        out.append({"nominal": k * pitch, "k": k, "mean": float(v.mean()),
                    "sd": float(v.std(ddof=1)) if len(v) > 1 else 0.0, "n": len(v), "values": v.tolist(),
                    "u_single": float(np.sqrt(np.mean(var))) if var else None})
    return out


def fit_grid(centres, rc, pitch, cov2d=None) -> dict:
    """Similarity fit of a grid (rows, cols at `pitch`) to dot centres (N, 2): centre, angle,
    scale (measured pitch / nominal) and residuals (m)."""
    c = check_points(centres, "centres", 2)
    rc = np.asarray(rc, float)
    rows, cols = rc[:, 0].max() + 1, rc[:, 1].max() + 1
    loc = np.column_stack([(rc[:, 1] - (cols - 1) / 2) * pitch, (rc[:, 0] - (rows - 1) / 2) * pitch])
    mc, ml = c.mean(0), loc.mean(0)
    A, B = loc - ml, c - mc
    # complex least squares B = z A
    za = A[:, 0] + 1j * A[:, 1]
    zb = B[:, 0] + 1j * B[:, 1]
    z = np.vdot(za, zb) / np.vdot(za, za)
    pred = np.column_stack([(z * za).real, (z * za).imag]) + mc
    res = c - pred
    return {"center": mc - np.array([(z * (ml[0] + 1j * ml[1])).real, (z * (ml[0] + 1j * ml[1])).imag]),
            "angle": float(np.angle(z)), "scale": float(abs(z)), "residuals": res,
            "rms": float(np.sqrt(np.mean((res ** 2).sum(1))))}


def fit_part_pose(plane: PlaneFit, nominal_xy, measured_xy, weights=None, angle_hint=None):
    """R_frame_part (3, 3), p_frame_part (3,) from feature centres: nominal (M, 2) in the part
    frame, measured (M, 2) in the plane coordinates of `plane`. With one centre the in-plane
    angle comes from `angle_hint` (rad, plane coordinates)."""
    a = check_points(nominal_xy, "nominal_xy", 2)
    b = check_points(measured_xy, "measured_xy", 2)
    w = np.ones(len(a)) if weights is None else np.asarray(weights, float)
    if len(a) >= 2 and np.ptp(a, axis=0).max() > 0:
        ma, mb = (w[:, None] * a).sum(0) / w.sum(), (w[:, None] * b).sum(0) / w.sum()
        H = ((a - ma) * w[:, None]).T @ (b - mb)
        ang = float(np.arctan2(H[0, 1] - H[1, 0], H[0, 0] + H[1, 1]))
    else:
        ang = float(angle_hint or 0.0)
        ma, mb = a.mean(0), b.mean(0)
    c, s = np.cos(ang), np.sin(ang)
    R2 = np.array([[c, -s], [s, c]])
    t = mb - R2 @ ma
    e1 = c * plane.e1 + s * plane.e2
    e2 = np.cross(plane.normal, e1)
    R = np.column_stack([e1, e2, plane.normal])
    p = plane.to_3d(t)[0]
    resid = b - (a @ R2.T + t)
    return R, p, ang, resid
