"""Simulated sphere-centre observations from a known truth (for tests and benchmarks).

The simulator uses only geometry.py's forward model (not the solver's
ct_model.py), plus the optional terms' own correction formulas, so a solver
bug does not cancel against a simulator bug. It returns the truth alongside
the data; only tests compare against it.

Observations are either projections of the sphere centres (the paper's
model) or, with ``contour_radius_m``, the centres of the exact silhouette
ellipses of cones of that radius about each sphere centre, computed with the
general conic of geometry.silhouette_ellipses (not with the closed form the
solvers use), with the ellipses' semi-minor axes, as a detector reports them.
The reference object of the tests is the shipped one (phantom.helix49).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import DetectorSpec, project_df, silhouette_ellipses, sphere_centres_df, static_to_detector_frame
from .observations import CentreObservations
from .terms import check_terms


@dataclass(frozen=True)
class SimulatedObservations:
    """Simulated observations with their truth.

    Attributes
    ----------
    obs : CentreObservations
        What a detector would deliver (noisy, missing where overlapped or out of view).
    uv_true_px : ndarray of shape (Q, 2)
        Noise-free centre projections of the same observations.
    outlier_mask : ndarray of shape (Q,), bool
        Observations replaced by gross errors.
    n_overlap_rejected, n_out_of_view : int
    """

    obs: CentreObservations
    uv_true_px: np.ndarray
    outlier_mask: np.ndarray
    n_overlap_rejected: int
    n_out_of_view: int


def simulate_observations(static_w, centres_of_m, detector: DetectorSpec, alpha_rad, rng: np.random.Generator,
                          sigma_px: float = 0.05, *, motion=None, terms=(), term_params=(),
                          sphere_diameter_m: float = 0.003, reject_overlap: bool = True,
                          overlap_factor: float = 1.1, edge_margin_px: float = 2.0,
                          outlier_fraction: float = 0.0, outlier_px: float = 5.0,
                          stamp_period_ns: int = 100_000_000, report_sigma: bool = False,
                          contour_radius_m=None, view_jitter_px: float = 0.0,
                          alpha_offset_rad: float = 0.0) -> SimulatedObservations:
    """Simulate observed centre projections at one stage position.

    Parameters
    ----------
    static_w : array_like of shape (13,)
        True static geometry at k = 1.
    centres_of_m : array_like of shape (N, 3)
        True sphere centres in {OF} [m].
    detector : DetectorSpec
    alpha_rad : array_like of shape (M,)
        Reported rotary angles of the projections [rad].
    rng : numpy.random.Generator
    sigma_px : float
        Standard deviation of the Gaussian noise on each coordinate [px].
    motion : array_like of shape (6,), optional
        True error motion of this position relative to k = 1 (None: k = 1).
    terms, term_params
        Optional terms and their TRUE parameter values (e.g. eccentricity).
    sphere_diameter_m : float
        For the overlap test: projections closer than ``overlap_factor``
        times the sum of the projected radii are rejected (both spheres).
    edge_margin_px : float
        Projections whose disc leaves the detector by more than this are dropped.
    outlier_fraction, outlier_px
        Fraction of kept observations displaced by a random vector of norm
        ``outlier_px`` (gross detection errors).
    stamp_period_ns : int
        Time between projections (stamps start at 0).
    report_sigma : bool
        Fill ``sigma_px`` in the observations with the true sigma.
    contour_radius_m : float or array_like of shape (N,), optional
        Observe the centre of the silhouette ellipse of a sphere of this
        radius about each centre (a detector's iso-transmission contour lies
        inside the full silhouette), and report its semi-minor axis in
        ``obs.minor_axis_px``. None: centre projections, no axes.
    view_jitter_px : float
        Standard deviation of a shift shared by every observation of a view
        (per coordinate) [px]: focal-spot jitter, per-projection wobble.
    alpha_offset_rad : float
        True rotary angle = reported + this (a rotary zero-index offset).

    Returns
    -------
    SimulatedObservations
    """
    terms = check_terms(terms)
    c_of = np.asarray(centres_of_m, dtype=float)
    alpha = np.atleast_1d(np.asarray(alpha_rad, dtype=float))
    n, m = len(c_of), len(alpha)
    geom = static_to_detector_frame(static_w, c_of)
    mot = np.zeros(6) if motion is None else np.asarray(motion, dtype=float)
    stamps = np.arange(m, dtype=np.int64) * int(stamp_period_ns)
    tp = np.asarray(term_params, dtype=float).reshape(-1)
    split, k = [], 0
    for t in terms:
        split.append(tp[k:k + t.n_params])
        k += t.n_params
    # per-view observation stub for the terms (alpha and stamp of each view)
    view_obs = CentreObservations(np.zeros((m, 2)), np.zeros(m, np.int64), alpha, np.arange(m), stamps)
    alpha_true = alpha + float(alpha_offset_rad)
    for t, p in zip(terms, split):
        if t.stage == "angle":
            alpha_true = alpha_true + t.angle_delta(p, alpha, view_obs)[0]
    pts = sphere_centres_df(geom, mot, alpha_true)                     # (M, N, 3)
    minor_px = None
    if contour_radius_m is None:
        uv = project_df(geom.source_df_m, pts, detector)               # (M, N, 2)
    else:
        rad = np.broadcast_to(np.asarray(contour_radius_m, dtype=float), (n,))
        ell, axes = silhouette_ellipses(geom.source_df_m, pts.reshape(-1, 3), np.tile(rad, m))
        c, r = detector.pixels_from_metric(ell[:, 0], ell[:, 1])
        uv = np.stack([c, r], axis=-1).reshape(m, n, 2)
        minor_px = (axes[:, 1] / detector.pixel_pitch_m).reshape(m, n)
    if any(t.stage == "image" for t in terms):
        view_i = np.repeat(np.arange(m), n)
        flat_obs = CentreObservations(np.zeros((m * n, 2)), np.tile(np.arange(n), m), alpha[view_i],
                                      view_i, stamps[view_i])
        xy = np.stack(detector.metric_from_pixels(uv[..., 0], uv[..., 1]), axis=-1).reshape(-1, 2)
        for t, p in zip(terms, split):
            if t.stage == "image":
                xy = xy + t.image_delta(p, xy, flat_obs)[0]
        c, r = detector.pixels_from_metric(xy[:, 0], xy[:, 1])
        uv = np.stack([c, r], axis=-1).reshape(m, n, 2)
    # projected radius [px]: sphere radius times the local magnification
    depth = pts[..., 2] - geom.source_df_m[2]
    rad_px = 0.5 * sphere_diameter_m * (-geom.source_df_m[2]) / depth / detector.pixel_pitch_m
    keep = np.ones((m, n), dtype=bool)
    n_overlap = 0
    if reject_overlap:
        d = np.linalg.norm(uv[:, :, None, :] - uv[:, None, :, :], axis=-1)
        lim = overlap_factor * (rad_px[:, :, None] + rad_px[:, None, :])
        close = d < lim
        close[:, np.arange(n), np.arange(n)] = False
        ov = close.any(axis=2)
        n_overlap = int(ov.sum())
        keep &= ~ov
    inside = ((uv[..., 0] - rad_px >= -0.5 - edge_margin_px) & (uv[..., 0] + rad_px <= detector.cols - 0.5 + edge_margin_px)
              & (uv[..., 1] - rad_px >= -0.5 - edge_margin_px) & (uv[..., 1] + rad_px <= detector.rows - 0.5 + edge_margin_px))
    n_out = int((keep & ~inside).sum())
    keep &= inside
    vi, si = np.nonzero(keep)
    uv_true = uv[vi, si]
    uv_obs = uv_true + rng.normal(0.0, sigma_px, uv_true.shape)
    if view_jitter_px > 0:
        uv_obs += rng.normal(0.0, view_jitter_px, (m, 2))[vi]
    out = np.zeros(len(vi), dtype=bool)
    if outlier_fraction > 0:
        n_o = int(round(outlier_fraction * len(vi)))
        pick = rng.choice(len(vi), n_o, replace=False)
        ang = rng.uniform(0, 2 * np.pi, n_o)
        uv_obs[pick] += outlier_px * np.stack([np.cos(ang), np.sin(ang)], axis=1)
        out[pick] = True
    obs = CentreObservations(uv_px=uv_obs, sphere_index=si, alpha_rad=alpha[vi], view_index=vi,
                             stamp_ns=stamps[vi], sigma_px=np.full(len(vi), sigma_px) if report_sigma else None,
                             minor_axis_px=None if minor_px is None else minor_px[vi, si])
    return SimulatedObservations(obs=obs, uv_true_px=uv_true, outlier_mask=out,
                                 n_overlap_rejected=n_overlap, n_out_of_view=n_out)
