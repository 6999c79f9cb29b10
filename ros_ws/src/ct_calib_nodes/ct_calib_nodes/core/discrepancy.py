"""Sim-to-real discrepancy engine, cell-agnostic core (numpy/scipy only).

Given what a calibration left over -- residuals ``r = observed - modelled`` of
a nominal model at its estimate, that model's Jacobian, and for every
residual its coordinates along the axes that can carry physics -- the engine

1. states a NOISE FLOOR estimated from the data (robust scale of the
   differences between neighbouring residuals, e.g. the same sphere in
   consecutive projections, which cancels anything smooth; and the scatter of
   a shift shared by a group, e.g. a projection, from the differences of
   neighbouring group means), never from the detector's stated sigma;
2. LOCATES structure beyond that floor along every axis the adapter supplies
   (empirical bases: angle harmonics, time polynomials, detector field, ...):
   generalised least squares against the floor's covariance, after projecting
   out what the nominal parameters absorb; significance from the chi-square
   reduction;
3. NAMES it from a catalogue of physical terms (each a linearised basis
   d modelled / d theta with names, units and a magnitude): greedy forward
   selection by the Bayesian information criterion on the data, each accepted
   term required to improve k-fold cross-validation on held-out blocks; terms
   that explain the data about as well are reported as degenerate, never
   picked silently; a term's overlap with the calibrated parameters is named;
4. MODELS it: the joint fit of nominal parameters and accepted terms, with
   uncertainties under the floor, fit and held-out error before and after;
5. reports structure no term explains (signature, absorbed only by a term
   labelled ``empirical:<axis>``), and a DETECTION LIMIT per catalogue term
   (smallest magnitude this recording would reveal at 90 % power).

The cell adapter (ct_discrepancy.py for CT; a Pixel Probe adapter supplies the
same :class:`Dataset` and :class:`Candidate` objects) does the physics: building
the bases, the nonlinear refit, the verdict's wording of its terms.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import sparse, stats

#: minimum BIC improvement for a term (Kass & Raftery: > 10 "very strong")
BIC_THRESHOLD = 10.0
#: candidates within this much BIC of the best are reported as degenerate with it
DEGENERATE_BIC = 6.0
#: power at which detection limits are stated
LIMIT_POWER = 0.9


@dataclass
class Dataset:
    """Everything the engine needs from one calibration (n residuals, p0 nominal parameters).

    residual : (n,) observed - modelled [unit] at the nominal estimate.
    jac : (n, p0) d modelled / d nominal parameters.
    nominal_names : (p0,) names of the nominal parameters.
    sigma : (n,) relative weights (the stated sigma; ones when none).
    component : (n,) int, 0..C-1 (e.g. image u, v): the floor is estimated per component.
    group : (n,) int, group sharing a common shift (e.g. projection), in acquisition order.
    neighbours : (m, 2) int, pairs of residual indices that differ only slightly in every physical
        axis (same feature, consecutive groups), for the floor.
    fold : (n,) int, cross-validation fold (contiguous blocks of groups).
    empirical : dict name -> (n, k) bases of the locate axes.
    unit : str, the residual unit ("px").
    rms_rows : (n,) bool or None: the rows the fit and held-out RMS are stated over (all when None; an
        adapter with residual blocks in other units, e.g. tracker readings in um, keeps them to ``unit``).
    shared_shift : estimate a shift shared by each group (the floor's ``tau``; default). An adapter turns it
        off where no shared shift is physical and its groups are too small for the estimate (the Pixel
        Probe: three cameras per station; see :func:`noise_floor`).
    refloor_after : when terms are found, the joint fit, its uncertainties and the fit and held-out figures
        after are computed under the floor of the residuals after those terms (the floor of the detection
        steps is kept for naming, unexplained structure and limits). For an adapter whose neighbouring
        residuals are far apart along a strong effect's axis (the Pixel Probe's grid stations, 4 mm apart),
        the effect inflates the neighbour-difference floor several times and with it the stated
        uncertainties, and it weighs the residual blocks against each other wrongly in the refit.
    """

    residual: np.ndarray
    jac: np.ndarray
    nominal_names: tuple
    sigma: np.ndarray
    component: np.ndarray
    group: np.ndarray
    neighbours: np.ndarray
    fold: np.ndarray
    empirical: dict = field(default_factory=dict)
    unit: str = "px"
    rms_rows: np.ndarray | None = None
    shared_shift: bool = True
    refloor_after: bool = False

    def rms(self, r) -> float:
        """RMS of a residual vector over ``rms_rows`` [unit]."""
        r = np.asarray(r, dtype=float)
        return float(np.sqrt(np.mean(np.square(r if self.rms_rows is None else r[self.rms_rows]))))


@dataclass
class Candidate:
    """One catalogue term evaluated on a dataset.

    basis : (n, p) d modelled / d theta [unit per parameter unit] at theta = 0.
    magnitude : callable theta (p,) -> float, in ``magnitude_unit`` (a norm of theta in display units).
    display_scale : (p,) factor from theta's SI value to the displayed unit.
    """

    id: str
    name: str
    mechanism: str
    param_names: tuple
    param_units: tuple
    basis: np.ndarray
    magnitude_unit: str
    display_scale: np.ndarray
    reveal_by: str
    magnitude: object = None
    plausible_max: float = np.inf     # largest physically plausible magnitude [magnitude_unit]

    def mag(self, theta):
        if self.magnitude is not None:
            return float(self.magnitude(theta))
        return float(np.linalg.norm(np.asarray(theta) * self.display_scale))


@dataclass(frozen=True)
class Floor:
    """Noise floor per component: independent sd ``factor * sigma`` and a group-shared sd ``tau``."""

    factor: np.ndarray          # (C,) scale of the stated sigma (within-group, independent part)
    tau: np.ndarray             # (C,) sd of the shift shared by a group [unit]
    sigma_median: float
    n_pairs: int
    method: str = ("robust (MAD) scale of differences between neighbouring residuals (same feature, "
                   "consecutive projections); group-shared part from differences of neighbouring group means")

    def to_dict(self, unit="px", names=("u", "v")):
        return {"method": self.method, "n_pairs": self.n_pairs,
                "independent_sd": {names[a]: float(self.factor[a] * self.sigma_median) for a in range(len(self.factor))},
                "shared_per_projection_sd": {names[a]: float(self.tau[a]) for a in range(len(self.tau))},
                "factor_of_stated_sigma": {names[a]: float(self.factor[a]) for a in range(len(self.factor))},
                "unit": unit}


def _mad(x):
    x = np.asarray(x, dtype=float)
    if x.size == 0:
        return np.nan
    return 1.4826 * float(np.median(np.abs(x - np.median(x))))


def noise_floor(ds: Dataset) -> Floor:
    """Noise floor from the data (see module docstring).

    The shared part comes from the differences of neighbouring group means, which cancel smooth structure
    only when neighbouring groups are neighbours along it (consecutive projections). With few members per
    group and groups that jump across the structure's axis (a serpentine grid of stations), an effect
    linear in position enters those differences, is taken for shared noise and, subtracted from the total,
    leaves an independent floor too small: with ``ds.shared_shift`` off the whole scale is independent."""
    z = ds.residual / ds.sigma
    n_c = int(ds.component.max()) + 1
    i, j = ds.neighbours[:, 0], ds.neighbours[:, 1]
    factor, tau = np.zeros(n_c), np.zeros(n_c)
    med = float(np.median(ds.sigma))
    for a in range(n_c):
        sel = ds.component[i] == a
        s_tot = _mad(z[i[sel]] - z[j[sel]]) / np.sqrt(2.0)      # total independent-looking sd, sigma units
        rows = np.flatnonzero(ds.component == a)
        g = ds.group[rows]
        gu, gi = np.unique(g, return_inverse=True)
        cnt = np.bincount(gi)
        means = np.bincount(gi, z[rows]) / cnt
        nbar = float(np.mean(cnt))
        t2 = 0.0
        if ds.shared_shift and gu.size >= 8:
            s_m2 = (_mad(np.diff(means)) ** 2) / 2.0
            t2 = (s_m2 - s_tot ** 2 / nbar) / max(1.0 - 1.0 / nbar, 1e-9)
            se = np.sqrt(2.0 / gu.size) * s_m2 * 1.6            # MAD-based variance: ~1.6x the normal SE
            if t2 < 2.0 * se:
                t2 = 0.0
        t2 = min(max(t2, 0.0), 0.95 * s_tot ** 2)
        factor[a] = np.sqrt(max(s_tot ** 2 - t2, 1e-30))
        tau[a] = np.sqrt(t2) * float(np.median(ds.sigma[rows]))     # the component's own unit
    return Floor(factor=factor, tau=tau, sigma_median=med, n_pairs=int(len(i)))


class Whitener:
    """x -> L x with L^T L = Cov^-1 under the floor (block per group and component, Sherman-Morrison)."""

    def __init__(self, ds: Dataset, floor: Floor):
        n = ds.residual.size
        d = (floor.factor[ds.component] * ds.sigma)          # independent sd per residual
        self.inv_d = 1.0 / d
        key = ds.group.astype(np.int64) * (int(ds.component.max()) + 1) + ds.component
        _, self.key = np.unique(key, return_inverse=True)
        nk = int(self.key.max()) + 1
        u = self.inv_d
        u2 = np.bincount(self.key, u * u, nk)
        tau_k = np.zeros(nk)
        tau_k[self.key] = floor.tau[ds.component]
        gamma = 1.0 / np.sqrt(1.0 + tau_k ** 2 * u2) - 1.0
        self.coef = (gamma / np.where(u2 > 0, u2, 1.0))[self.key] * u      # (n,)
        self.s = sparse.csr_matrix((u, (self.key, np.arange(n))), shape=(nk, n))
        self.active = np.any(floor.tau > 0)

    def __call__(self, x):
        x = np.asarray(x, dtype=float)
        one = x.ndim == 1
        x2 = x[:, None] if one else x
        y = x2 * self.inv_d[:, None]
        if self.active:
            sums = self.s @ y                                    # u^T y per block (u = 1/d, y = x/d)
            y = y + self.coef[:, None] * np.asarray(sums)[self.key]
        return y[:, 0] if one else y


def sigma_from_chi2(d_chi2: float, dof: int) -> float:
    """Gaussian-equivalent (one-sided) significance of a chi-square reduction with ``dof`` dof."""
    if dof <= 0 or not np.isfinite(d_chi2) or d_chi2 <= 0:
        return 0.0
    logp = float(stats.chi2.logsf(d_chi2, dof))
    if logp > -700:
        return max(float(stats.norm.isf(np.exp(logp))), 0.0)
    k = float(dof)                                       # far tail: Wilson-Hilferty cube-root normal
    return float(((d_chi2 / k) ** (1.0 / 3.0) - (1.0 - 2.0 / (9.0 * k))) / np.sqrt(2.0 / (9.0 * k)))


def required_noncentrality(crit: float, dof: int, power: float = LIMIT_POWER) -> float:
    """Noncentrality lambda at which a chi2(dof) statistic exceeds ``crit`` with probability ``power``."""
    lo, hi = 0.0, max(4.0 * crit, 50.0)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if stats.ncx2.sf(crit, dof, mid) < power:
            lo = mid
        else:
            hi = mid
    return hi


def _orth(a, rtol=1e-9, ref=None):
    """Orthonormal basis of the column space of a (n, k), and the rank-revealing singular values.

    Directions with singular values below ``rtol`` times ``ref`` (default the largest one; pass the norm of a
    basis before projection so that what a model already absorbed is not resurrected by rounding) are dropped."""
    if a.shape[1] == 0:
        return a, np.zeros(0)
    u, s, _ = np.linalg.svd(a, full_matrices=False)
    keep = s > rtol * max(s[0] if ref is None else ref, 1e-300)
    return u[:, keep], s


def _project_out(q, b):
    return b - q @ (q.T @ b) if q.shape[1] else b


@dataclass
class Context:
    """Whitened quantities shared by every test of one analysis."""

    ds: Dataset
    floor: Floor
    wh: Whitener
    z: np.ndarray            # whitened residual
    x0: np.ndarray           # whitened nominal Jacobian
    n: int


def _fit(zs, xs):
    """Least squares zs ~ xs beta; returns beta (k,)."""
    if xs.shape[1] == 0:
        return np.zeros(0)
    return np.linalg.lstsq(xs, zs, rcond=None)[0]


def _cv(ctx: Context, extra: list, raw_extra: list):
    """Held-out chi-square (whitened) and RMS [unit] of the model nominal + extra bases, by folds."""
    ds = ctx.ds
    xw = np.hstack([ctx.x0] + extra) if extra else ctx.x0
    xr = np.hstack([ds.jac] + raw_extra) if raw_extra else ds.jac
    chi2, sq, n, n_rms = 0.0, 0.0, 0, 0
    keep = np.ones(ds.residual.size, bool) if ds.rms_rows is None else np.asarray(ds.rms_rows, bool)
    for f in np.unique(ds.fold):
        te = ds.fold == f
        tr = ~te
        beta = _fit(ctx.z[tr], xw[tr])
        chi2 += float(np.sum((ctx.z[te] - xw[te] @ beta) ** 2))
        tk = te & keep
        sq += float(np.sum((ds.residual[tk] - xr[tk] @ beta) ** 2))
        n += int(te.sum())
        n_rms += int(tk.sum())
    return chi2 / max(n, 1), np.sqrt(sq / max(n_rms, 1))


def make_context(ds: Dataset, floor: Floor | None = None) -> Context:
    floor = floor or noise_floor(ds)
    wh = Whitener(ds, floor)
    return Context(ds, floor, wh, wh(ds.residual), wh(ds.jac), ds.residual.size)


def _test_block(ctx: Context, q_model, b_w):
    """Chi-square reduction of adding whitened basis b_w to the model with orthonormal basis q_model."""
    bp = _project_out(q_model, b_w)
    qb, s = _orth(bp, 1e-4, np.linalg.norm(b_w, 2) if b_w.size else 1.0)
    zp = _project_out(q_model, ctx.z)
    proj = qb.T @ zp
    return float(proj @ proj), qb.shape[1], bp


def locate(ctx: Context, q_model, families: dict, z=None) -> list:
    """Significance of each empirical family given the current model (orthonormal whitened basis q_model) and
    whitened residual z (default: the nominal one); list of dicts, most significant first."""
    out = []
    ln_n = np.log(ctx.n)
    z = ctx.z if z is None else z
    zp = _project_out(q_model, z)
    for name, b in families.items():
        bw = ctx.wh(b)
        bp = _project_out(q_model, bw)
        qb, _ = _orth(bp, 1e-3, np.linalg.norm(bw, 2))
        k = qb.shape[1]
        if k == 0:
            continue
        proj = qb.T @ zp
        d = float(proj @ proj)
        coef = _fit(zp, bp)
        amp = b @ coef
        out.append({"axis": name, "dof": k, "delta_chi2": d, "significance_sigma": sigma_from_chi2(d, k),
                    "delta_bic": d - k * ln_n, "amplitude_rms": float(np.sqrt(np.mean(amp ** 2))),
                    "amplitude_max": float(np.max(np.abs(amp)))})
    out.sort(key=lambda e: -e["delta_bic"])
    return out


def _set_score(ctx: Context, q0, ws: list):
    """Joint evidence of a set of whitened bases against the nominal model: (delta BIC, delta chi2, rank)."""
    d, k, _ = _test_block(ctx, q0, np.hstack(ws))
    return d - k * np.log(ctx.n), d, k


def refine_set(ctx: Context, q0, chosen: list, cand_w: dict, candidates: list, plausible, *, max_terms: int,
               bic_threshold: float = BIC_THRESHOLD, say=lambda _m: None):
    """The set of up to max_terms terms with the highest joint BIC, in place of the forward selection's.

    Forward selection is greedy: a term taken early can stand in for two that only explain the data
    together (a camera aspect error for a stage scale error while the stage's angular motions are not
    in), and then neither of the two passes the threshold alone. Every subset is scored (a few hundred
    least-squares projections); one replaces the forward set only if its joint BIC is higher, every
    member earns its place given the others (BIC drop without it >= bic_threshold, held-out chi2 worse
    without it) and every magnitude is plausible. Returns (chosen, findings, alternatives): the findings'
    statistics are each term's given the others (None when the forward set stands), and
    ``alternatives[i]`` the candidates that, in place of term i with the others kept, explain the data
    about as well (joint BIC within DEGENERATE_BIC, or held-out chi2 no worse)."""
    import itertools
    raw = {c.id: c.basis for c in candidates}
    ids = [c.id for c in candidates]
    memo, memo_cv = {frozenset(): (0.0, 0.0, 0)}, {}

    def score(S):
        key = frozenset(S)
        if key not in memo:
            memo[key] = _set_score(ctx, q0, [cand_w[i] for i in sorted(key)])
        return memo[key]

    def cv(S):
        key = frozenset(S)
        if key not in memo_cv:
            memo_cv[key] = _cv(ctx, [cand_w[i] for i in sorted(key)], [raw[i] for i in sorted(key)])
        return memo_cv[key]
    cur = score(chosen)[0]
    final, new = list(chosen), False
    ranked = sorted(((score(S)[0], S) for r in range(1, max_terms + 1) for S in itertools.combinations(ids, r)),
                    key=lambda x: -x[0])
    for b, S in ranked:
        if b <= cur:
            break
        if all(b - score(set(S) - {i})[0] >= bic_threshold for i in S) and \
                all(cv(S)[0] < cv(set(S) - {i})[0] for i in S) and plausible(list(S)):
            say(f"term set {list(S)}: joint delta BIC {b:.1f}, above the forward selection's {cur:.1f} "
                f"({chosen})")
            final, cur, new = list(S), b, True
            break
    findings = None
    if new:
        ln_n = np.log(ctx.n)
        full = score(final)
        order = sorted(final, key=lambda i: -(full[0] - score(set(final) - {i})[0]))
        findings, prev = [], []
        for i in order:
            wo = score(set(final) - {i})
            d, k = full[1] - wo[1], full[2] - wo[2]
            cv_prev = cv(prev)[0]
            cv_new, rms_new = cv(prev + [i])
            findings.append({"term": i, "delta_chi2": d, "dof": k, "delta_bic": d - k * ln_n,
                             "significance_sigma": sigma_from_chi2(d, max(k, 1)), "cv_gain": cv_prev - cv_new,
                             "held_out_rms_after": rms_new, "degenerate_with": []})
            prev.append(i)
        final = order
    alternatives = {}
    cv_cur = cv(final)[0]
    for pos, i in enumerate(final):
        alt = []
        for c in ids:
            if c in final:
                continue
            trial = final[:pos] + [c] + final[pos + 1:]
            b = score(trial)[0]
            if b >= cur - 3 * bic_threshold and (b >= cur - DEGENERATE_BIC or cv(trial)[0] <= cv_cur) \
                    and plausible(trial):
                alt.append(c)
        alternatives[i] = alt
    return final, findings, alternatives


def analyse(ds: Dataset, candidates: list, *, max_terms: int = 4, bic_threshold: float = BIC_THRESHOLD,
            progress=None, refine: bool = False) -> dict:
    """Run floor, locate, name, model, limits. Returns a plain dict (the core of discrepancy.json).

    refine: after the forward selection, the best subset by joint BIC when it beats the forward set
    (:func:`refine_set`), and as degenerate the candidates that could replace a chosen term with the others
    kept."""
    say = progress or (lambda _m: None)
    ctx = make_context(ds)
    ln_n = np.log(ctx.n)
    q0, _ = _orth(ctx.x0)
    cand_w = {c.id: ctx.wh(c.basis) for c in candidates}
    by_id = {c.id: c for c in candidates}
    # ---- before
    zp0 = _project_out(q0, ctx.z)
    beta0 = _fit(ctx.z, ctx.x0)
    r_before = ds.residual - ds.jac @ beta0
    dof0 = max(ctx.n - q0.shape[1], 1)
    cvchi0, cvrms0 = _cv(ctx, [], [])
    before = {"rms": ds.rms(r_before), "chi2_dof": float(zp0 @ zp0 / dof0),
              "held_out_rms": cvrms0, "held_out_chi2_dof": cvchi0}
    say(f"noise floor: factor {np.round(ctx.floor.factor, 3).tolist()} of stated sigma, shared "
        f"{np.round(ctx.floor.tau, 4).tolist()} {ds.unit}; chi2/dof against it {before['chi2_dof']:.3f}")
    located = locate(ctx, q0, ds.empirical)
    # ---- name: greedy forward selection
    chosen, findings, implausible = [], [], []
    q_model = q0
    scores_first = None
    while len(chosen) < max_terms:
        scores = []
        for c in candidates:
            if c.id in chosen:
                continue
            d, k, _ = _test_block(ctx, q_model, cand_w[c.id])
            if k == 0:
                continue
            scores.append((d - k * ln_n, d, k, c.id))
        if scores_first is None:
            scores_first = {s[3]: s for s in scores}
        if not scores:
            break
        scores.sort(reverse=True)
        # a term is a physical name only at a physically plausible magnitude
        zp = _project_out(q_model, ctx.z)
        best = None
        for s_ in scores:
            if s_[0] < bic_threshold:
                break
            th = _fit(zp, _project_out(q_model, cand_w[s_[3]]))
            if by_id[s_[3]].mag(th) <= by_id[s_[3]].plausible_max:
                best = s_
                break
            implausible.append({"term": s_[3], "delta_bic": s_[0], "magnitude": by_id[s_[3]].mag(th)})
        if best is None:
            break
        scores = [best] + [s_ for s_ in scores if s_ is not best]
        extra_w = [cand_w[i] for i in chosen + [best[3]]]
        extra_r = [by_id[i].basis for i in chosen + [best[3]]]
        prev_w = [cand_w[i] for i in chosen]
        prev_r = [by_id[i].basis for i in chosen]
        cv_prev, _ = _cv(ctx, prev_w, prev_r)
        cv_new, cv_rms_new = _cv(ctx, extra_w, extra_r)
        cv_gain = cv_prev - cv_new
        # degenerate alternatives: nearly the same evidence now, and no longer needed once best is in
        q_try, _ = _orth(np.hstack([q_model, cand_w[best[3]]]))
        degenerate = []
        for s in scores[1:]:
            if s[0] >= best[0] - DEGENERATE_BIC and s[0] >= bic_threshold and s[3] not in {i["term"] for i in implausible}:
                d2, k2, _ = _test_block(ctx, q_try, cand_w[s[3]])
                if d2 - k2 * ln_n < bic_threshold:
                    degenerate.append(s[3])
        if cv_gain <= 0:
            say(f"{best[3]}: BIC {best[0]:.1f} but no held-out gain ({cv_gain:.4g}); not accepted")
            break
        chosen.append(best[3])
        q_model = q_try
        findings.append({"term": best[3], "delta_chi2": best[1], "dof": best[2], "delta_bic": best[0],
                         "significance_sigma": sigma_from_chi2(best[1], best[2]), "cv_gain": cv_gain,
                         "held_out_rms_after": cv_rms_new, "degenerate_with": degenerate})
        say(f"found {best[3]}: delta BIC {best[0]:.1f}, {findings[-1]['significance_sigma']:.1f} sigma, "
            f"held-out chi2/n gain {cv_gain:.4f}" + (f"; degenerate with {degenerate}" if degenerate else ""))

    def plausible(ids):
        xs = _project_out(q0, np.hstack([cand_w[i] for i in ids]))
        th = _fit(_project_out(q0, ctx.z), xs)
        k, ok = 0, True
        for i in ids:
            p = cand_w[i].shape[1]
            ok &= by_id[i].mag(th[k:k + p]) <= by_id[i].plausible_max
            k += p
        return ok
    if refine and chosen:
        chosen, f_new, alternatives = refine_set(ctx, q0, chosen, cand_w, candidates, plausible,
                                                 max_terms=max_terms, bic_threshold=bic_threshold, say=say)
        findings = f_new or findings
        for f in findings:
            f["degenerate_with"] = sorted(set(f["degenerate_with"]) | set(alternatives.get(f["term"], [])))

    # ---- joint linear fit with the chosen terms (the adapter refits nonlinearly)
    chosen_w, chosen_r = [cand_w[i] for i in chosen], [by_id[i].basis for i in chosen]
    xw = np.hstack([ctx.x0] + chosen_w)
    xr = np.hstack([ds.jac] + chosen_r)
    beta = _fit(ctx.z, xw)
    xw_detect = xw                              # the model whitened under the floor that named the terms
    ctx_fit, floor_after = ctx, None
    if chosen and ds.refloor_after:
        floor_after = noise_floor(replace(ds, residual=ds.residual - xr @ beta))
        ctx_fit = make_context(ds, floor_after)
        chosen_w = [ctx_fit.wh(b) for b in chosen_r]
        xw = np.hstack([ctx_fit.x0] + chosen_w)
        beta = _fit(ctx_fit.z, xw)
        say(f"noise floor after the terms: factor {np.round(floor_after.factor, 3).tolist()} of stated sigma; "
            f"the joint fit and its uncertainties use it")
    cov = np.linalg.pinv(xw.T @ xw)
    q_after, _ = _orth(xw)
    za = _project_out(q_after, ctx_fit.z)
    dof_a = max(ctx.n - q_after.shape[1], 1)
    birge = 1.0
    if floor_after is not None:
        # what the neighbour differences miss (structure correlated over a few stations) still shows in the
        # residuals' chi2 against the floor: the uncertainties take it as a factor (Birge ratio, never < 1)
        birge = float(np.sqrt(max(1.0, za @ za / dof_a)))
        cov = cov * birge ** 2
    p0 = ds.jac.shape[1]
    k = p0
    for f in findings:
        c = by_id[f["term"]]
        p = c.basis.shape[1]
        th, ct = beta[k:k + p], cov[k:k + p, k:k + p]
        f["theta"], f["theta_cov"] = th, ct
        # overlap with the calibrated parameters: correlations in the joint covariance
        sd = np.sqrt(np.maximum(np.diag(cov), 1e-300))
        corr = cov / np.outer(sd, sd)
        strong = sorted({ds.nominal_names[i] for j in range(k, k + p) for i in range(p0) if abs(corr[i, j]) > 0.9})
        f["correlated_nominal"] = strong
        k += p
    r_after = ds.residual - xr @ beta
    cvchi1, cvrms1 = _cv(ctx_fit, chosen_w, chosen_r)
    after = {"rms": ds.rms(r_after), "chi2_dof": float(za @ za / dof_a),
             "held_out_rms": cvrms1, "held_out_chi2_dof": cvchi1}
    if floor_after is not None:                 # before, against the same (final) floor
        zp_f = _project_out(_orth(ctx_fit.x0)[0], ctx_fit.z)
        before["chi2_dof_final_floor"] = float(zp_f @ zp_f / dof0)
        after["floor"] = "after the terms"
        after["u_factor"] = birge
    # ---- unexplained structure, under the floor of the detection steps (the model's basis whitened by it)
    q_loc = q_after if floor_after is None else _orth(xw_detect)[0]
    remaining = [e for e in locate(ctx, q_loc, ds.empirical) if e["delta_bic"] >= bic_threshold]
    # ---- detection limits (given the nominal model only)
    limits = {}
    for c in candidates:
        bw = cand_w[c.id]
        p = bw.shape[1]
        crit = p * ln_n + bic_threshold
        lam = required_noncentrality(crit, p)
        bp = _project_out(q0, bw)
        scale = np.asarray(c.display_scale, dtype=float)
        fisher = (bp / scale).T @ (bp / scale)               # in display units
        raw = (bw / scale).T @ (bw / scale)
        evr, vr = np.linalg.eigh(raw)
        # directions the term's own basis does not respond to (a constrained parametrisation, e.g.
        # traceless) are not detection directions: restrict to the range of its raw information
        rng_ = evr > 1e-12 * max(evr.max(), 1e-300)
        ev = np.linalg.eigvalsh(vr[:, rng_].T @ fisher @ vr[:, rng_]) if rng_.any() else np.zeros(1)
        evr = evr[rng_] if rng_.any() else np.zeros(1)
        absorbed = 1.0 - (ev.min() / evr.max() if evr.max() > 0 else 0.0)
        lim = float(np.sqrt(lam / ev.min())) if ev.min() > 1e-300 else np.inf
        limits[c.id] = {"limit": lim, "unit": c.magnitude_unit, "absorbed_fraction": float(absorbed),
                        "first_delta_bic": None if scores_first is None or c.id not in scores_first
                        else float(scores_first[c.id][0])}
    return {"context": ctx, "floor": ctx.floor, "floor_after": floor_after, "located": located,
            "findings": findings, "chosen": chosen, "beta": beta, "cov": cov, "before": before, "after": after,
            "unexplained": remaining, "limits": limits, "n": ctx.n, "implausible": implausible}


def _fmt(v, unit):
    return f"{v:.3g} {unit}"


def finding_entry(term, f: dict, theta, theta_u, magnitude: float, magnitude_u: float, magnitude_unit: str,
                  separate_by) -> dict:
    """One entry of discrepancy.json's ``findings`` for an accepted catalogue term (either cell's adapter):
    ``term`` has id, name, mechanism, param_names, param_units; ``f`` is the engine's finding (significance,
    delta BIC, CV gain, degenerate_with, correlated_nominal); ``separate_by`` the acquisitions that would
    tell it from its rivals, reported only when it has any (degenerate or correlated with the calibration)."""
    return {
        "term": term.id, "name": term.name, "mechanism": term.mechanism,
        "significance_sigma": f["significance_sigma"], "delta_bic": f["delta_bic"], "cv_gain": f["cv_gain"],
        "magnitude": magnitude, "magnitude_u": magnitude_u, "magnitude_unit": magnitude_unit,
        "parameters": [{"name": n, "value": float(v), "u": float(uu), "unit": un}
                       for n, v, uu, un in zip(term.param_names, theta, theta_u, term.param_units)],
        "degenerate_with": list(f["degenerate_with"]),
        "correlated_with_calibrated": f["correlated_nominal"],
        "separate_by": sorted(separate_by) if (f["degenerate_with"] or f["correlated_nominal"]) else [],
    }


def verdict_sentence(findings: list, unexplained: list, *, name_of: dict, n_obs: int, obs_noun: str,
                     floor_sd, floor_axes: str, held_out_before: float, held_out_after: float,
                     clean_examples: str, unit: str = "px") -> str:
    """The one-sentence verdict every adapter writes first in its report.

    findings: dicts with name, magnitude, magnitude_unit, significance_sigma, degenerate_with (term ids);
    unexplained: dicts with axis, significance_sigma, amplitude_rms_px; name_of: term id -> name;
    floor_sd: (2,) independent noise floor per image axis [unit]; clean_examples: the adapter's "no X above
    L and no Y above M" clause for the no-discrepancy case.
    """
    if not findings and not unexplained:
        return (f"No significant discrepancy: the nominal model explains the {n_obs} {obs_noun} down to the "
                f"noise floor ({floor_sd[0]:.3g} / {floor_sd[1]:.3g} {unit} in {floor_axes}); e.g. {clean_examples}.")
    if findings:
        f0 = findings[0]
        alt = (f" (or, indistinguishable here, {', '.join(name_of[d] for d in f0['degenerate_with'])})"
               if f0["degenerate_with"] else "")
        out = (f"The nominal model leaves out {f0['name']}{alt}: {_fmt(f0['magnitude'], f0['magnitude_unit'])} "
               f"at {f0['significance_sigma']:.1f} sigma; with it the held-out residual falls from "
               f"{held_out_before:.4g} to {held_out_after:.4g} {unit} (noise floor {floor_sd[0]:.3g} {unit}).")
        if len(findings) > 1:
            out += " Also: " + "; ".join(f"{f['name']} ({_fmt(f['magnitude'], f['magnitude_unit'])})"
                                         for f in findings[1:]) + "."
        if unexplained:
            out += f" Structure along {unexplained[0]['axis']} remains unexplained."
        return out
    e = unexplained[0]
    return (f"Structure beyond the noise floor along {e['axis']} ({e['significance_sigma']:.1f} sigma, "
            f"{e['amplitude_rms_px']:.3g} {unit} rms) that no catalogue term explains; absorbed only by an "
            f"empirical term, physics unknown.")


def unexplained_entries(remaining: list) -> list:
    """discrepancy.json ``unexplained`` entries from :func:`locate` results left after the named terms."""
    return [{"axis": e["axis"], "significance_sigma": e["significance_sigma"], "delta_bic": e["delta_bic"],
             "amplitude_rms_px": e["amplitude_rms"], "amplitude_max_px": e["amplitude_max"],
             "absorbed_by": f"empirical:{e['axis']}"} for e in remaining]
