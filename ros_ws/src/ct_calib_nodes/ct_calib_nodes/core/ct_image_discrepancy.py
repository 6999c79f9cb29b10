"""Image-level discrepancy checks of a CT recording (issue 11, "where centres hide the effect").

The calibrated geometry is rendered with the project's renderer (core/render.py, noiseless, unblurred
transmission, the reference object as its YAML gives it) for a few projections of the first stage
position, and the recorded frames are compared with it in the neighbourhood of every sphere shadow
(a box of the shadow plus ``RING_PX``). What the nominal image model may get wrong without it being
physics the engine should name is a nuisance, fitted per box: a local background (offset and gradient:
flat-field errors, the heel effect, a support tube or holder crossing the box), the shadow contrast
(gain, counts) and the attenuation (``T ln T``: the spheres' effective attenuation, beam hardening);
the detector blur is one Gaussian sigma fitted for the whole recording. What is left is tested against
three named image terms (a catalogue like the feature-level one; each one basis with a physical name):

* ``scatter_glare``: a fraction f of the transmitted intensity spread by a wide kernel (scatter in the
  object, detector glare / veiling): ``T' = (1 - f) B(T) + f G(T)``, G a Gaussian of ``HALO_SIGMA_PX``;
  a halo around every shadow, symmetric, so the centres do not move.
* ``detector_lag``: a fraction of the previous projection's signal deficit persists (scintillator
  afterglow, lag): ``T'_k = B(T_k) - a (1 - B(T_{k-1}))``; a ghost of the previous shadow.
* ``source_output_drift``: the open-beam intensity drifts during the scan while the flat field is from
  before it: the shadow contrast changes linearly in time (slope of the per-projection contrast scale
  against the scan time, tested against the scatter of those scales between projections).

Noise floor from the data: the pixel noise is ``s0 sqrt(T)`` (counting statistics) with s0 the robust
(MAD) scale of differences between horizontally neighbouring residual pixels divided by sqrt 2. Each
term's significance is its chi-square reduction against that floor (generalised least squares with the
nuisance projected out), accepted when delta BIC > 10 (as the feature level); its detection limit is the
amplitude found with 90 % power. Structure that none of them explains is reported by ring (mean residual
per distance band from the shadow edge) without a physical name.

numpy/scipy/cv2 only; no truth: the frames, their angles and stamps, the calibrated 13 parameters, the
reference object, the detector and the flat-field level are all that enter.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import stats

from .discrepancy import BIC_THRESHOLD, required_noncentrality, sigma_from_chi2
from .render import RenderSettings, render_projection

RING_PX = 10            # box margin beyond the shadow's semi-major axis [px]
HALO_SIGMA_PX = 6.0     # width of the scatter / glare kernel [px]
LIMIT_POWER = 0.9
OUTLIER_Z = 4.0         # pixels further than this from the model (in floor units) are masked with their neighbours


@dataclass
class ImageFrame:
    """One recorded projection as transmission I / I0 (float32, rows x cols), with its stage reading."""

    transmission: np.ndarray
    alpha_rad: float
    stamp_ns: int


def pick_pairs(n_frames: int, n_pairs: int) -> list:
    """Indices (k-1, k) of ``n_pairs`` consecutive-projection pairs spread over a scan of n_frames."""
    if n_frames < 2:
        return []
    ks = np.unique(np.linspace(1, n_frames - 1, max(1, min(n_pairs, n_frames - 1))).round().astype(int))
    return [(int(k) - 1, int(k)) for k in ks]


def _blur(img, sigma):
    if sigma <= 0:
        return img
    return cv2.GaussianBlur(img, (0, 0), float(sigma), borderType=cv2.BORDER_REPLICATE)


def _model(w, alpha, ref, detector, time_s=0.0):
    st = RenderSettings(poisson=False, blur_sigma_px=0.0, mu_tube_per_m=0.0)
    fr = render_projection(w, np.zeros(6), alpha, ref, detector, st, None, time_s=time_s, output="transmission")
    return fr.image.astype(np.float32), fr.truth


def _regions(truth, detector, ring=RING_PX):
    """Label image: each pixel within ``ring`` px of a shadow (by its ellipse's semi-major axis) gets the
    nearest shadow's index + 1, else 0; shadows whose region touches the image border are dropped."""
    c = truth.ellipse_centre_px
    a = truth.semi_axes_px[:, 0]
    rows, cols = detector.rows, detector.cols
    best = np.full((rows, cols), np.inf, dtype=np.float32)
    lab = np.zeros((rows, cols), dtype=np.int32)
    for i in range(len(c)):
        r0, r1 = int(np.floor(c[i, 1] - a[i] - ring)), int(np.ceil(c[i, 1] + a[i] + ring)) + 1
        c0, c1 = int(np.floor(c[i, 0] - a[i] - ring)), int(np.ceil(c[i, 0] + a[i] + ring)) + 1
        if r0 < 0 or c0 < 0 or r1 > rows or c1 > cols:
            continue
        rr, cc = np.mgrid[r0:r1, c0:c1]
        d = (np.hypot(cc - c[i, 0], rr - c[i, 1]) - a[i]).astype(np.float32)
        sub_b, sub_l = best[r0:r1, c0:c1], lab[r0:r1, c0:c1]
        take = (d < ring) & (d < sub_b)
        sub_b[take] = d[take]
        sub_l[take] = i + 1
    return lab


def _region_solve(rid, n_reg, x, ys, wgt=None):
    """Per-region least squares of each column of ys (n, m) on the region's columns x (n, p), vectorised
    (normal equations from bincounts). Returns the residuals (n, m), weighted by ``wgt`` when given."""
    if wgt is not None:
        x = x * wgt[:, None]
        ys = ys * wgt[:, None]
    p, m = x.shape[1], ys.shape[1]
    a = np.empty((n_reg, p, p))
    for i in range(p):
        for j in range(i, p):
            a[:, i, j] = a[:, j, i] = np.bincount(rid, x[:, i] * x[:, j], n_reg)
    b = np.empty((n_reg, p, m))
    for i in range(p):
        for k in range(m):
            b[:, i, k] = np.bincount(rid, x[:, i] * ys[:, k], n_reg)
    a += np.eye(p)[None] * 1e-12 * np.trace(a, axis1=1, axis2=2)[:, None, None]
    beta = np.linalg.solve(a, b)                     # (n_reg, p, m)
    return ys - np.einsum("np,npm->nm", x, beta[rid]), beta


class _Frames:
    """Model images and the pixels of the shadow regions of the analysed frames (one long vector)."""

    def __init__(self, obs, t0, tprev, labels):
        self.t0, self.tprev = t0, tprev
        rows, cols = labels[0].shape
        self.shape = (rows, cols)
        fj, pix, rid = [], [], []
        n_reg = 0
        for j, lab in enumerate(labels):
            flat = lab.ravel()
            sel = np.flatnonzero(flat)
            ids, inv, cnt = np.unique(flat[sel], return_inverse=True, return_counts=True)
            ok = cnt[inv] >= 30
            sel, inv = sel[ok], inv[ok]
            _, inv = np.unique(inv, return_inverse=True)
            fj.append(np.full(sel.size, j))
            pix.append(sel)
            rid.append(inv + n_reg)
            n_reg += int(inv.max()) + 1 if inv.size else 0
        self.fj, self.pix, self.rid = np.concatenate(fj), np.concatenate(pix), np.concatenate(rid)
        self.n_reg = n_reg
        self.y = np.concatenate([o.ravel()[p] for o, p in zip(obs, pix)]).astype(float)
        rr, cc = np.divmod(self.pix, cols)
        cnt = np.bincount(self.rid, None, n_reg)
        mc = np.bincount(self.rid, cc, n_reg) / cnt
        mr = np.bincount(self.rid, rr, n_reg) / cnt
        self.xn = (cc - mc[self.rid]) / 10.0
        self.yn = (rr - mr[self.rid]) / 10.0
        self.glare = self._gather([_blur(t, HALO_SIGMA_PX) for t in t0])
        tc = [np.clip(t, 1e-6, 1.0) for t in t0]
        self.tlnt = [t * np.log(t) for t in tc]

    def _gather(self, imgs):
        out = np.empty(self.pix.size)
        for j, img in enumerate(imgs):
            m = self.fj == j
            out[m] = img.ravel()[self.pix[m]]
        return out

    def nuisance(self, sigma):
        b = self._gather([_blur(t, sigma) for t in self.t0])
        btl = self._gather([_blur(t, sigma) for t in self.tlnt])
        return np.stack([np.ones_like(b), self.xn, self.yn, b - 1.0, btl], axis=1), b

    def residual_ss(self, sigma):
        x, _ = self.nuisance(sigma)
        r, _ = _region_solve(self.rid, self.n_reg, x, self.y[:, None])
        return float(np.sum(r ** 2))


def analyse_images(frames, pairs: list, w, ref, detector, scan_ns=(0, 0), *, progress=None) -> dict:
    """Image-level checks on the frame pairs (k-1, k); ``frames`` maps those indices (recording order of the
    first stage position) to ImageFrames; ``scan_ns`` = (first, last) stamp of the scan. Returns a plain dict."""
    say = progress or (lambda _m: None)
    if not pairs:
        return {"performed": False, "why": "fewer than two projections"}
    t_min = float(scan_ns[0])
    span = float(scan_ns[1] - scan_ns[0])
    obs, t0s, tps, labels, taus = [], [], [], [], []
    for kp, k in pairs:
        f, fp = frames[k], frames[kp]
        t0, truth = _model(w, f.alpha_rad, ref, detector)
        tp, _ = _model(w, fp.alpha_rad, ref, detector)
        img = np.asarray(f.transmission, dtype=np.float32)
        lab = _regions(truth, detector)
        lab[~np.isfinite(img)] = 0
        obs.append(np.nan_to_num(img))
        t0s.append(t0)
        tps.append(tp)
        labels.append(lab)
        taus.append(0.0 if span <= 0 else (f.stamp_ns - t_min) / span - 0.5)
    fr = _Frames(obs, t0s, tps, labels)
    if fr.n_reg == 0:
        return {"performed": False, "why": "no sphere shadow fully on the detector"}
    # blur: golden-section search of the one Gaussian sigma [px]; its remaining error is a nuisance column
    lo, hi = 0.05, 2.5
    g = (np.sqrt(5) - 1) / 2
    a_, b_ = hi - g * (hi - lo), lo + g * (hi - lo)
    fa, fb = fr.residual_ss(a_), fr.residual_ss(b_)
    for _ in range(12):
        if fa < fb:
            hi, b_, fb = b_, a_, fa
            a_ = hi - g * (hi - lo)
            fa = fr.residual_ss(a_)
        else:
            lo, a_, fa = a_, b_, fb
            b_ = lo + g * (hi - lo)
            fb = fr.residual_ss(b_)
    sigma = 0.5 * (lo + hi)
    x, b = fr.nuisance(sigma)
    dlt = 0.02
    dbs = fr._gather([(_blur(t, sigma + dlt) - _blur(t, max(sigma - dlt, 1e-3))) / (2 * dlt) for t in fr.t0])
    x = np.hstack([x, dbs[:, None]])
    halo = fr.glare - b
    lag = fr._gather([_blur(t, sigma) for t in fr.tprev]) - 1.0
    sq = 1.0 / np.sqrt(np.clip(b, 1e-3, None))
    # floor: s0 from horizontally neighbouring residual pixels of the same region, in sqrt(T) units
    r0, beta0 = _region_solve(fr.rid, fr.n_reg, x, fr.y[:, None])
    zr = r0[:, 0] * sq
    nb = (np.diff(fr.pix) == 1) & (np.diff(fr.rid) == 0)
    dd = np.diff(zr)[nb]
    s0 = 1.4826 * float(np.median(np.abs(dd - np.median(dd)))) / np.sqrt(2.0)
    # regions with structure far beyond the floor after the nuisance (an edge of a support or holder the
    # reference object does not describe, a defect) are left out and counted: the named terms are judged
    # on the regions the nominal scene describes
    cnt = np.bincount(fr.rid, None, fr.n_reg)
    red = np.bincount(fr.rid, (zr / s0) ** 2, fr.n_reg) / np.maximum(cnt, 1)
    med = float(np.median(red))
    cut = med + max(0.25, 6.0 * 1.4826 * float(np.median(np.abs(red - med))))
    keep_reg = red <= cut
    excluded = int(np.count_nonzero(~keep_reg))
    # and, in the regions kept, pixels beyond OUTLIER_Z of the floor with their 8 neighbours (lines of a
    # support's wall crossing a region; counting noise alone removes ~0.4 % of the pixels)
    rows, cols = fr.shape
    out_px = np.zeros(fr.pix.size, dtype=bool)
    for j in range(len(pairs)):
        m = fr.fj == j
        im = np.zeros(rows * cols, dtype=np.uint8)
        im[fr.pix[m][np.abs(zr[m] / s0) > OUTLIER_Z]] = 1
        im = cv2.dilate(im.reshape(rows, cols), np.ones((3, 3), np.uint8)).ravel()
        out_px[m] = im[fr.pix[m]] > 0
    keep = keep_reg[fr.rid] & ~out_px
    masked_fraction = float(np.count_nonzero(keep_reg[fr.rid] & out_px) / max(np.count_nonzero(keep_reg[fr.rid]), 1))
    reg_frame = np.zeros(fr.n_reg, dtype=int)
    reg_frame[fr.rid] = fr.fj
    level = {}
    for rg in np.flatnonzero(keep_reg):
        level.setdefault(int(reg_frame[rg]), []).append(float(beta0[rg, 0, 0]))   # background (B(T0) - 1 = 0)
    # whitened, nuisance-projected data and bases of the two pixel terms (kept regions)
    rid_k = np.unique(fr.rid[keep], return_inverse=True)[1]
    n_k = int(rid_k.max()) + 1
    wgt = sq[keep] / s0
    res, _ = _region_solve(rid_k, n_k, x[keep], np.stack([fr.y[keep], halo[keep], lag[keep]], axis=1), wgt)
    z, h, lg = res[:, 0], res[:, 1], res[:, 2]
    n_pix = int(z.size)
    ln_n = np.log(max(n_pix, 2))
    crit = ln_n + BIC_THRESHOLD
    lam = required_noncentrality(crit, 1, LIMIT_POWER)
    terms = {}
    basis = np.stack([h, lg], axis=1)
    beta_j = np.linalg.lstsq(basis, z, rcond=None)[0]
    cov_j = np.linalg.pinv(basis.T @ basis)
    for i, tid in enumerate(("scatter_glare", "detector_lag")):
        v, other = basis[:, i], basis[:, 1 - i]
        vp = v - other * (other @ v) / max(other @ other, 1e-300)
        fisher = float(vp @ vp)
        d_chi2 = float((vp @ z) ** 2 / max(fisher, 1e-300))
        terms[tid] = {"value": float(beta_j[i] * 100), "u": float(np.sqrt(cov_j[i, i]) * 100), "unit": "%",
                      "delta_chi2": d_chi2, "significance_sigma": sigma_from_chi2(d_chi2, 1),
                      "delta_bic": d_chi2 - ln_n, "limit": float(np.sqrt(lam / max(fisher, 1e-300)) * 100)}
    # output drift: slope of the per-projection background level (median over the shadow regions; the flat
    # field normalises it to 1) in scan time, against the scatter of those levels about the line
    cs = np.array([np.median(level[j]) for j in range(len(pairs)) if j in level])
    tt = np.array([taus[j] for j in range(len(pairs)) if j in level])
    if span > 0 and cs.size >= 4 and np.ptp(tt) > 0:
        fit = stats.linregress(tt, cs / np.mean(cs))
        dof = cs.size - 2
        tstat = fit.slope / max(fit.stderr, 1e-300)
        p = 2 * stats.t.sf(abs(tstat), dof)
        need = _sigma_needed(cs.size)
        t_crit = stats.t.isf(stats.norm.sf(need), dof)
        terms["source_output_drift"] = {
            "value": float(fit.slope * 100), "u": float(fit.stderr * 100), "unit": "% over the scan",
            "significance_sigma": float(stats.norm.isf(max(p / 2, 1e-300))), "delta_chi2": float(tstat ** 2),
            "delta_bic": float(tstat ** 2 - np.log(cs.size)), "accept_sigma": need,
            "limit": float((t_crit + stats.t.isf(1 - LIMIT_POWER, dof)) * fit.stderr * 100)}
    else:
        terms["source_output_drift"] = {"value": None, "u": None, "unit": "% over the scan", "limit": None,
                                        "cannot_see": "fewer than 4 analysed projections with time stamps"}
    findings = []
    for tid, t in terms.items():
        if t.get("value") is None:
            continue
        hit = (t["significance_sigma"] >= t["accept_sigma"]) if tid == "source_output_drift" \
            else t["delta_bic"] > BIC_THRESHOLD
        if hit:
            findings.append({"term": tid, **{k: IMAGE_TERMS[tid][k] for k in ("name", "mechanism")}, **t})
    findings.sort(key=lambda f: -f["significance_sigma"])
    zres = z - basis @ beta_j
    bands = _bands(fr, keep, zres, t0s)
    say(f"image level: {len(pairs)} projection pairs, {fr.n_reg} shadows ({excluded} left out), {n_pix} px "
        f"({100 * masked_fraction:.2g} % masked), "
        f"blur {sigma:.2f} px, pixel floor {s0:.4g} sqrt(T); "
        + (", ".join(f"{f['term']} {f['value']:.3g} {f['unit']} ({f['significance_sigma']:.1f} sigma)"
                     for f in findings) or "nothing named"))
    return {"performed": True, "pairs": [list(p) for p in pairs], "n_shadows": int(fr.n_reg), "n_pixels": n_pix,
            "excluded_shadows": excluded, "masked_pixel_fraction": masked_fraction, "excluded_rule": f"chi2 per pixel after the nuisance above {cut:.3g} "
            f"(median {med:.3g}): structure the nominal scene does not describe (e.g. a support or holder edge)",
            "blur_sigma_px": sigma, "pixel_floor_sqrtT": s0, "terms": terms, "findings": findings,
            "residual_by_band": bands,
            "nuisance": "per shadow region: offset, gradient, contrast, attenuation (T ln T), blur derivative; "
                        "one blur sigma",
            "catalogue": [{"id": k, **v} for k, v in IMAGE_TERMS.items()]}


def _bands(fr, keep, zres, t0s, edges=(-4, -1, 1, 3, 6, 10)):
    """Mean whitened residual (after nuisance and named terms) per band of distance from the shadow edge [px],
    with its significance (sigma; white-noise floor)."""
    dist = []
    for t0 in t0s:
        inside = (t0 < 0.999).astype(np.uint8)
        d_out = cv2.distanceTransform(1 - inside, cv2.DIST_L2, 3)
        d_in = cv2.distanceTransform(inside, cv2.DIST_L2, 3)
        dist.append(np.where(inside > 0, -d_in, d_out))
    d = fr._gather(dist)[keep]
    k = np.digitize(d, edges) - 1
    ok = (k >= 0) & (k < len(edges) - 1)
    nb = len(edges) - 1
    sums = np.bincount(k[ok], zres[ok], nb)
    cnt = np.bincount(k[ok], None, nb)
    return [{"from_px": edges[i], "to_px": edges[i + 1], "n": int(cnt[i]),
             "mean_sigma_units": float(sums[i] / max(cnt[i], 1)),
             "significance_sigma": float(abs(sums[i]) / np.sqrt(max(cnt[i], 1)))} for i in range(nb)]


def _sigma_needed(n):
    """Gaussian-equivalent significance a 1-parameter term needs at BIC > BIC_THRESHOLD with n samples."""
    return float(np.sqrt(np.log(max(n, 2)) + BIC_THRESHOLD))


IMAGE_TERMS = {
    "scatter_glare": {"name": "scatter / detector glare halo",
                      "mechanism": f"a fraction of the transmitted intensity is spread by a wide kernel (scatter in "
                                   f"the object, glare in the scintillator): a halo of about {HALO_SIGMA_PX:.0f} px "
                                   f"around every shadow that leaves the centres in place",
                      "reveal_by": "frames with dense shadows near the detector centre; a beam-stop measurement"},
    "detector_lag": {"name": "detector lag / afterglow ghost",
                     "mechanism": "a fraction of the previous projection's signal deficit persists (scintillator "
                                  "afterglow, detector lag): a ghost of the previous shadow in every frame",
                     "reveal_by": "fast rotation (shadows far apart between projections); dark frames after an "
                                  "exposure"},
    "source_output_drift": {"name": "source output drift (stale flat field)",
                            "mechanism": "the open-beam intensity changes during the scan while the flat field is "
                                         "from before it, so the shadow contrast changes with time",
                            "reveal_by": "a longer scan; open-beam frames at the start and end; a dose monitor"},
}
