"""CT adapter of the discrepancy engine: catalogue of physical terms, datasets, refit, verdict.

Input: the observations of the first stage position (``CentreObservations``,
as the static solve gets them from a recording) and the nominal static
calibration (``StaticResult``). Nothing else: no truth, no simulator state.

The catalogue (:data:`CATALOGUE`) is a list of :class:`CtTerm`; each term is a
small function that changes one stage of an independent forward model of the
observed centre (angle -> object placement -> source -> central projection
-> ellipse centre -> detector recording) with named parameters in SI units.
The engine uses each term's linearised basis (central differences of that
model, the calibration's analytic Jacobian for the 13 nominal parameters);
the accepted terms are then refitted by Gauss-Newton on the exact model.
Add a term: append one ``CtTerm`` with its function and its docs.

Time: every drift is linear in the normalised scan time
``tau = (t - t_mid) / T`` (T = last - first stamp), its parameters being the
change over the whole scan.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .ct_model import StaticKernel
from .discrepancy import (BIC_THRESHOLD, Candidate, Dataset, _orth, analyse, locate, required_noncentrality,
                          finding_entry, sigma_from_chi2, unexplained_entries, verdict_sentence)
from .geometry import STATIC_PARAM_NAMES, DetectorSpec, motion_rotation, static_to_detector_frame
from .observations import CentreObservations

ARCSEC = np.pi / (180.0 * 3600.0)


# --------------------------------------------------------------------------- forward model
@dataclass
class _State:
    alpha: np.ndarray      # (Q,) true rotary angle
    tau: np.ndarray        # (Q,) normalised scan time
    C: np.ndarray          # (Q, 3) sphere centres in {DF}
    S: np.ndarray          # (Q, 3) focal spot in {DF}
    R: np.ndarray          # (3,) stage point
    axis: np.ndarray       # (3,) rotation axis
    cen: np.ndarray        # (Q, 3) object centroid in {DF}
    xy: np.ndarray | None = None   # (Q, 2) point on the detector [m]
    P: np.ndarray | None = None    # (Q, 2) principal point
    D: np.ndarray | None = None    # (Q,) source-detector distance
    b2: np.ndarray | None = None   # (Q,) squared semi-minor axis of the shadow [m^2] or None
    half: tuple = (0.2, 0.2)


def _rotate(v, axis, ca, sa):
    """Rodrigues rotation of rows of v (Q,3) about the unit axis by angles with cos ca, sin sa (Q,)."""
    cr = np.cross(axis, v)
    dot = v @ axis
    return v * ca[:, None] + cr * sa[:, None] + np.outer(dot * (1.0 - ca), axis)


def _beam(st: _State):
    b = st.R - st.S.mean(axis=0)
    b = b / np.linalg.norm(b)
    h = np.cross(st.axis, b)
    return b, h / np.linalg.norm(h)


# each term: f(theta, st) modifies st in place at its stage
def _t_encoder1(th, st):
    st.alpha = st.alpha + th[0] * np.cos(st.alpha) + th[1] * np.sin(st.alpha)


def _t_encoder2(th, st):
    st.alpha = st.alpha + th[0] * np.cos(2 * st.alpha) + th[1] * np.sin(2 * st.alpha)


def _t_radial_runout(th, st):
    _, h = _beam(st)
    st.C = st.C + np.outer(th[0] * np.cos(st.alpha) + th[1] * np.sin(st.alpha), h)


def _t_axial_runout(th, st):
    st.C = st.C + np.outer(th[0] * np.cos(st.alpha) + th[1] * np.sin(st.alpha), st.axis)


def _t_tilt(th, st):
    _, h = _beam(st)
    eh = th[0] * np.cos(st.alpha) + th[1] * np.sin(st.alpha)
    st.C = st.C + eh[:, None] * np.cross(h, st.C - st.R)


def _t_stage_drift(th, st):
    st.C = st.C + np.outer(st.tau, [th[0], th[1], 0.0])


def _t_stage_drift_axial(th, st):
    st.C = st.C + np.outer(st.tau, [0.0, 0.0, th[0]])


def _t_expansion(th, st):
    st.C = st.cen + (1.0 + th[0] * st.tau)[:, None] * (st.C - st.cen)


def _t_focal_lateral(th, st):
    st.S = st.S + np.outer(st.tau, [th[0], th[1], 0.0])


def _t_focal_axial(th, st):
    st.S = st.S + np.outer(st.tau, [0.0, 0.0, th[0]])


def _t_ellipse(th, st):
    if st.b2 is not None:
        st.xy = st.xy + (th[0] * st.b2 / st.D ** 2)[:, None] * (st.xy - st.P)


def _t_bow(th, st):
    x, y = st.xy[:, 0], st.xy[:, 1]
    h = th[0] * (x / st.half[0]) ** 2 + th[1] * (y / st.half[1]) ** 2
    st.xy = st.xy + (h / st.D)[:, None] * (st.xy - st.P)


def _t_distortion(th, st):
    st.xy = st.xy * (1.0 + th[0] * np.sum(st.xy ** 2, axis=1))[:, None]


def _t_detector_drift(th, st):
    st.xy = st.xy - np.outer(st.tau, th[:2])


@dataclass(frozen=True)
class CtTerm:
    """One physical extension of the CT projection model.

    id, name, mechanism (one sentence), stage ("angle", "object", "source", "ellipse", "image"),
    param_names, param_units (SI), fd_step (SI, per parameter), display (unit, factor from SI),
    needs_time, reveal_by (the acquisition that shows it), fn(theta, state).
    """

    id: str
    name: str
    mechanism: str
    stage: str
    param_names: tuple
    param_units: tuple
    fd_step: tuple
    display_unit: str
    display_factor: float
    reveal_by: str
    fn: object
    needs_time: bool = False
    plausible_max: float = np.inf      # [display unit] larger fitted values are not this physics


CATALOGUE = (
    CtTerm("focal_spot_drift", "focal-spot drift across the beam",
           "the electron beam's spot on the target wanders as the tube heats, moving every shadow by (1 - M) times "
           "its displacement, in proportion to each sphere's magnification", "source",
           ("dSx_scan", "dSy_scan"), ("m", "m"), (2e-6, 2e-6), "um", 1e6,
           "a longer scan or repeated projections at the start and end (a drift shows as a difference); against a "
           "stage or detector drift, a higher magnification (object near the source) with more projections",
           _t_focal_lateral, True),
    CtTerm("focal_spot_drift_axial", "focal-spot drift along the beam",
           "the spot moves towards or away from the detector during the scan, changing the magnification with time",
           "source", ("dSz_scan",), ("m",), (5e-6,), "um", 1e6,
           "a longer scan, spheres spread wide on the detector (the magnification change scales with field position)",
           _t_focal_axial, True),
    CtTerm("detector_drift", "detector drift in its plane",
           "the panel or its mount creeps during the scan, shifting every recorded position equally",
           "image", ("dDx_scan", "dDy_scan"), ("m", "m"), (2e-6, 2e-6), "um", 1e6,
           "spheres spread in depth (magnification) so that a detector shift and a source shift differ, or a "
           "fiducial fixed to the detector", _t_detector_drift, True),
    CtTerm("stage_drift", "stage drift during the scan",
           "the rotary stage and object creep (thermal drift of the axes), moving the object linearly in time",
           "object", ("dX_scan", "dY_scan"), ("m", "m"), (2e-6, 2e-6), "um", 1e6,
           "a longer scan or a repeated first projection at the end; a shift of the source instead moves each shadow "
           "by (1 - M) rather than M times, so spheres spread in depth separate the two: a higher magnification "
           "(object near the source) with more projections", _t_stage_drift, True, 500.0),
    CtTerm("stage_drift_axial", "stage drift along the beam during the scan",
           "the object creeps towards or away from the source, changing the magnification with time",
           "object", ("dZ_scan",), ("m",), (5e-6,), "um", 1e6,
           "a longer scan; a temperature log, or the object raised off the principal ray (an expansion scales about "
           "the object's centre, an axial drift about the principal point), separates it from thermal expansion",
           _t_stage_drift_axial, True, 2000.0),
    CtTerm("object_thermal_expansion", "thermal expansion of the object during the scan",
           "the reference object warms or cools during the scan, its sphere distances growing in time (a constant "
           "scale is degenerate with z_R and needs a temperature reading)", "object",
           ("expansion_scan",), ("1",), (2e-6,), "ppm", 1e6,
           "a scan during a temperature change, a temperature log of the object; the object raised off the principal "
           "ray (20 mm is enough) separates it from an axial drift of the source or stage", _t_expansion, True),
    CtTerm("encoder_eccentricity", "rotary encoder eccentricity (once per revolution)",
           "the encoder disc is off-centre on the spindle, so the reported angle is off by a sine of the angle",
           "angle", ("ecc_a", "ecc_b"), ("rad", "rad"), (5e-6, 5e-6), "arcsec", 1.0 / ARCSEC,
           "a full revolution with spheres at a large radius", _t_encoder1),
    CtTerm("encoder_second_harmonic", "rotary encoder error, twice per revolution",
           "an elliptical encoder scale or a tilted read head gives an angle error with two periods per turn",
           "angle", ("enc2_a", "enc2_b"), ("rad", "rad"), (5e-6, 5e-6), "arcsec", 1.0 / ARCSEC,
           "a full revolution with spheres at a large radius", _t_encoder2),
    CtTerm("rotary_radial_runout", "radial error motion of the rotary axis",
           "the spindle moves across the beam once per revolution (bearing runout fixed in space)",
           "object", ("runout_c", "runout_s"), ("m", "m"), (1e-6, 1e-6), "um", 1e6,
           "a full revolution at a higher magnification (the shadows move by M times the runout); a sphere near "
           "the axis", _t_radial_runout),
    CtTerm("rotary_axial_runout", "axial error motion of the rotary axis",
           "the table lifts and sinks once per revolution (axial runout)", "object",
           ("axial_c", "axial_s"), ("m", "m"), (1e-6, 1e-6), "um", 1e6,
           "a full revolution", _t_axial_runout),
    CtTerm("rotary_tilt_error", "tilt error motion (wobble) of the rotary axis",
           "the axis tilts once per revolution about the horizontal across-beam direction (fixed in space), moving "
           "spheres along the beam and vertically in proportion to their height and depth (a tilt turning with the "
           "table is the object's pose and is absorbed by it)", "object", ("tilt_h_c", "tilt_h_s"),
           ("rad",) * 2, (5e-6,) * 2, "arcsec", 1.0 / ARCSEC,
           "spheres spread in height (a tall object) over a full revolution", _t_tilt),
    CtTerm("detector_bow", "detector bow (panel not flat)",
           "the panel surface lies behind its plane by a sag growing with the square of the distance from the "
           "centre; rays are recorded further out by sag x (position - principal point) / distance", "image",
           ("sag_x_edge", "sag_y_edge"), ("m", "m"), (5e-5, 5e-5), "mm", 1e3,
           "shadows over the whole field, including the corners", _t_bow),
    CtTerm("detector_distortion", "radial distortion of the detector",
           "the recorded position is scaled by 1 + k1 r^2 about the detector centre (fibre-optic taper, "
           "image-intensifier or scintillator geometry)", "image", ("k1",), ("1/m^2",), (1e-3,), "1/m^2", 1.0,
           "shadows over the whole field, including the corners", _t_distortion),
    CtTerm("ellipse_centre_bias", "ellipse-centre bias unlike the model",
           "the detected centre lies c (b/D)^2 further from the principal point than the ellipse-centre model says "
           "(c = -1: the detector reports centre projections, not ellipse centres)", "ellipse", ("c",), ("1",),
           (0.5,), "1", 1.0, "large spheres close to the source, far from the principal point", _t_ellipse,
           False, 3.0),
)
CATALOGUE_BY_ID = {t.id: t for t in CATALOGUE}


def scan_time(obs: CentreObservations):
    """Normalised scan time tau (Q,) and the scan duration [s], or (zeros, 0) without stamps."""
    if obs.stamp_ns is None or obs.n_obs == 0:
        return np.zeros(obs.n_obs), 0.0
    t = (obs.stamp_ns - obs.stamp_ns.min()).astype(float) * 1e-9
    span = float(t.max())
    if span <= 0:
        return np.zeros(obs.n_obs), 0.0
    return (t - 0.5 * span) / span, span


def predict_px(w, obs: CentreObservations, centres_of_m, detector: DetectorSpec, thetas: dict | None = None, *,
               motion=None, tau=None):
    """Modelled observation (col, row) (Q, 2) [px] of the nominal model extended by catalogue terms.

    ``thetas``: term id -> parameters (SI). With none it equals the static kernel's model (tested).
    ``motion``: the stage's error motion (6,) of this position relative to the first (geometry.sphere_centres_df);
    ``tau``: the normalised time of every observation for the time terms (default: this scan's, scan_time).
    """
    thetas = thetas or {}
    terms = [(CATALOGUE_BY_ID[k], np.asarray(v, dtype=float)) for k, v in thetas.items()]
    geom = static_to_detector_frame(np.asarray(w[:13], dtype=float), centres_of_m)
    tau = scan_time(obs)[0] if tau is None else np.asarray(tau, dtype=float)
    q = obs.n_obs
    r_df, axis, c_df = np.asarray(geom.stage_df_m, float), np.asarray(geom.axis_df, float), geom.centres_df_m
    if motion is not None:                                  # eqs 8-10: the stage moved and turned
        m = np.asarray(motion, dtype=float)
        g = motion_rotation(m[3], m[4], m[5])
        c_df = (c_df - r_df) @ g.T + r_df + m[:3]
        r_df, axis = r_df + m[:3], g @ axis
    c0 = c_df[obs.sphere_index]
    st = _State(alpha=np.asarray(obs.alpha_rad, dtype=float).copy(), tau=tau, C=None,
                S=np.tile(geom.source_df_m, (q, 1)), R=r_df, axis=axis, cen=None,
                half=(detector.cols * detector.pixel_pitch_m / 2.0, detector.rows * detector.pixel_pitch_m / 2.0))
    for t, th in terms:
        if t.stage == "angle":
            t.fn(th, st)
    ca, sa = np.cos(st.alpha), np.sin(st.alpha)
    st.C = st.R + _rotate(c0 - st.R, st.axis, ca, sa)
    st.cen = st.R + _rotate(np.tile(c_df.mean(axis=0) - st.R, (q, 1)), st.axis, ca, sa)
    for stage in ("object", "source"):
        for t, th in terms:
            if t.stage == stage:
                t.fn(th, st)
    s, c = st.S, st.C
    lam = -s[:, 2] / (c[:, 2] - s[:, 2])
    st.xy = s[:, :2] + lam[:, None] * (c[:, :2] - s[:, :2])
    st.P = s[:, :2]
    st.D = -s[:, 2]
    if obs.minor_axis_px is not None:
        st.b2 = (obs.minor_axis_px * detector.pixel_pitch_m) ** 2
        st.xy = st.P + (1.0 + st.b2 / st.D ** 2)[:, None] * (st.xy - st.P)
    for stage in ("ellipse", "image"):
        for t, th in terms:
            if t.stage == stage:
                t.fn(th, st)
    col, row = detector.pixels_from_metric(st.xy[:, 0], st.xy[:, 1])
    return np.stack([col, row], axis=1)


def _blocked(uv):
    return np.concatenate([uv[:, 0], uv[:, 1]])


def term_basis(term: CtTerm, w, obs, centres_of_m, detector, base=None):
    """d modelled / d theta (2Q, p), blocked, by central differences at theta = 0 (plus ``base`` terms)."""
    base = dict(base or {})
    p = len(term.param_names)
    cols = []
    for k in range(p):
        th = np.zeros(p)
        h = term.fd_step[k]
        th[k] = h
        up = predict_px(w, obs, centres_of_m, detector, {**base, term.id: th})
        th[k] = -h
        dn = predict_px(w, obs, centres_of_m, detector, {**base, term.id: th})
        cols.append(_blocked(up - dn) / (2 * h))
    return np.stack(cols, axis=1)


# --------------------------------------------------------------------------- dataset
def _legendre(x, k):
    return np.polynomial.legendre.legval(x, [0] * k + [1])


def build_dataset(obs: CentreObservations, static, detector: DetectorSpec, n_folds: int = 6) -> tuple:
    """(Dataset, extras) from the observations and the nominal static result."""
    centres = static.centres_of_m
    x = np.asarray(static.x[:13], dtype=float)
    kern = StaticKernel(obs, centres, detector)
    f, jac = kern.evaluate(x)
    resid = -f                                           # observed - modelled, blocked
    jmat = np.ascontiguousarray(jac().T)                  # (2Q, 13) d modelled / d w
    q = obs.n_obs
    sig = np.ones(2 * q) if obs.sigma_px is None else np.concatenate([obs.sigma_px, obs.sigma_px])
    comp = np.repeat([0, 1], q)
    _, vcode = np.unique(obs.view_index, return_inverse=True)
    n_views = int(vcode.max()) + 1
    group = np.concatenate([vcode, vcode])
    # neighbours: the same sphere in consecutive projections
    order = np.lexsort((vcode, obs.sphere_index))
    si, vc = obs.sphere_index[order], vcode[order]
    ok = (si[1:] == si[:-1]) & (vc[1:] - vc[:-1] == 1)
    a, b = order[:-1][ok], order[1:][ok]
    neigh = np.concatenate([np.stack([a, b], 1), np.stack([a + q, b + q], 1)])
    fold_v = (np.arange(n_views) * n_folds) // n_views
    fold = np.concatenate([fold_v[vcode], fold_v[vcode]])
    # axes that can carry physics
    alpha = obs.alpha_rad
    tau, span = scan_time(obs)
    # detector position from the MODELLED centres: a basis built from the noisy observed ones would correlate
    # with the noise it is meant to test
    mod = obs.uv_px + np.stack([f[:q], f[q:]], axis=1)
    u_m, v_m = detector.metric_from_pixels(mod[:, 0], mod[:, 1])
    half = max(detector.cols, detector.rows) * detector.pixel_pitch_m / 2.0
    xn, yn = u_m / half, v_m / half
    geom = static_to_detector_frame(x, centres)
    rel = geom.centres_df_m - geom.stage_df_m
    height = rel @ geom.axis_df
    hq = height[obs.sphere_index]
    hq = (hq - hq.mean()) / max(np.ptp(hq) / 2.0, 1e-12)
    zero = np.zeros(q)

    def both(col):        # one column acting on u, one on v
        return np.stack([np.concatenate([col, zero]), np.concatenate([zero, col])], axis=1)

    emp = {}
    for k in range(1, 7):
        emp[f"rotary angle harmonic {k}"] = np.hstack([both(np.cos(k * alpha)), both(np.sin(k * alpha))])
    if span > 0:
        for k in range(1, 4):
            emp[f"time order {k}"] = both(_legendre(tau, k))
    # detector position: radial and tangential cubic fields (rows grow along -y: v = -y)
    r2 = xn ** 2 + yn ** 2
    emp["detector radial"] = np.concatenate([xn * r2, -yn * r2])[:, None]
    emp["detector tangential"] = np.concatenate([-yn * r2, -xn * r2])[:, None]
    emp["detector smooth field"] = np.hstack([both(xn ** 2), both(xn * yn), both(yn ** 2)])
    emp["sphere height"] = np.hstack([both(hq), both(_legendre(hq, 2))])
    depth = _rotate(rel[obs.sphere_index], geom.axis_df, np.cos(alpha), np.sin(alpha)) @ np.array([0, 0, 1.0])
    emp["sphere depth (magnification)"] = both((depth - depth.mean()) / max(np.ptp(depth) / 2, 1e-12))
    ds = Dataset(residual=resid, jac=jmat, nominal_names=STATIC_PARAM_NAMES, sigma=sig, component=comp,
                 group=group, neighbours=neigh, fold=fold, empirical=emp, unit="px")
    return ds, {"span_s": span, "tau": tau, "x": x, "kernel": kern}


def catalogue_candidates(obs, static, detector, span_s: float):
    x = np.asarray(static.x[:13], dtype=float)
    out = []
    for t in CATALOGUE:
        b = term_basis(t, x, obs, static.centres_of_m, detector)
        if t.needs_time and span_s <= 0:
            b = np.zeros_like(b)
        out.append(Candidate(t.id, t.name, t.mechanism, t.param_names, t.param_units, b, t.display_unit,
                             np.full(len(t.param_names), t.display_factor), t.reveal_by,
                             plausible_max=t.plausible_max))
    return out


# --------------------------------------------------------------------------- refit
def refit(obs, static, detector, chosen: list, ds: Dataset, ctx, beta0, iterations: int = 3):
    """Gauss-Newton on the exact extended model from the linear solution; returns (x13, thetas, cov, resid)."""
    centres = static.centres_of_m
    x = np.asarray(static.x[:13], dtype=float) + beta0[:13]
    sizes = [len(CATALOGUE_BY_ID[c].param_names) for c in chosen]
    th = {}
    k = 13
    for c, p in zip(chosen, sizes):
        th[c] = np.asarray(beta0[k:k + p], dtype=float)
        k += p
    wh = ctx.wh
    cov = None
    for _ in range(iterations):
        r = _blocked(obs.uv_px - predict_px(x, obs, centres, detector, th))
        jw = np.ascontiguousarray(StaticKernel(obs, centres, detector).evaluate(x)[1]().T)
        # the nominal columns at the current terms: FD of the terms' effect on them is second order; use analytic
        cols = [jw]
        for c in chosen:
            base = {i: v for i, v in th.items() if i != c}
            t = CATALOGUE_BY_ID[c]
            p = len(t.param_names)
            bc = []
            for j in range(p):
                d = np.zeros(p)
                d[j] = t.fd_step[j]
                up = predict_px(x, obs, centres, detector, {**base, c: th[c] + d})
                dn = predict_px(x, obs, centres, detector, {**base, c: th[c] - d})
                bc.append(_blocked(up - dn) / (2 * t.fd_step[j]))
            cols.append(np.stack(bc, axis=1))
        xr = np.hstack(cols)
        xw = wh(xr)
        step = np.linalg.lstsq(xw, wh(r), rcond=None)[0]
        cov = np.linalg.pinv(xw.T @ xw)
        x = x + step[:13]
        k = 13
        for c, p in zip(chosen, sizes):
            th[c] = th[c] + step[k:k + p]
            k += p
    r = _blocked(obs.uv_px - predict_px(x, obs, centres, detector, th))
    return x, th, cov, r, xr


# --------------------------------------------------------------------------- the analysis
def _fmt(v, unit):
    return f"{v:.3g} {unit}"


def run(obs: CentreObservations, static, detector: DetectorSpec, *, progress=None, max_terms: int = 4) -> dict:
    """The whole CT analysis; returns the discrepancy.json dict (plus private arrays under ``_arrays``)."""
    import time  # noqa: PLC0415

    say = progress or (lambda _m: None)
    clock = [time.perf_counter()]
    timing = {}

    def lap(name):
        now = time.perf_counter()
        timing[name] = now - clock[0]
        clock[0] = now

    ds, ext = build_dataset(obs, static, detector)
    lap("dataset_s")
    cands = catalogue_candidates(obs, static, detector, ext["span_s"])
    lap("catalogue_bases_s")
    say(f"{obs.n_obs} centres in {obs.n_views} projections over {ext['span_s']:.1f} s; "
        f"{len(cands)} catalogue terms, {len(ds.empirical)} locate axes")
    res = analyse(ds, cands, max_terms=max_terms, progress=say)
    lap("floor_locate_name_limits_s")
    ctx = res["context"]
    chosen = res["chosen"]
    by_id = {c.id: c for c in cands}
    x_after, th_after, cov_after, r_after, design = (static.x[:13], {}, None, ds.residual, ds.jac)
    if chosen:
        x_after, th_after, cov_after, r_after, design = refit(obs, static, detector, chosen, ds, ctx, res["beta"])
        # structure left after the exact refit (the engine's linearised 'unexplained' is replaced)
        q_after, _ = _orth(ctx.wh(design))
        res["unexplained"] = [e for e in locate(ctx, q_after, ds.empirical, ctx.wh(r_after))
                              if e["delta_bic"] >= BIC_THRESHOLD]
    lap("refit_s")
    findings = []
    k = 13
    for f in res["findings"]:
        t = CATALOGUE_BY_ID[f["term"]]
        p = len(t.param_names)
        th = th_after.get(f["term"], f["theta"])
        ct = cov_after[k:k + p, k:k + p] if cov_after is not None else f["theta_cov"]
        k += p
        u = np.sqrt(np.maximum(np.diag(ct), 0))
        mag = float(np.linalg.norm(th) * t.display_factor)
        g = th / max(np.linalg.norm(th), 1e-300)                 # d |theta| / d theta
        mag_u = float(np.sqrt(max(g @ ct @ g, 0.0)) * t.display_factor)
        sep = {t.reveal_by} | {CATALOGUE_BY_ID[d].reveal_by for d in f["degenerate_with"]}
        if f["correlated_nominal"]:
            sep.add("an independent reference for " + ", ".join(f["correlated_nominal"]))
        findings.append(finding_entry(t, f, th, u, mag, mag_u, t.display_unit, sep))
    # fit after (exact refit) and held-out from the engine's folds
    wh = ctx.wh
    za = wh(r_after)
    dof_a = max(ds.residual.size - 13 - sum(len(CATALOGUE_BY_ID[c].param_names) for c in chosen), 1)
    after = dict(res["after"])
    after.update(rms=float(np.sqrt(np.mean(r_after ** 2))), chi2_dof=float(za @ za / dof_a))
    limits = {}
    for c in cands:
        lim = res["limits"][c.id]
        t = CATALOGUE_BY_ID[c.id]
        if t.needs_time and ext["span_s"] <= 0:
            limits[c.id] = {"limit": None, "unit": t.display_unit,
                            "cannot_see": "the recording has no usable time stamps (one instant)",
                            "reveal_by": t.reveal_by}
        elif lim["absorbed_fraction"] > 0.999 or not np.isfinite(lim["limit"]):
            limits[c.id] = {"limit": None, "unit": t.display_unit,
                            "cannot_see": "absorbed by the calibrated parameters in this acquisition",
                            "reveal_by": t.reveal_by}
        else:
            limits[c.id] = {"limit": lim["limit"], "unit": t.display_unit, "reveal_by": t.reveal_by,
                            "absorbed_fraction": lim["absorbed_fraction"]}
    unexplained = unexplained_entries(res["unexplained"])
    adequate = not findings and not unexplained
    fl = res["floor"]
    floor_d = fl.to_dict("px")
    floor_d["stated_sigma_median_px"] = fl.sigma_median
    verdict = verdict_sentence(
        findings, unexplained, name_of={t.id: t.name for t in CATALOGUE}, n_obs=obs.n_obs, obs_noun="sphere centres",
        floor_sd=fl.factor[:2] * fl.sigma_median, floor_axes="columns / rows",
        held_out_before=res["before"]["held_out_rms"], held_out_after=after["held_out_rms"],
        clean_examples=(f"no focal-spot drift above {_fmt(limits['focal_spot_drift']['limit'] or np.inf, 'um')} over "
                        f"the scan and no detector bow above {_fmt(limits['detector_bow']['limit'] or np.inf, 'mm')} sag"))
    names = list(STATIC_PARAM_NAMES)
    x_before = np.asarray(static.x[:13], dtype=float)
    sd_after = None if cov_after is None else np.sqrt(np.maximum(np.diag(cov_after)[:13], 0))
    out = {
        "verdict": verdict, "adequate": bool(adequate), "noise_floor": floor_d,
        "fit_before": res["before"], "fit_after": after,
        "findings": findings, "unexplained": unexplained,
        "located": [{k: v for k, v in e.items()} for e in res["located"]],
        "detection_limits": limits,
        "calibration_before": {"names": names, "x": x_before.tolist(), "std": list(map(float, static.std[:13]))},
        "calibration_after": {"names": names, "x": np.asarray(x_after).tolist(),
                              "std": None if sd_after is None else sd_after.tolist()},
        "catalogue": [{"id": t.id, "name": t.name, "mechanism": t.mechanism, "parameters": list(t.param_names),
                       "units": list(t.param_units), "magnitude_unit": t.display_unit, "reveal_by": t.reveal_by}
                      for t in CATALOGUE],
        "engine_timing_s": timing,
        "n_observations": obs.n_obs, "n_projections": obs.n_views, "scan_duration_s": ext["span_s"],
        "_arrays": {"residual_before": ds.residual, "residual_after": r_after, "alpha": obs.alpha_rad,
                    "tau": ext["tau"], "uv": obs.uv_px},
    }
    return out


def significance_of(d_chi2, dof):  # re-export for callers
    return sigma_from_chi2(d_chi2, dof)


# --------------------------------------------------------------------------- stage-position axis
def source_df(x13, cov13, centres_of_m):
    """Focal spot in {DF} (3,) [m] of a static solution and its covariance (3, 3) (central differences).

    In the model of a campaign (static geometry + per-position error motions of the stage) the focal spot
    relative to the detector is the same at every stage position: the error motions move the stage only."""
    x = np.asarray(x13[:13], dtype=float)
    s0 = static_to_detector_frame(x, centres_of_m).source_df_m
    if cov13 is None:
        return s0, None
    cov = np.asarray(cov13, dtype=float)[:13, :13]
    jac = np.zeros((3, 13))
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    for i in range(13):
        h = max(0.1 * sd[i], 1e-9)
        up, dn = x.copy(), x.copy()
        up[i] += h
        dn[i] -= h
        jac[:, i] = (static_to_detector_frame(up, centres_of_m).source_df_m
                     - static_to_detector_frame(dn, centres_of_m).source_df_m) / (2 * h)
    return s0, jac @ cov @ jac.T


def judge_position(k: int, srd_reported_m: float, obs: CentreObservations, centres_of_m, detector: DetectorSpec,
                   sdd_reported_m: float, *, min_views: int = 8, max_terms: int = 4, static=None, out=None):
    """The engine at one stage position with its own nominal calibration (the static solver on that position's
    projections, the 13 parameters free, unless ``static`` is given; ``out``: its run() result if already made).

    Returns (row, None) or (None, {"position", "why"}) when the position cannot be judged."""
    from .static_solver import solve_static  # noqa: PLC0415

    if obs.n_views < min_views:
        return None, {"position": k, "why": f"{obs.n_views} projection(s), fewer than {min_views}"}
    st = static if static is not None else solve_static(obs, centres_of_m, detector, float(srd_reported_m),
                                                        float(sdd_reported_m))
    if not np.all(np.isfinite(st.x[:13])) or st.outcome in ("failed", "insufficient_data", "degenerate"):
        return None, {"position": k, "why": f"nominal calibration {st.outcome}: {st.message}"}
    # a POOR_FIT calibration is judged: that is where the engine is needed
    out = out if out is not None else run(obs, st, detector, max_terms=max_terms)
    t_mid = None if obs.stamp_ns is None else float(0.5 * (obs.stamp_ns.min() + obs.stamp_ns.max()))
    s, s_cov = source_df(st.x[:13], getattr(st, "covariance", None), centres_of_m)
    row = {"position": k, "srd_reported_m": float(srd_reported_m), "mid_stamp_ns": t_mid,
           "scan_s": out["scan_duration_s"], "n_projections": obs.n_views, "adequate": out["adequate"],
           "nominal_outcome": st.outcome, "verdict": out["verdict"],
           "noise_floor_px": out["noise_floor"]["independent_sd"],
           "findings": [{"term": f["term"], "magnitude": f["magnitude"], "magnitude_u": f["magnitude_u"],
                         "unit": f["magnitude_unit"], "significance_sigma": f["significance_sigma"],
                         "degenerate_with": f["degenerate_with"]} for f in out["findings"]],
           "unexplained": [u["axis"] for u in out["unexplained"]],
           "source_df_m": s.tolist(), "source_df_cov_m2": None if s_cov is None else s_cov.tolist()}
    return row, None


def _srd_trends(rows: list) -> list:
    """Every term named at two or more positions: its magnitude fitted linearly against the reported SRD."""
    trends = []
    terms = sorted({f["term"] for r in rows for f in r["findings"]})
    for t in terms:
        pts = [(r["srd_reported_m"], f["magnitude"], f["magnitude_u"]) for r in rows
               for f in r["findings"] if f["term"] == t]
        if len(pts) < 2:
            continue
        x = np.array([p[0] for p in pts])
        m = np.array([p[1] for p in pts])
        u = np.maximum(np.array([p[2] for p in pts]), 1e-12)
        tr = {"term": t, "unit": CATALOGUE_BY_ID[t].display_unit, "n_positions": len(pts),
              "magnitudes": m.tolist(), "u": u.tolist(), "srd_reported_m": x.tolist()}
        if np.ptp(x) > 0:
            a = np.vstack([np.ones_like(x), x - x.mean()]).T / u[:, None]
            cov = np.linalg.pinv(a.T @ a)
            beta = cov @ a.T @ (m / u)
            tr["slope_per_m_srd"] = float(beta[1])
            tr["u_slope_per_m_srd"] = float(np.sqrt(cov[1, 1]))
            tr["slope_significance_sigma"] = float(abs(beta[1]) / np.sqrt(cov[1, 1]))
        trends.append(tr)
    return trends


# campaign-long terms: (id, components of the focal spot in {DF}, name, mechanism, degenerate_with, reveal_by)
CAMPAIGN_TERMS = (
    ("focal_spot_drift", (0, 1), "focal-spot drift across the beam over the campaign",
     "the focal spot moves relative to the detector between stage positions (tube heating over the campaign, or "
     "the panel creeping in its plane: once the stage's error motions are free per position the two are the "
     "same), so every position's calibration puts the source elsewhere", ("detector_drift",),
     "repeated projections of one position at the start and end of the campaign, or a fiducial fixed to the "
     "detector (separates a source from a detector drift)"),
    ("focal_spot_drift_axial", (2,), "source-detector distance drifting over the campaign",
     "the focal spot (or the detector) moves along the beam between stage positions, so the calibrated "
     "source-detector distance changes from position to position", (),
     "repeated projections of one position at the start and end of the campaign; a temperature log of the tube "
     "and detector mounts"),
)


def _gls(ys, covs, design_rows):
    """Generalised least squares over positions: ys[k] (p,), covs[k] (p, p), design_rows[k] (p, m).
    Returns (beta (m,), cov (m, m), chi2, fisher (m, m))."""
    m = design_rows[0].shape[1]
    fisher, rhs, yy = np.zeros((m, m)), np.zeros(m), 0.0
    for y, c, a in zip(ys, covs, design_rows):
        wi = np.linalg.inv(c)
        fisher += a.T @ wi @ a
        rhs += a.T @ wi @ y
        yy += y @ wi @ y
    cov = np.linalg.pinv(fisher)
    beta = cov @ rhs
    return beta, cov, float(yy - beta @ rhs), fisher


def campaign_drift(rows: list, *, bic_threshold: float = BIC_THRESHOLD) -> dict:
    """Campaign-long effects the per-position solves absorb (the joint model "static + error motions" with
    campaign-long time terms, at the level of the per-position calibrations).

    In that model the focal spot relative to the detector is shared by all positions (the error motions move
    the stage). Each judged position gives it in {DF} with its covariance (its own 13-parameter solve); it is
    fitted over the positions as constant, then linear in the campaign time ``tau = (t - t_mid) / T`` (T =
    last - first position's mid-scan stamp; the parameters are the change between the first and the last
    position). The linear term is named (CAMPAIGN_TERMS) when delta BIC = delta chi2 - p ln n > 10 (n: the 3K
    coordinates), as the engine; scatter about the line beyond the uncertainties (a per-position offset, p (K - 2)
    dof, same criterion) is reported unexplained. Detection limits at 90 % power for the worst direction.
    Limits: a stage drift over the campaign is the error map itself (absorbed; a revisited position separates
    it); a linear trend in time and one in SRD are one when the campaign visits the positions in SRD order.
    """
    use = [r for r in rows if r.get("source_df_cov_m2") is not None and r.get("mid_stamp_ns") is not None]
    out = {"performed": False, "findings": [], "unexplained": [], "detection_limits": {}, "n_positions": len(use)}
    if len(use) < 3:
        out["why"] = (f"{len(use)} judged position(s) with time stamps; a campaign-long trend needs 3 (two give "
                      "a line with no check)")
        return out
    t = np.array([r["mid_stamp_ns"] for r in use]) * 1e-9
    span = float(t.max() - t.min())
    if span <= 0:
        out["why"] = "all positions at one instant: no time axis"
        return out
    tau = (t - 0.5 * (t.max() + t.min())) / span
    srd = np.array([r["srd_reported_m"] for r in use])
    corr = float(np.corrcoef(tau, srd)[0, 1]) if np.ptp(srd) > 0 else 0.0
    s_um = np.array([r["source_df_m"] for r in use]) * 1e6
    c_um = np.array([r["source_df_cov_m2"] for r in use]) * 1e12
    ln_n = np.log(3 * len(use))
    scan_s = float(np.median([r.get("scan_s") or 0.0 for r in use]))
    out.update(performed=True, span_s=span, positions=[r["position"] for r in use], tau=tau.tolist(),
               time_srd_correlation=corr, source_df_um=s_um.tolist(),
               u_source_df_um=np.sqrt(np.maximum(np.einsum("kii->ki", c_um), 0)).tolist(),
               method="focal spot in {DF} of each position's calibration (its covariance propagated), GLS over the "
                      "positions: constant vs linear in campaign time; delta BIC > 10 names a campaign-long term")
    for tid, comp, name, mech, degen, reveal in CAMPAIGN_TERMS:
        idx = list(comp)
        p = len(idx)
        ys = [s[idx] for s in s_um]
        cs = [c[np.ix_(idx, idx)] for c in c_um]
        eye = np.eye(p)
        _, _, chi0, _ = _gls(ys, cs, [eye] * len(use))
        beta, cov, chi1, fisher = _gls(ys, cs, [np.hstack([eye, tk * eye]) for tk in tau])
        d = chi0 - chi1
        dbic = float(d - p * ln_n)
        fb = fisher[p:, p:] - fisher[p:, :p] @ np.linalg.pinv(fisher[:p, :p]) @ fisher[:p, p:]
        ev = float(np.linalg.eigvalsh(fb).min())
        lam = required_noncentrality(p * ln_n + bic_threshold, p)
        limit = float(np.sqrt(lam / ev)) if ev > 0 else None
        sep = reveal + ("; this campaign visits the positions in SRD order, so a change with time and one with "
                        "the stage position are the same here: revisit a position" if abs(corr) > 0.95 else "")
        out["detection_limits"][tid] = {"limit": limit, "unit": "um over the campaign", "reveal_by": sep}
        b, cb = beta[p:], cov[p:, p:]
        mag = float(np.linalg.norm(b))
        g = b / max(mag, 1e-300)
        mag_u = float(np.sqrt(max(g @ cb @ g, 0.0)))
        dof_s = p * (len(use) - 2)
        entry = {"term": tid, "name": name, "mechanism": mech, "scope": "campaign",
                 "significance_sigma": sigma_from_chi2(d, p), "delta_bic": dbic, "magnitude": mag,
                 "magnitude_u": mag_u, "magnitude_unit": "um over the campaign",
                 "per_scan_um": mag * scan_s / span,
                 "parameters": [{"name": f"d{'xyz'[i]}_source_campaign", "value": float(v) * 1e-6,
                                 "u": float(np.sqrt(cb[j, j])) * 1e-6, "unit": "m"} for j, (i, v) in
                                enumerate(zip(idx, b))],
                 "degenerate_with": list(degen), "correlated_with_calibrated": [],
                 "separate_by": [sep], "scatter_chi2": chi1, "scatter_dof": dof_s}
        if dbic >= bic_threshold:
            out["findings"].append(entry)
        if dof_s > 0:
            sbic = float(chi1 - dof_s * ln_n)
            if sbic >= bic_threshold:
                out["unexplained"].append({"axis": f"campaign: focal spot {'xyz'[idx[0]] if p == 1 else 'x/y'} "
                                                   "between stage positions", "significance_sigma":
                                           sigma_from_chi2(chi1, dof_s), "delta_bic": sbic,
                                           "chi2": chi1, "dof": dof_s})
    out["findings"].sort(key=lambda f: -f["delta_bic"])
    out["adequate"] = not out["findings"] and not out["unexplained"]
    return out


def campaign_sentence(camp: dict) -> str:
    """One or two sentences on the campaign-long analysis (appended to a verdict)."""
    if not camp.get("performed"):
        return f" Campaign-long drift not judged: {camp.get('why', 'not performed')}."
    if camp["adequate"]:
        lim = camp["detection_limits"].get("focal_spot_drift", {}).get("limit")
        span = camp["span_s"]
        span = f"{span:.0f} s" if span < 120 else f"{span / 60:.0f} min" if span < 7200 else f"{span / 3600:.1f} h"
        return (f" Over the campaign ({camp['n_positions']} positions, {span}) the focal "
                f"spot stays put relative to the detector" + (f" (no drift across the beam above {lim:.3g} um)"
                                                              if lim else "") + ".")
    parts = []
    for f in camp["findings"]:
        alt = (" (or " + ", ".join(CATALOGUE_BY_ID[d].name for d in f["degenerate_with"]) + " over the campaign)"
               if f["degenerate_with"] else "")
        parts.append(f"{f['name']}{alt}: {_fmt(f['magnitude'], 'um')} between the first and last position at "
                     f"{f['significance_sigma']:.1f} sigma (about {_fmt(f['per_scan_um'], 'um')} within one scan)")
    parts += [f"scatter of the {u['axis']} beyond its uncertainty ({u['significance_sigma']:.1f} sigma)"
              for u in camp["unexplained"]]
    return " Campaign-long: " + "; ".join(parts) + "; the per-position calibrations and error motions absorb it."


def across_positions(rows: list, skipped: list) -> dict:
    """What run_positions returns from the judged positions' rows (trends against SRD, campaign-long terms)."""
    rows = sorted(rows, key=lambda r: r["position"])
    camp = campaign_drift(rows)
    inadequate = [r["position"] for r in rows if not r["adequate"]]
    return {"positions": rows, "trends": _srd_trends(rows), "campaign": camp, "not_judged": list(skipped),
            "inadequate_positions": inadequate,
            "adequate": bool(rows) and not inadequate and camp.get("adequate", True),
            "method": "per position: static solve with the 13 parameters free, then the engine; across positions: "
                      "weighted linear fit of each repeatedly named term's magnitude against the reported SRD; "
                      "campaign: the focal spot in {DF} of every position's calibration, constant vs linear in time"}


def run_positions(positions: list, centres_of_m, detector: DetectorSpec, sdd_reported_m: float, *,
                  min_views: int = 8, max_terms: int = 4, progress=None, first: int = 0,
                  given: dict | None = None) -> dict:
    """The engine at every stage position: ``positions`` is a list of (srd_reported_m, CentreObservations),
    numbered from ``first``; ``given``: {position: (static, run() result)} already made (e.g. the first).

    Each position gets its own nominal calibration (judge_position: the stage's error motion between positions
    is absorbed, what changes WITHIN a position's scan is not) and its own verdict. Across positions, the
    magnitude of every term named at two or more positions is fitted linearly against the reported SRD, and
    the focal spot of the positions' calibrations is tested for a campaign-long drift (campaign_drift).
    Returns across_positions(): {"positions", "trends", "campaign", "not_judged", "inadequate_positions",
    "adequate", "method"}.
    """
    say = progress or (lambda _m: None)
    given = given or {}
    rows, skipped = [], []
    for k, (srd, obs) in enumerate(positions, start=first):
        st, out = given.get(k, (None, None))
        row, skip = judge_position(k, srd, obs, centres_of_m, detector, sdd_reported_m, min_views=min_views,
                                   max_terms=max_terms, static=st, out=out)
        if row is None:
            skipped.append(skip)
            continue
        rows.append(row)
        say(f"stage position {k + 1} (SRD {srd * 1e3:.2f} mm): {row['verdict']}")
    return across_positions(rows, skipped)
