"""Run the user's command on independently rendered recordings and compare with the truth.

One case = ct_indep_gen.generate (recording + YAML in one directory, the truth in ANOTHER directory) ->
``scripts/ros2run ct_calib_nodes ct_offline_solve REC --out OUT`` (a subprocess, as a user runs it) ->
results.json (static estimate, covariance, variance factor) and results.mcap (/ct/observations: every
detection of every frame with its identity and flag) compared with the truth:

* z-scores of the 13 parameters (the 7 instrument ones always; the object pose when the solver kept the
  file's labelling: the helix is symmetric under turning it upside down and may be relabelled);
* the convention-free end metric: sphere centre projections of the file's centres predicted by the
  fitted parameters vs by the true ones (this module's own projection code), over every view, with
  the uncertainty the reported covariance gives each (J C J^T, J by central differences);
* detections: every sphere visible (in view, its shadow clear of others) found; accepted detections
  that are no sphere (false) or carry another sphere's id; each accepted centre's error against the
  true ellipse centre (centre projection + the cone-section shift the ct_core doc states) relative to
  its reported sigma, with its radial component (from the principal point) to show a radial pattern.
Shared by tests/ct_validation/test_ct_indep.py and tests/benchmarks/validate_ct_indep.py.
"""

from __future__ import annotations

import json
import pathlib
import resource
import subprocess
import time

import numpy as np

import ct_indep_gen as gen

ROOT = gen.ROOT
N_INSTRUMENT = 7


