"""Optional physics terms that extend the base CT projection model.

A model is the base geometry of geometry.py (13 static parameters, or the 6
error-motion parameters) plus any number of TERMS. A term contributes named
parameters with units and acts at one STAGE of the projection pipeline,
returning its correction and the derivatives the solver needs for the
chain rule. The solver never knows which term it is running: adding a term
is writing one class here (or anywhere), not touching the solver.

Stages (the pipeline order in ct_model.py):

``"angle"``
    Corrects the reported rotary angle of each observation:
    ``alpha_true = alpha + delta(params; alpha, stamp)``. Implement
    :meth:`Term.angle_delta` returning ``delta`` (Q,) [rad] and
    ``d delta / d params`` (Q, p).
``"image"``
    Corrects the ideal intersection point on the detector plane, in metric
    {DF} coordinates: ``xy_true = xy + delta(params; xy, obs)``. Implement
    :meth:`Term.image_delta` returning ``delta`` (Q, 2) [m],
    ``d delta / d params`` (Q, 2, p) and ``d delta / d xy`` (Q, 2, 2).

A focal-spot drift term (source moving with time stamp) would need a
``"source"`` stage; the pipeline does not have it yet (see doc/ct_core.md).

In the error-motion solve the terms are applied with the values fitted by
the static solve and held fixed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STAGES = ("angle", "image")


class Term:
    """Base class of an optional model term (see module docstring).

    Subclasses set ``name``, ``stage``, ``param_names``, ``param_units`` and
    implement the method of their stage. ``x0`` gives the start value of the
    parameters (default zeros: a term that is absent).
    """

    name: str = "term"
    stage: str = "angle"
    param_names: tuple = ()
    param_units: tuple = ()

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    def x0(self) -> np.ndarray:
        """Start values of the term's parameters, shape (p,)."""
        return np.zeros(self.n_params)

    def angle_delta(self, params, alpha_rad, obs):
        """Angle correction: (delta (Q,) [rad], d delta / d params (Q, p))."""
        raise NotImplementedError(f"{type(self).__name__} has no 'angle' stage")

    def image_delta(self, params, xy_m, obs):
        """Image correction: (delta (Q, 2) [m], d/d params (Q, 2, p), d/d xy (Q, 2, 2))."""
        raise NotImplementedError(f"{type(self).__name__} has no 'image' stage")


@dataclass(frozen=True)
class EncoderEccentricity(Term):
    """Once-per-revolution rotary encoder error (eccentric encoder disc).

    ``alpha_true = alpha + a cos(alpha) + b sin(alpha)`` with ``a``, ``b``
    [rad]. A constant angle offset is not included: it is indistinguishable
    from the object orientation rho_Y.
    """

    name: str = "encoder_eccentricity"
    stage: str = "angle"
    param_names: tuple = ("ecc_a", "ecc_b")
    param_units: tuple = ("rad", "rad")

    def angle_delta(self, params, alpha_rad, obs):
        a, b = float(params[0]), float(params[1])
        c, s = np.cos(alpha_rad), np.sin(alpha_rad)
        return a * c + b * s, np.stack([c, s], axis=1)


@dataclass(frozen=True)
class RadialDistortion(Term):
    """Radial detector distortion about the detector centre.

    ``xy_true = xy (1 + k1 r^2)`` with ``r^2 = (x^2 + y^2) / scale^2`` and
    ``k1`` dimensionless; ``scale_m`` (fixed, default 0.2 m, about half a
    detector side) keeps k1 of order one.
    """

    scale_m: float = 0.2
    name: str = "radial_distortion"
    stage: str = "image"
    param_names: tuple = ("k1",)
    param_units: tuple = ("1",)

    def image_delta(self, params, xy_m, obs):
        k1 = float(params[0])
        s2 = self.scale_m ** 2
        x, y = xy_m[:, 0], xy_m[:, 1]
        r2 = (x * x + y * y) / s2
        delta = xy_m * (k1 * r2)[:, None]
        d_par = (xy_m * r2[:, None])[:, :, None]
        # d (x k1 r2) / dx = k1 r2 + x k1 2x / s2, etc.
        d_xy = np.empty((len(x), 2, 2))
        d_xy[:, 0, 0] = k1 * r2 + 2 * k1 * x * x / s2
        d_xy[:, 0, 1] = 2 * k1 * x * y / s2
        d_xy[:, 1, 0] = 2 * k1 * x * y / s2
        d_xy[:, 1, 1] = k1 * r2 + 2 * k1 * y * y / s2
        return delta, d_par, d_xy


def check_terms(terms) -> tuple:
    """Validate a sequence of terms; returns them as a tuple."""
    terms = tuple(terms)
    names = set()
    for t in terms:
        if not isinstance(t, Term):
            raise ValueError(f"terms must be Term instances, got {type(t).__name__}")
        if t.stage not in STAGES:
            raise ValueError(f"term {t.name!r} has unknown stage {t.stage!r}; known: {STAGES}")
        if len(t.param_names) != len(t.param_units):
            raise ValueError(f"term {t.name!r}: param_names and param_units differ in length")
        for n in t.param_names:
            if n in names:
                raise ValueError(f"duplicate term parameter name {n!r}")
            names.add(n)
    return terms
