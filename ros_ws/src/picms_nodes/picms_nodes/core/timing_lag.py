"""Clock lag of the tracker's stamps against the stage's, from readings taken while the stage moves.

The calibration uses settled stations only, where a clock offset moves nothing. Every recording also
holds the moves between stations: the tracker keeps reading the constellation SMRs (INTERFACES.md:
readings all the time, each with its own stamp) while the encoders stream joint_states. The axes do
not move in step (each has its own profile), so the path between two stations is not straight. A
constellation SMR read at time t during the move from station k to k+1 sits at

    x(t) = X_k + M (q(t) - q_k) + e_k lambda(t),
    e_k = X_k+1 - X_k - M (q_k+1 - q_k),   lambda(t) = (q(t) - q_k) . (q_k+1 - q_k) / |q_k+1 - q_k|^2,

with X_k its mean reading at station k, q(t) the encoders (interpolated at t) and M the SMR's
displacement per encoder metre fitted to its own station means (X_k = c + M q_k, least squares). No
calibrated quantity enters, and the move's own misfit e_k (error motions, squareness) is spread along
it. A tracker whose stamps run late by L read x(t - L) at stamp t; L is fitted by Gauss-Newton over
every reading of every move. The noise floor comes from the data: the reading
scatter at the settled stations, and the scatter of the per-move estimates about the common one (a
factor of at least 1 on the uncertainty). Held-out: folds over moves (fit on the others, predict).
Pure numpy; no ROS.
"""
from __future__ import annotations

import numpy as np

from .calibrate import assign, settled_windows

MIN_MOVE_M = 1e-5           # moves shorter than this carry no timing information
DERIV_H_S = 0.004           # finite-difference step of the model's time derivative (d r / d L)


def _interp_q(t_s, ts, qs):
    return np.column_stack([np.interp(t_s, ts, qs[:, a]) for a in range(3)])


def _moves(stamps_ns, positions, tracker, names):
    """Per move: (q_k, q_k+1, {name: (X_k, X_k+1, M (3, 3), t_i (n,), x_i (n, 3))}); the settled scatter
    (list of deviations from their window means); the joint_states' times [s from the first] and positions."""
    o = np.argsort(np.asarray(stamps_ns, np.int64), kind="stable")
    st = np.asarray(stamps_ns, np.int64)[o]
    qs = np.asarray(positions, float)[o]
    t0 = int(st[0]) if st.size else 0
    win = settled_windows(st, qs)
    by_name = {n: ([], []) for n in names}
    for stamp, name, p in tracker:
        if name in by_name:
            by_name[name][0].append((int(stamp) - t0) * 1e-9)
            by_name[name][1].append(np.asarray(p, float))
    arr = {}
    for n, (tt, xx) in by_name.items():
        if tt:
            k = np.argsort(tt, kind="stable")
            arr[n] = (np.asarray(tt)[k], np.asarray(xx)[k])
    ws = [((w.start_ns - t0) * 1e-9, (w.end_ns - t0) * 1e-9, w.q) for w in win]
    means, scatter = [], []
    for station in assign(win, [], [r for r in tracker if r[1] in arr]):      # the calibration's grouping
        m = {}
        for n, xs in station.readings.items():
            k = len(xs)
            if k >= 2:
                xx = np.array(xs)
                m[n] = xx.mean(0)
                scatter.append((xx - m[n]) * np.sqrt(k / (k - 1)))    # about a mean of k: unbiased
        means.append(m)
    Ms = {}
    for n in arr:
        ks = [k for k in range(len(ws)) if n in means[k]]
        if len(ks) >= 5:
            A = np.column_stack([np.array([ws[k][2] for k in ks]), np.ones(len(ks))])
            Ms[n] = np.linalg.lstsq(A, np.array([means[k][n] for k in ks]), rcond=None)[0][:3].T   # (3, 3)
    moves = []
    for k in range(len(ws) - 1):
        (_a, b, qa), (c, _d, qb) = ws[k], ws[k + 1]
        if np.linalg.norm(qb - qa) < MIN_MOVE_M:
            continue
        per = {}
        for n, (tt, xx) in arr.items():
            if n in means[k] and n in means[k + 1] and n in Ms:
                sel = (tt > b) & (tt < c)
                if sel.any():
                    per[n] = (means[k][n], means[k + 1][n], Ms[n], tt[sel], xx[sel])
        if per:
            moves.append((qa, qb, per))
    return moves, scatter, (st - t0) * 1e-9, qs