def _children_cpu():
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_solver(rec_dir, out_dir, timeout=900):
    """The user's command (README): scripts/ros2run ct_calib_nodes ct_offline_solve REC --out OUT."""
    cmd = [str(ROOT / "scripts" / "ros2run"), "ct_calib_nodes", "ct_offline_solve", str(rec_dir), "--out",
           str(out_dir), "--workers", "1", "--history", "none"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def read_detections(results_mcap):
    """[(rotary angle, [(sphere_id, flag, col, row, sigma_px, semi_minor_px, reason), ...]) per frame]."""
    from rosbags.highlevel import AnyReader

    frames = []
    with AnyReader([pathlib.Path(results_mcap)]) as r:
        conns = [c for c in r.connections if c.topic.endswith("ct/observations")]
        for c, _, raw in r.messages(connections=conns):
            m = r.deserialize(raw, c.msgtype)
            frames.append((float(m.rotary_angle_rad), [(int(o.sphere_id), int(o.flag), float(o.col_px), float(o.row_px),
                                                        float(o.sigma_px), float(o.semi_minor_px), str(o.reason))
                                                       for o in m.observations]))
    return frames


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def labelling(w_fit, w_true, c_file):
    """How the solver labelled the spheres: (perm, matched, kind).

    perm[i] = the true sphere nearest to where the fit puts file sphere i at alpha = 0; matched[i] = it is
    within 0.5 mm. kind: "file" (perm = identity), "upside_down" (the helix49 symmetry i -> N-1-i, which
    the solver may legitimately use), or "wrong" (any other: the helix is screw-symmetric, so a labelling
    shifted along it fits all but its end spheres)."""
    fit = gen.Instrument(np.asarray(w_fit), 0, 0, 1, 1, 1)
    tru = gen.Instrument(np.asarray(w_true), 0, 0, 1, 1, 1)
    a = c_file @ fit.r_obj.T + fit.w[7:10]
    b = c_file @ tru.r_obj.T + tru.w[7:10]
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
    perm, matched = np.argmin(d, axis=1), np.min(d, axis=1) < 5e-4
    n = len(perm)
    kind = ("file" if np.all(perm == np.arange(n)) and matched.all() else
            "upside_down" if np.all(perm == np.arange(n)[::-1]) and matched.all() else "wrong")
    return perm, matched, kind


def pixel_discrepancy(w_fit, cov, w_true, c_file, perm, matched, truth):
    """Predicted centre projections, fitted vs true geometry, with the fitted ones' standard uncertainty
    (file spheres the fit places on a true sphere: all of them unless the labelling is wrong)."""
    c_file, c_true_of = c_file[matched], c_file[perm[matched]]
    alphas = np.array([v["alpha"] for v in truth["views"]])
    p_fit = gen.predicted_px(w_fit, c_file, alphas, truth)
    p_true = gen.predicted_px(w_true, c_true_of, alphas, truth)
    h = np.sqrt(np.diag(cov)) * 1e-3
    jac = np.stack([(gen.predicted_px(w_fit + h[i] * np.eye(13)[i], c_file, alphas, truth)
                     - gen.predicted_px(w_fit - h[i] * np.eye(13)[i], c_file, alphas, truth)) / (2 * h[i])
                    for i in range(13)], axis=-1)                         # (views, N, 2, 13)
    sd = np.sqrt(np.einsum("...i,ij,...j->...", jac, cov, jac))
    inside = ((p_true[..., 0] > 0) & (p_true[..., 0] < truth["cols"] - 1) & (p_true[..., 1] > 0)
              & (p_true[..., 1] < truth["rows"] - 1))
    d = (p_fit - p_true)[inside]
    z = d / sd[inside]
    return {"max_px": float(np.max(np.abs(d))), "rms_px": float(np.sqrt(np.mean(d ** 2))),
            "sd_rms_px": float(np.sqrt(np.mean(sd[inside] ** 2))), "max_abs_z": float(np.max(np.abs(z))),
            "rms_z": float(np.sqrt(np.mean(z ** 2)))}


# A shadow whose geometric gap to every other shadow is at least this must be found. The detector rejects
# pairs whose thresholded (blurred, so larger) outlines are closer than 4 px; with a PSF of up to ~1 px sd
# that is a geometric gap of up to ~6 px. Closer pairs are counted per gap bin, not required.
CLEAR_GAP_PX = 6.0
GAP_BINS_PX = (0.0, 2.0, 4.0, 6.0)


def _miss_reason(detail):
    """The reason code of a refused observation's text; ``overlap`` split into ``overlap_merged`` (the
    blob's shape: merged shadows) and ``overlap_proximity`` (threshold outlines closer than the margin)."""
    code = detail.split(":")[0] or "accepted, wrong id"
    if code == "overlap":
        code += "_merged" if "merged" in detail else "_proximity" if "neighbouring" in detail else ""
    return code


def detection_check(frames, truth, legit, id_index, w_true):
    """Visible spheres found, false / misidentified detections, centre errors against the truth.

    legit[i] = the true sphere that file sphere i is under the labelling a correct identification gives
    (the file's, or its upside-down image); a detection at sphere k named otherwise is found (detection)
    but misidentified (identity). Visible = shadow inside the detector, its gap to the nearest other shadow >= CLEAR_GAP_PX (computed
    with upper bounds of the shadow radii); spheres closer than that (but apart) are counted separately."""
    inst = gen.instrument_from(w_true, truth)
    pp = inst.principal_point_px
    alphas = np.array([v["alpha"] for v in truth["views"]])
    out = {"frames": len(frames), "visible": 0, "found_visible": 0, "close": 0, "found_close": 0, "accepted": 0,
           "false": 0, "misidentified": 0, "missed": [], "false_at": [], "missed_reasons": {},
           "by_gap": {f"{lo:g}-{hi:g}px": [0, 0] for lo, hi in zip(GAP_BINS_PX[:-1], GAP_BINS_PX[1:])}}
    errs, sig, radial = [], [], []
    for alpha, obs in frames:
        j = int(np.argmin(np.abs(_wrap(alphas - alpha))))
        v = truth["views"][j]
        cr, rad, gap = np.array(v["centre_px"]), np.array(v["shadow_radius_px"]), np.array(v["gap_px"])
        vis, close = gap >= CLEAR_GAP_PX, (gap > 0) & (gap < CLEAR_GAP_PX)
        found = np.zeros(len(cr), bool)
        for sid, flag, col, row, s, b, _ in obs:
            if flag != 0:
                continue
            out["accepted"] += 1
            dist = np.linalg.norm(cr - [col, row], axis=1)
            k = int(np.argmin(dist))
            if dist[k] > 0.5 * rad[k]:
                out["false"] += 1
                out["false_at"].append([j, round(col, 1), round(row, 1)])
                continue
            if sid not in id_index or legit[id_index[sid]] != k:
                out["misidentified"] += 1                     # found, but named as another sphere
            found[k] = True
            e_true = inst.ellipse_centre_px(cr[k], b)
            e = np.array([col, row]) - e_true
            errs.append(e)
            sig.append(s)
            rdir = cr[k] - pp
            radial.append(e @ rdir / max(np.linalg.norm(rdir), 1e-9))
        out["visible"] += int(vis.sum())
        out["found_visible"] += int((found & vis).sum())
        out["close"] += int(close.sum())
        for lo, hi in zip(GAP_BINS_PX[:-1], GAP_BINS_PX[1:]):
            sel = (gap > lo) & (gap < hi) if lo == 0 else (gap >= lo) & (gap < hi)
            out["by_gap"][f"{lo:g}-{hi:g}px"][0] += int(sel.sum())
            out["by_gap"][f"{lo:g}-{hi:g}px"][1] += int((sel & found).sum())
        out["found_close"] += int((found & close).sum())
        for k in np.flatnonzero(vis & ~found):
            out["missed"].append([j, int(k)])
            near = [_miss_reason(o[6]) for o in obs if np.hypot(o[2] - cr[k, 0], o[3] - cr[k, 1]) < 0.5 * rad[k]]
            reason = near[0] if near else "no detection"
            out["missed_reasons"][reason] = out["missed_reasons"].get(reason, 0) + 1
    errs, sig, radial = np.array(errs).reshape(-1, 2), np.array(sig), np.array(radial)
    if len(errs):
        out.update(n_err=len(errs), err_mean_px=errs.mean(axis=0).tolist(), err_rms_px=np.sqrt((errs ** 2).mean(axis=0)).tolist(),
                   radial_mean_px=float(radial.mean()), radial_sem_px=float(radial.std() / np.sqrt(len(radial))),
                   err_over_sigma_rms=np.sqrt(((errs / sig[:, None]) ** 2).mean(axis=0)).tolist(),
                   sigma_median_px=float(np.median(sig)))
    out["missed"] = out["missed"][:20]
    out["false_at"] = out["false_at"][:20]
    return out


def run_case(seed, work_dir, *, cols=512, n_views=36, vary_physics=True, object_tilt_deg=0.5):
    """Generate, solve with the user's command, compare. Returns a dict of figures (plain types)."""
    work_dir = pathlib.Path(work_dir)
    rec, truth_path, out = work_dir / "recordings" / f"scan_{seed}", work_dir / "truth" / f"{seed}.json", \
        work_dir / "solved" / f"scan_{seed}"
    c0 = time.process_time()
    truth = gen.generate(rec, truth_path, seed, cols=cols, n_views=n_views, vary_physics=vary_physics,
                         object_tilt_deg=object_tilt_deg)
    cpu_gen = time.process_time() - c0
    ch0, t0 = _children_cpu(), time.monotonic()
    proc = run_solver(rec, out)
    cpu_solve, wall_solve = _children_cpu() - ch0, time.monotonic() - t0
    case = {"seed": seed, "cpu_generate_s": round(cpu_gen, 2), "cpu_solve_s": round(cpu_solve, 2),
            "wall_solve_s": round(wall_solve, 1)}
    if proc.returncode != 0:                 # the command refused the data (e.g. the quality gate): a finding
        lines = [ln for ln in proc.stdout.splitlines() if "problem" in ln or "identity" in ln or "pose" in ln]
        case.update(outcome="no_result", physics=truth["physics"],
                    object_tilt_deg=np.degrees(truth["w"][10:13:2]).tolist(),
                    message=f"exit {proc.returncode}: " + " | ".join(lines)[-1500:] + proc.stderr[-500:])
        return case
    case.update(evaluate(out, truth))
    return case


def evaluate(out, truth):
    """Figures of one solved recording (``out``: the ct_offline_solve output directory) against its truth."""
    out = pathlib.Path(out)
    r = json.loads((out / "results.json").read_text())
    st = r["static"]
    case = {"physics": truth["physics"], "object_tilt_deg": np.degrees(truth["w"][10:13:2]).tolist(),
            "srd_m": truth["srd_reported_m"], "pitch_m": truth["pitch_m"], "problems": r["problems"],
            "outcome": st["outcome"] if st else "none"}
    if not st or st["outcome"] != "success":
        case["message"] = st["message"] if st else "no static result"
        return case
    assert tuple(st["names"]) == gen.PARAM_NAMES, st["names"]
    x, std, cov = np.array(st["x"]), np.array(st["std"]), np.array(st["covariance"])
    w = np.array(truth["w"])
    ids, c_file = gen.load_reference()[:2]
    perm, matched, kind = labelling(x, w, c_file)
    same_labels = kind == "file"
    legit = np.arange(len(perm))[::-1] if kind == "upside_down" else np.arange(len(perm))
    err = x - w
    err[10:13] = _wrap(err[10:13])
    z = err / std
    case.update(z=z[:N_INSTRUMENT].tolist() + (z[N_INSTRUMENT:].tolist() if same_labels else [None] * 6),
                err=err[:N_INSTRUMENT].tolist(), std=std[:N_INSTRUMENT].tolist(), same_labels=same_labels,
                labelling=kind, labels_unmatched=int((~matched).sum()),
                label_shift=sorted({int(v) for v in (perm - np.arange(len(perm)))[matched]}),
                identity_messages=[m["message"][:200] for m in r["identity"]], variance_factor=st["variance_factor"], rms_px=st["rms_px"],
                noise_factors=[st["noise"]["factor_u"], st["noise"]["factor_v"]], n_obs=st["n_obs"],
                chi2_instrument=float(err[:N_INSTRUMENT] @ np.linalg.solve(cov[:N_INSTRUMENT, :N_INSTRUMENT],
                                                                            err[:N_INSTRUMENT])))
    nz = st["noise"]
    if "track_lag_corr_u" in nz:                  # the correlation along sphere tracks (noise.py), diagnostic
        infl = nz.get("track_sd_inflation") or [1.0] * len(x)
        case["track"] = {"lag1_u": (nz["track_lag_corr_u"] or [None])[0], "lag1_v": (nz["track_lag_corr_v"] or [None])[0],
                         "lags_used_u": len(nz["track_corr_u"]), "lags_used_v": len(nz["track_corr_v"]),
                         "sd_inflation_instrument": infl[:N_INSTRUMENT]}
    case["pixel"] = pixel_discrepancy(x, cov, w, c_file, perm, matched, truth)
    id_index = {int(i): k for k, i in enumerate(ids)}
    case["detection"] = detection_check(read_detections(out / "results.mcap"), truth, legit, id_index, w)
    return case
