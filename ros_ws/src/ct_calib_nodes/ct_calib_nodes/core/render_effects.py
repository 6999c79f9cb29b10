"""Hidden physics for the CT renderer beyond the switches built into render.py.

Every effect here is OFF unless listed in ``RenderSettings.effects``; the
solvers and the discrepancy engine are never told about them. They exist to
make recordings in which one physical effect the solvers do not model is
concealed (issue 11: prove that the engine finds, names and models it).

An effect acts at up to three places of the image formation (render.py calls
the hooks below):

* ``angle_delta(alpha)``: the true rotary angle is ``alpha + delta`` [rad];
* ``place(scene, alpha, t)``: moves the placed scene in {DF} (focal spot,
  sphere centres, tube axis points) at acquisition time ``t`` [s];
* ``landing_from_recorded(xy, source)`` / ``recorded_from_landing(xy, source)``:
  the map between the point where a ray from the focal spot ``source`` (3,)
  crosses the plane z = 0 and the position the detector records it at
  (metric {DF}, from the detector centre).

Time ``t`` is the renderer's ``time_s``. The drifts below are linear in time
from ``t_ref_s``; give the scan duration so that ``total`` is the change over
the scan: ``rate = total / duration``.

All geometry is exact (no small-angle shortcuts except where stated): these
are the TRUTH, and the engine's catalogue (ct_discrepancy.py) models them
independently, at the level of centre projections.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .geometry import rot_axis_angle


@dataclass(frozen=True)
class Scene:
    """What the hooks may move: focal spot (3,), sphere centres (N, 3), extra object points (M, 3)."""

    source_df_m: np.ndarray
    stage_df_m: np.ndarray
    axis_df: np.ndarray
    centres_df_m: np.ndarray
    extra_df_m: np.ndarray | None


class RenderEffect:
    """Base class: every hook is the identity."""

    name = "effect"

    def angle_delta(self, alpha_rad: float) -> float:
        return 0.0

    def place(self, scene: Scene, alpha_rad: float, time_s: float) -> Scene:
        return scene

    def landing_from_recorded(self, xy_m, source_df_m):
        return xy_m

    def recorded_from_landing(self, xy_m, source_df_m):
        return xy_m


def _beam_axes(scene: Scene):
    """Unit vectors: b (source -> stage), h = axis x b (horizontal, across the beam)."""
    b = scene.stage_df_m - scene.source_df_m
    b = b / np.linalg.norm(b)
    h = np.cross(scene.axis_df, b)
    return b, h / np.linalg.norm(h)


def _move_object(scene: Scene, fn) -> Scene:
    extra = None if scene.extra_df_m is None else fn(scene.extra_df_m)
    return replace(scene, centres_df_m=fn(scene.centres_df_m), extra_df_m=extra)


@dataclass(frozen=True)
class EncoderHarmonic(RenderEffect):
    """Rotary encoder error of order n: ``alpha_true = alpha + A sin(n alpha + phi)``."""

    order: int = 2
    amplitude_rad: float = 0.0
    phase_rad: float = 0.0
    name = "encoder_harmonic"

    def angle_delta(self, alpha_rad):
        return float(self.amplitude_rad * np.sin(self.order * alpha_rad + self.phase_rad))


@dataclass(frozen=True)
class RotaryTiltError(RenderEffect):
    """Tilt error motion of the rotary axis, once per revolution, fixed in space.

    At reported angle alpha the object is turned about the stage point by
    ``e_h(alpha) = a_h cos(alpha) + b_h sin(alpha)`` about the horizontal
    across-beam axis h and by ``e_b(alpha)`` (same form) about the beam b.
    """

    h_cos_rad: float = 0.0
    h_sin_rad: float = 0.0
    b_cos_rad: float = 0.0
    b_sin_rad: float = 0.0
    name = "rotary_tilt_error"

    def place(self, scene, alpha_rad, time_s):
        b, h = _beam_axes(scene)
        c, s = np.cos(alpha_rad), np.sin(alpha_rad)
        eh = self.h_cos_rad * c + self.h_sin_rad * s
        eb = self.b_cos_rad * c + self.b_sin_rad * s
        rot = rot_axis_angle(b, eb) @ rot_axis_angle(h, eh)
        r = scene.stage_df_m
        return _move_object(scene, lambda p: (p - r) @ rot.T + r)


@dataclass(frozen=True)
class RotaryRunout(RenderEffect):
    """Radial (across the beam) and axial error motion of the rotary axis, once per revolution, fixed in space.

    The object is displaced by ``(c_h cos alpha + s_h sin alpha) h + (c_a cos alpha + s_a sin alpha) axis`` [m].
    """

    h_cos_m: float = 0.0
    h_sin_m: float = 0.0
    axial_cos_m: float = 0.0
    axial_sin_m: float = 0.0
    name = "rotary_runout"

    def place(self, scene, alpha_rad, time_s):
        _, h = _beam_axes(scene)
        c, s = np.cos(alpha_rad), np.sin(alpha_rad)
        d = (self.h_cos_m * c + self.h_sin_m * s) * h + (self.axial_cos_m * c + self.axial_sin_m * s) * scene.axis_df
        return _move_object(scene, lambda p: p + d)


@dataclass(frozen=True)
class StageDrift(RenderEffect):
    """The stage (and object) drift linearly in time: ``+ rate (t - t_ref)`` in {DF} [m/s]."""

    rate_m_per_s: tuple = (0.0, 0.0, 0.0)
    t_ref_s: float = 0.0
    name = "stage_drift"

    def place(self, scene, alpha_rad, time_s):
        d = np.asarray(self.rate_m_per_s, dtype=float) * (time_s - self.t_ref_s)
        return _move_object(scene, lambda p: p + d)


@dataclass(frozen=True)
class ObjectExpansion(RenderEffect):
    """The object warms during the scan: lengths scale by ``1 + rate (t - t_ref)`` about its centroid."""

    rate_per_s: float = 0.0
    t_ref_s: float = 0.0
    name = "object_thermal_expansion"

    def place(self, scene, alpha_rad, time_s):
        s = 1.0 + self.rate_per_s * (time_s - self.t_ref_s)
        cen = scene.centres_df_m.mean(axis=0)
        return _move_object(scene, lambda p: cen + s * (p - cen))


@dataclass(frozen=True)
class DetectorDrift(RenderEffect):
    """The detector slides in its own plane linearly in time (rate (2,) [m/s] along {DF} X, Y).

    Rendered as the equivalent motion of everything else by the opposite amount.
    """

    rate_m_per_s: tuple = (0.0, 0.0)
    t_ref_s: float = 0.0
    name = "detector_drift"

    def place(self, scene, alpha_rad, time_s):
        r = np.asarray(self.rate_m_per_s, dtype=float)
        d = -np.array([r[0], r[1], 0.0]) * (time_s - self.t_ref_s)
        moved = _move_object(scene, lambda p: p + d)
        return replace(moved, source_df_m=scene.source_df_m + d, stage_df_m=scene.stage_df_m + d)


@dataclass(frozen=True)
class DetectorBow(RenderEffect):
    """The panel is not flat: its surface lies ``h(x, y) = sag_x (x/X)^2 + sag_y (y/Y)^2`` behind the plane
    z = 0 (away from the source), X, Y the half width and height [m]. A ray is recorded where it meets the
    surface, at in-plane position x_rec (exact: the pixel grid follows the surface, its arc length differs
    from the in-plane distance by h'^2 / 2 ~ 1e-5 relative); it crossed z = 0 at
    ``P + (x_rec - P) D / (D + h(x_rec))`` with P the principal point (the source's x, y) and D = -S_z. A sag
    of 0.72 mm at the corner of a 410 mm panel at D = 1.05 m displaces the corner by about 0.5 px (0.4 mm
    pixels)."""

    sag_x_m: float = 0.0
    sag_y_m: float = 0.0
    half_width_m: float = 0.2048
    half_height_m: float = 0.2048
    name = "detector_bow"

    def _h(self, xy):
        return (self.sag_x_m * (xy[..., 0] / self.half_width_m) ** 2
                + self.sag_y_m * (xy[..., 1] / self.half_height_m) ** 2)

    def landing_from_recorded(self, xy_m, source_df_m):
        xy = np.asarray(xy_m, dtype=float)
        p, d = np.asarray(source_df_m[:2], dtype=float), -float(source_df_m[2])
        return p + (xy - p) * (d / (d + self._h(xy)))[..., None]

    def recorded_from_landing(self, xy_m, source_df_m):
        xy = np.asarray(xy_m, dtype=float)
        p, d = np.asarray(source_df_m[:2], dtype=float), -float(source_df_m[2])
        rec = xy
        for _ in range(8):
            rec = p + (xy - p) * ((d + self._h(rec)) / d)[..., None]
        return rec


def check_effects(effects) -> tuple:
    effects = tuple(effects)
    for e in effects:
        if not isinstance(e, RenderEffect):
            raise ValueError(f"RenderSettings.effects must hold RenderEffect instances, got {type(e).__name__}")
    return effects


# ------------------------------------------------------------------ hooks called by render.py
def angle_delta(effects, alpha_rad: float) -> float:
    return float(sum(e.angle_delta(alpha_rad) for e in effects))


def place(effects, geom, centres_df, extra_df, alpha_rad: float, time_s: float):
    """Apply the effects to a placed frame; returns (geom with the moved source, centres, extra)."""
    if not effects:
        return geom, centres_df, extra_df
    sc = Scene(np.asarray(geom.source_df_m, float), np.asarray(geom.stage_df_m, float),
               np.asarray(geom.axis_df, float), np.asarray(centres_df, float),
               None if extra_df is None else np.asarray(extra_df, float))
    for e in effects:
        sc = e.place(sc, alpha_rad, time_s)
    return replace(geom, source_df_m=sc.source_df_m), sc.centres_df_m, sc.extra_df_m


def landing_from_recorded(effects, xy_m, source_df_m):
    for e in reversed(effects):
        xy_m = e.landing_from_recorded(xy_m, source_df_m)
    return xy_m


def recorded_from_landing(effects, xy_m, source_df_m):
    for e in effects:
        xy_m = e.recorded_from_landing(xy_m, source_df_m)
    return xy_m