def _blocks(moves, L, ts, qs):
    """Residuals r (n, 3) [m] and their derivative g = dr/dL (n, 3) [m/s] per move, at lag L."""
    out = []
    for qa, qb, per in moves:
        rs, gs = [], []
        for Xa, Xb, M, tt, xx in per.values():
            e = Xb - Xa - M @ (qb - qa)
            rs.append(xx - _model(tt - L, Xa, M, e, qa, qb, ts, qs))
            # d r / d L = + dx/dt at t - L
            gs.append((_model(tt - L + DERIV_H_S, Xa, M, e, qa, qb, ts, qs)
                       - _model(tt - L - DERIV_H_S, Xa, M, e, qa, qb, ts, qs)) / (2 * DERIV_H_S))
        out.append((np.vstack(rs), np.vstack(gs)))
    return out


def _model(t, Xa, M, e, qa, qb, ts, qs):
    q = _interp_q(t, ts, qs)
    d = qb - qa
    return Xa + (q - qa) @ M.T + np.outer((q - qa) @ d / (d @ d), e)


def _fit(moves, ts, qs, L0=0.0, iters=8):
    L = L0
    for _ in range(iters):
        bl = _blocks(moves, L, ts, qs)
        gg = sum(float(np.sum(g * g)) for _r, g in bl)
        if gg <= 0:
            return L, bl, 0.0
        step = -sum(float(np.sum(g * r)) for r, g in bl) / gg
        step = float(np.clip(step, -0.1, 0.1))
        L += step
        if abs(step) < 1e-7:
            break
    bl = _blocks(moves, L, ts, qs)
    return L, bl, sum(float(np.sum(g * g)) for _r, g in bl)


def estimate(stamps_ns, positions, tracker, names, *, n_folds: int = 5) -> dict:
    """The lag L [s] (tracker stamps late by L) with its uncertainty, or why it cannot be seen.

    stamps_ns, positions: joint_states (N,), (N, 3) m; tracker: [(stamp_ns, name, (3,) m)]; names: the
    constellation SMRs (bodies that move with the stage). Returns a dict: ``seen`` (bool), ``reason`` when
    not, else lag_s, u_lag_s, n_readings, n_moves, sigma_m (settled reading scatter, per axis), factor
    (per-move scatter over its expectation), rms_before_m / rms_after_m and held_out_rms_before_m /
    held_out_rms_after_m (readings while moving, without and with the lag), per_move (lag_s, u_s)."""
    if len(stamps_ns) < 3:
        return {"seen": False, "reason": "no stage readings (joint_states)"}
    moves, scatter, ts, qs = _moves(stamps_ns, positions, tracker, names)
    if len(moves) < 2:
        return {"seen": False, "reason": "fewer than two moves between settled stations with constellation readings "
                                         "on both ends and while moving"}
    dev = np.vstack(scatter) if scatter else np.zeros((0, 3))
    if dev.shape[0] < 10:
        return {"seen": False, "reason": "too few readings at the settled stations for a noise floor"}
    sigma = float(1.4826 * np.median(np.abs(dev - np.median(dev, 0))))
    L, bl, gg = _fit(moves, ts, qs)
    if gg <= 0 or sigma <= 0:
        return {"seen": False, "reason": "no tracker readings while the stage moved"}
    # per-move estimates about the common one (linearised there): the floor's check on the model
    per = []
    for r, g in bl:
        gm = float(np.sum(g * g))
        if gm > 0:
            per.append((L - float(np.sum(g * r)) / gm, sigma / np.sqrt(gm)))
    pm = np.array(per)
    chi2 = float(np.sum(((pm[:, 0] - L) / pm[:, 1]) ** 2))
    factor = float(np.sqrt(chi2 / max(len(pm) - 1, 1)))
    u = sigma / np.sqrt(gg) * max(1.0, factor)
    n = int(sum(r.shape[0] for r, _g in bl))
    r0 = _blocks(moves, 0.0, ts, qs)
    rms0 = float(np.sqrt(np.mean(np.vstack([r for r, _g in r0]) ** 2)))
    rms1 = float(np.sqrt(np.mean(np.vstack([r for r, _g in bl]) ** 2)))
    # held-out: folds over moves
    ho0, ho1 = [], []
    for f in range(min(n_folds, len(moves))):
        train = [m for i, m in enumerate(moves) if i % n_folds != f]
        test = [m for i, m in enumerate(moves) if i % n_folds == f]
        Lf, _b, _gg = _fit(train, ts, qs)
        ho0 += [r for r, _g in _blocks(test, 0.0, ts, qs)]
        ho1 += [r for r, _g in _blocks(test, Lf, ts, qs)]
    return {"seen": True, "lag_s": float(L), "u_lag_s": float(u), "n_readings": n, "n_moves": len(moves),
            "sigma_m": sigma, "factor": factor, "rms_before_m": rms0, "rms_after_m": rms1,
            "held_out_rms_before_m": float(np.sqrt(np.mean(np.vstack(ho0) ** 2))),
            "held_out_rms_after_m": float(np.sqrt(np.mean(np.vstack(ho1) ** 2))),
            "per_move": pm.tolist()}
