"""Observed sphere-centre projections: the input of the CT geometry solvers.

One observation is the projected centre of one sphere in one projection
(image). Missing observations (spheres overlapping, out of view, rejected by
the detector) are simply absent; nothing is padded.

The node layer builds a :class:`CentreObservations` from detections; the
simulators build one from a known truth (see ``simulate_obs.py``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


def _n_distinct(idx: np.ndarray) -> int:
    """Number of distinct values of a non-negative int array (bincount when compact, else unique)."""
    if idx.size == 0:
        return 0
    top = int(idx.max())
    if top <= 4 * idx.size + 1024:
        return int(np.count_nonzero(np.bincount(idx, minlength=top + 1)))
    return int(np.unique(idx).size)


@dataclass(frozen=True)
class CentreObservations:
    """Observed sphere-centre projections of one stage position.

    Attributes
    ----------
    uv_px : ndarray of shape (Q, 2)
        Observed centre (col, row) [px], OpenCV convention (pixel (c, r)
        centred at (c, r)).
    sphere_index : ndarray of shape (Q,), int
        Row of the sphere in the reference object's centre array
        ``centres_of_m`` (0-based). Not the simulator's id: whatever the
        identification step assigned.
    alpha_rad : ndarray of shape (Q,)
        Rotary-stage angle reported with the projection [rad].
    view_index : ndarray of shape (Q,), int
        Index of the projection the observation comes from (0-based,
        acquisition order). Observations of one image share it.
    stamp_ns : ndarray of shape (Q,), int64, or None
        ``header.stamp`` of the projection [ns], if known.
    sigma_px : ndarray of shape (Q,) or None
        Standard uncertainty of each coordinate [px], if the detector
        reports one. ``None`` means "equal, unknown": the solvers then
        estimate it from the residuals.
    minor_axis_px : ndarray of shape (Q,) or None
        Semi-minor axis of the shadow ellipse the centre was fitted to [px].
        With it the solvers model the observed point as the ellipse centre
        (not the projection of the sphere centre; see ct_model.py); None
        means the observations ARE centre projections.
    systematic_px : ndarray of shape (Q, 2) or None
        One standard deviation of an error pattern shared by every
        observation of the recording [px] (fully correlated: one unknown
        factor scales all of them; detect.FrameDetections.systematic_px). The
        solvers propagate it into the covariance; it does not enter the fit.

    The constructor converts and validates everything (float64 / int64,
    shapes, NaN / inf, negative indices) and raises ``ValueError`` naming the
    offending field. Arrays are stored read-only.
    """

    uv_px: np.ndarray
    sphere_index: np.ndarray
    alpha_rad: np.ndarray
    view_index: np.ndarray
    stamp_ns: np.ndarray | None = None
    sigma_px: np.ndarray | None = None
    minor_axis_px: np.ndarray | None = None
    systematic_px: np.ndarray | None = None

    def __post_init__(self):
        uv = np.asarray(self.uv_px, dtype=float)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ValueError(f"uv_px must have shape (Q, 2), got {uv.shape}")
        q = uv.shape[0]
        if not np.all(np.isfinite(uv)):
            raise ValueError("uv_px contains NaN or inf")

        def as_index(name, v):
            a = np.asarray(v)
            if a.shape != (q,):
                raise ValueError(f"{name} must have shape ({q},), got {a.shape}")
            if a.size and not np.issubdtype(a.dtype, np.integer):
                af = a.astype(float)
                if not np.all(np.isfinite(af)) or np.any(af != np.round(af)):
                    raise ValueError(f"{name} must hold integers")
            a = a.astype(np.int64)
            if a.size and a.min() < 0:
                raise ValueError(f"{name} must be >= 0, got min {a.min()}")
            return a

        si = as_index("sphere_index", self.sphere_index)
        vi = as_index("view_index", self.view_index)
        al = np.asarray(self.alpha_rad, dtype=float)
        if al.shape != (q,):
            raise ValueError(f"alpha_rad must have shape ({q},), got {al.shape}")
        if not np.all(np.isfinite(al)):
            raise ValueError("alpha_rad contains NaN or inf")
        st = None
        if self.stamp_ns is not None:
            st = np.asarray(self.stamp_ns)
            if st.shape != (q,):
                raise ValueError(f"stamp_ns must have shape ({q},), got {st.shape}")
            if st.size and not np.issubdtype(st.dtype, np.integer):
                raise ValueError("stamp_ns must be integer nanoseconds")
            st = st.astype(np.int64)
        sg = None
        if self.sigma_px is not None:
            sg = np.asarray(self.sigma_px, dtype=float)
            if sg.shape != (q,):
                raise ValueError(f"sigma_px must have shape ({q},), got {sg.shape}")
            if not np.all(np.isfinite(sg)) or np.any(sg <= 0):
                raise ValueError("sigma_px must be finite and > 0")
        mb = None
        if self.minor_axis_px is not None:
            mb = np.asarray(self.minor_axis_px, dtype=float)
            if mb.shape != (q,):
                raise ValueError(f"minor_axis_px must have shape ({q},), got {mb.shape}")
            if not np.all(np.isfinite(mb)) or np.any(mb <= 0):
                raise ValueError("minor_axis_px must be finite and > 0")
        sy = None
        if self.systematic_px is not None:
            sy = np.asarray(self.systematic_px, dtype=float)
            if sy.shape != (q, 2):
                raise ValueError(f"systematic_px must have shape ({q}, 2), got {sy.shape}")
            if not np.all(np.isfinite(sy)):
                raise ValueError("systematic_px contains NaN or inf")
        for name, val in (("uv_px", uv), ("sphere_index", si), ("alpha_rad", al),
                          ("view_index", vi), ("stamp_ns", st), ("sigma_px", sg), ("minor_axis_px", mb),
                          ("systematic_px", sy)):
            object.__setattr__(self, name, None if val is None else _readonly(val))

    # ------------------------------------------------------------------ helpers
    @classmethod
    def from_views(cls, uv_px_per_view, sphere_index_per_view, alpha_rad_per_view,
                   stamp_ns_per_view=None, sigma_px_per_view=None,
                   minor_axis_px_per_view=None, systematic_px_per_view=None) -> "CentreObservations":
        """Build from per-projection lists (what a detector produces image by image).

        Parameters
        ----------
        uv_px_per_view : sequence of array_like of shape (Q_j, 2)
        sphere_index_per_view : sequence of array_like of shape (Q_j,)
        alpha_rad_per_view : array_like of shape (M,)
            One rotary angle per projection [rad].
        stamp_ns_per_view : array_like of shape (M,), int, optional
        sigma_px_per_view : sequence of array_like of shape (Q_j,), optional
        minor_axis_px_per_view : sequence of array_like of shape (Q_j,), optional
        systematic_px_per_view : sequence of array_like of shape (Q_j, 2), optional
        """
        m = len(uv_px_per_view)
        if len(sphere_index_per_view) != m or len(np.atleast_1d(alpha_rad_per_view)) != m:
            raise ValueError("per-view sequences must all have the same length")
        uv = [np.asarray(u, dtype=float).reshape(-1, 2) for u in uv_px_per_view]
        counts = np.array([len(u) for u in uv], dtype=np.int64)
        view = np.repeat(np.arange(m), counts)
        alpha = np.repeat(np.asarray(alpha_rad_per_view, dtype=float), counts)
        stamps = None if stamp_ns_per_view is None else np.repeat(
            np.asarray(stamp_ns_per_view, dtype=np.int64), counts)
        sig = None if sigma_px_per_view is None else np.concatenate(
            [np.asarray(s, dtype=float).reshape(-1) for s in sigma_px_per_view])
        minor = None if minor_axis_px_per_view is None else np.concatenate(
            [np.asarray(s, dtype=float).reshape(-1) for s in minor_axis_px_per_view])
        syst = None if systematic_px_per_view is None or not m else np.concatenate(
            [np.asarray(s, dtype=float).reshape(-1, 2) for s in systematic_px_per_view])
        return cls(uv_px=np.concatenate(uv) if m else np.zeros((0, 2)),
                   sphere_index=np.concatenate([np.asarray(s).reshape(-1) for s in sphere_index_per_view]).astype(np.int64) if m else np.zeros(0, np.int64),
                   alpha_rad=alpha, view_index=view, stamp_ns=stamps, sigma_px=sig, minor_axis_px=minor,
                   systematic_px=syst)

    @property
    def n_obs(self) -> int:
        """Number of observations Q."""
        return int(self.uv_px.shape[0])

    @functools.cached_property
    def n_views(self) -> int:
        """Number of distinct projections (computed once: the arrays are read-only)."""
        return _n_distinct(self.view_index)

    @functools.cached_property
    def n_spheres_seen(self) -> int:
        """Number of distinct spheres observed (computed once)."""
        return _n_distinct(self.sphere_index)

    def select(self, mask) -> "CentreObservations":
        """Subset by a boolean mask or index array of shape (Q,) / (n,)."""
        m = np.asarray(mask)
        pick = lambda a: None if a is None else a[m]
        return CentreObservations(self.uv_px[m], self.sphere_index[m], self.alpha_rad[m],
                                  self.view_index[m], pick(self.stamp_ns), pick(self.sigma_px),
                                  pick(self.minor_axis_px), pick(self.systematic_px))

    def first_view(self) -> "CentreObservations":
        """Observations of the first projection (smallest view_index): the paper's j = 1."""
        if self.n_obs == 0:
            return self
        return self.select(self.view_index == self.view_index.min())

    def check_spheres(self, n_spheres: int) -> None:
        """Raise ValueError if a sphere_index does not address ``n_spheres`` centres."""
        if self.n_obs and self.sphere_index.max() >= n_spheres:
            raise ValueError(f"sphere_index {self.sphere_index.max()} out of range for "
                             f"{n_spheres} reference centres")
