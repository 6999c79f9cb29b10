"""Noise that depends on where a sphere's shadow falls relative to the object: location classes.

Why. The reference object's spheres sit on a support (helix49: a CFRP body tube whose outer surface
they touch). Seen from the source, the tube's wall projects a dense band along each side of the
object's silhouette, and a sphere whose shadow lies across that band has its centre pulled by the
band's intensity step, in a direction and by an amount fixed by the geometry. Measured on the 22
independent 512 px recordings (seeds 7200-7221, ct_detect.md "Location classes"): with the tube, the
column errors of spheres at lateral positions |s| = 0.8-1 of the object's radius (about a quarter of
the detections) had a mean of -1.0 to +1.5 times their stated sigma and a scatter of 2.3-2.6 times it;
everywhere else, and in every bin without the tube, about 0 and 1. The detector cannot see this (its
sigma comes from its own edge scatter) and the per-axis noise factor spreads it over all observations,
so the tilt phi, which the silhouette spheres determine, came out 1.5 times too confident.

What. After a first fit, each observation is put in a class by its sphere's place relative to the
object's Y axis, from the fitted geometry (no truth, no holder model): the lateral position
s = (offset from the axis) . e_lat / |offset| in 10 bins of |s| over [0, 1], times front / back of
the axis as seen from the source (20 classes). Per image axis, each class's mean square of the
whitened residuals is compared with the median class's; a class whose excess is significant
(chi-square, Bonferroni over the classes and axes at ``P_CLASS``, at least ``MIN_CLASS_OBS``
observations) gets its own factor sqrt(mean square / median), the larger of its two axes', applied
to both axes (one factor per class), everything else 1. The solver then multiplies the detector's
sigma by the factors, refits and forms the covariance under the new weights (noise.py's model on
top). Objects whose centres do not lie on a cylinder about their Y axis get no classes.

Measured (22 recordings, same detections, solved in-process without / with the classes): phi z sd
1.49 -> 1.00 (mean -0.33 -> -0.12), sum of the 7 instrument z^2 9.08 -> 8.07 per case; theta
unchanged (1.32: not a silhouette effect); x_D 1.05 -> 1.29 (the silhouette spheres carried x_D
information; the rest has a small bias of its own). Classes fired on 16 of 16 tube cases (the
silhouette bins 0.7-1.0) and on 2 of 6 without the tube (one bin each, factors 1.37-1.46): the
chi-square test is sensitive to heavier tails than Gaussian. Removing the silhouette detections by
the truth instead (diagnostic only) gave phi 1.13, x_D 1.23. With 30 more instruments through
ct_offline_solve (52 in all): phi 1.38 -> 1.05, every instrument parameter's |mean| <= 0.27 and sd
1.05-1.21; the sum of the 7 z^2 ~9 against 7 before and after (ct_detect.md).
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from .geometry import cylinder_about_y, sphere_centres_srf

N_BINS = 10                 # bins of |s| over [0, 1]
N_CLASSES = 2 * N_BINS      # |s| bins in front of the object's axis, then behind it
MIN_CLASS_OBS = 30          # a class needs this many observations to be tested
P_CLASS = 1e-3              # family-wise false-alarm probability of a class factor per solve
CYLINDER_TOLERANCE = 0.05   # centres' radii about the Y axis within 5 % of their median


def on_cylinder(centres_of_m) -> bool:
    """Do the calibrated centres lie on a cylinder about the object's Y axis (geometry.cylinder_about_y,
    to 5 % of its radius: the classes need only the side of the axis and the lateral position)?"""
    return cylinder_about_y(centres_of_m, rel_tol=CYLINDER_TOLERANCE) is not None


def location_class(w, centres_of_m, sphere_index, alpha_rad) -> np.ndarray:
    """Class (Q,) int in [0, N_CLASSES) of each observation: |s| bin, + N_BINS behind the axis."""
    c_of = np.asarray(centres_of_m, dtype=float)
    si = np.asarray(sphere_index)
    angles, ai = np.unique(np.asarray(alpha_rad, dtype=float), return_inverse=True)
    # the spheres, the object's origin and a point 1 m up its Y axis, in {SRF} at each distinct angle
    pts = sphere_centres_srf(w, np.vstack([c_of, [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0]]]), angles)
    n = len(c_of)
    a0 = pts[:, n][ai]                                                     # (Q, 3) axis point
    ad = (pts[:, n + 1] - pts[:, n])[ai]                                   # unit axis direction
    d = pts[ai, si] - a0
    d -= np.sum(d * ad, axis=1)[:, None] * ad                              # offset from the axis
    e_ray = a0 / np.linalg.norm(a0, axis=1)[:, None]                       # source at the SRF origin
    e_lat = np.cross(ad, e_ray)
    e_lat /= np.maximum(np.linalg.norm(e_lat, axis=1), 1e-300)[:, None]
    nd = np.maximum(np.linalg.norm(d, axis=1), 1e-300)
    s = np.abs(np.sum(d * e_lat, axis=1)) / nd
    b = np.minimum((s * N_BINS).astype(int), N_BINS - 1)
    return b + N_BINS * (np.sum(d * e_ray, axis=1) > 0)


def class_factors(residuals, sigma, classes) -> np.ndarray:
    """Factor (N_CLASSES,) on the sigma of each class, 1 where nothing is significant.

    residuals, sigma: blocked (2Q,) [u..., v...]; classes: (Q,). Each axis is tested; a class noisier
    on either gets the larger of its two axes' factors, for both: the observation is degraded as a
    whole (measured on the 22 recordings: the column factor on the columns only left phi at z sd 1.57,
    on both axes 1.00)."""
    r = np.asarray(residuals, dtype=float)
    q = r.size // 2
    sig = np.ones(2 * q) if sigma is None else np.asarray(sigma, dtype=float)
    cl = np.asarray(classes)
    out = np.ones(N_CLASSES)
    cnt = np.bincount(cl, minlength=N_CLASSES)
    tested = np.flatnonzero(cnt >= MIN_CLASS_OBS)
    if tested.size < 3:
        return out
    p_each = P_CLASS / (2 * tested.size)
    for a in range(2):
        z2 = (r[a * q:(a + 1) * q] / sig[a * q:(a + 1) * q]) ** 2
        ms = np.bincount(cl, z2, minlength=N_CLASSES)[tested] / cnt[tested]
        base = float(np.median(ms))
        if not base > 0:
            continue
        chi2 = ms * cnt[tested] / base
        crit = stats.chi2.isf(p_each, cnt[tested])
        hit = chi2 > crit
        out[tested[hit]] = np.maximum(out[tested[hit]], np.sqrt(ms[hit] / base))
    return out


def scaled_sigma(sigma, classes, factors) -> np.ndarray:
    """The blocked sigma (2Q,) times each observation's class factor (on both axes)."""
    cl = np.asarray(classes)
    sig = np.ones(2 * cl.size) if sigma is None else np.asarray(sigma, dtype=float)
    return sig * np.tile(np.asarray(factors, dtype=float)[cl], 2)
