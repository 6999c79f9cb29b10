"""Offline sim-to-real discrepancy check of a CT recording (issue 11).

    ct_discrepancy RECORDING [--instrument ct_instrument.yaml] [--reference-object reference_object.yaml]
                   [--out DIR] [--max-terms 4]

The recording is replayed exactly as ``ct_offline_solve`` does (detection, identity,
static solve with the nominal model); the first stage position's sphere centres and
the nominal calibration then go through the discrepancy engine
(core/ct_discrepancy.py). Written to ``--out`` (default ``<recording>_discrepancy``):
``discrepancy.json`` (keys documented in doc/ct_discrepancy.md), ``report.md`` (the
verdict first, then the tables) and PNG plots of the residual structure before and
after. Files are written under temporary names and renamed; nothing is written when
the recording gives no static calibration.

Exit status: 0 verdict written (adequate or not); 1 nothing usable; 2 bad arguments or files.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np


def _plots(out, tmp: pathlib.Path, detector) -> list:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    a = out["_arrays"]
    q = len(a["alpha"])
    files = []
    rb, ra = np.asarray(a["residual_before"]), np.asarray(a["residual_after"])
    for axis_name, xval, xlabel in (("angle", np.degrees(a["alpha"]), "rotary angle [deg]"),
                                    ("time", a["tau"], "scan time (normalised, -0.5 .. 0.5)")):
        fig, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
        for ax, comp, lab in ((axes[0], 0, "u (columns)"), (axes[1], 1, "v (rows)")):
            ax.plot(xval, rb[comp * q:(comp + 1) * q], ".", ms=1.5, alpha=0.5, label="before (nominal model)")
            ax.plot(xval, ra[comp * q:(comp + 1) * q], ".", ms=1.5, alpha=0.5, label="after (with the named terms)")
            ax.set_ylabel(f"residual {lab} [px]")
        axes[0].legend(markerscale=6, fontsize=8)
        axes[1].set_xlabel(xlabel)
        fig.suptitle(f"residual (observed - modelled) against {axis_name}")
        fig.tight_layout()
        name = f"residual_vs_{axis_name}.png"
        fig.savefig(tmp / name, dpi=90)
        plt.close(fig)
        files.append(name)
    # detector field: binned mean residual vectors
    uv = np.asarray(a["uv"])
    nb = 8
    ci = np.clip((uv[:, 0] / detector.cols * nb).astype(int), 0, nb - 1)
    ri = np.clip((uv[:, 1] / detector.rows * nb).astype(int), 0, nb - 1)
    key = ri * nb + ci
    fig, axes = plt.subplots(1, 2, figsize=(10, 5))
    for ax, r, title in ((axes[0], rb, "before"), (axes[1], ra, "after")):
        cnt = np.bincount(key, minlength=nb * nb)
        mu = np.bincount(key, r[:q], nb * nb) / np.maximum(cnt, 1)
        mv = np.bincount(key, r[q:], nb * nb) / np.maximum(cnt, 1)
        yy, xx = np.divmod(np.arange(nb * nb), nb)
        sel = cnt > 0
        ax.quiver((xx[sel] + 0.5) * detector.cols / nb, (yy[sel] + 0.5) * detector.rows / nb, mu[sel], -mv[sel],
                  angles="xy")
        ax.set_xlim(0, detector.cols)
        ax.set_ylim(detector.rows, 0)
        ax.set_title(f"mean residual per detector cell, {title}")
        ax.set_xlabel("column [px]")
        ax.set_ylabel("row [px]")
    fig.tight_layout()
    fig.savefig(tmp / "residual_detector_field.png", dpi=90)
    plt.close(fig)
    files.append("residual_detector_field.png")
    return files


def image_level(recording, res, instrument, ref, n_pairs: int, say, namespace: str = "/") -> dict:
    """Image-level checks (core/ct_image_discrepancy.py) on ``n_pairs`` consecutive-projection pairs of the
    first stage position, re-read from the recording and flat-fielded as the detector does."""
    from ct_calib_nodes.core import ct_image_discrepancy as imd  # noqa: PLC0415
    from ct_calib_nodes.core.detect import FrameError, to_transmission  # noqa: PLC0415
    from ct_calib_nodes.io import namespaces  # noqa: PLC0415
    from ct_calib_nodes.io.convert import MessageError, array_from_image, stamp_ns  # noqa: PLC0415
    from ct_calib_nodes.io.mcap_io import ReadReport, iter_recording  # noqa: PLC0415

    obs = res.acc.positions[0].observations()
    if obs.stamp_ns is None or n_pairs <= 0:
        return {"performed": False, "why": "no time stamps" if n_pairs > 0 else "not requested"}
    st, first = np.unique(obs.stamp_ns, return_index=True)
    alphas = obs.alpha_rad[first]
    pairs = imd.pick_pairs(len(st), n_pairs)
    want = {int(st[k]): k for p in pairs for k in p}
    image_topic = namespaces.topic(namespace, namespaces.CT_RAW[0])
    shape = (instrument.detector.rows, instrument.detector.cols)
    frames, problems = {}, []
    for m in iter_recording(recording, topics=(image_topic,), report=ReadReport(),
                            types={image_topic: "sensor_msgs/msg/Image"}):
        t = stamp_ns(m.msg.header.stamp)
        if t not in want or want[t] in frames:
            continue
        try:
            img, enc = array_from_image(m.msg, shape)
            tr = to_transmission(img, enc, instrument.flat_field(), shape, instrument.dark)
        except (MessageError, FrameError) as exc:
            problems.append(f"frame {t} ns: {exc}")
            continue
        frames[want[t]] = imd.ImageFrame(tr, float(alphas[want[t]]), t)
        if len(frames) == len(want):
            break
    pairs = [p for p in pairs if p[0] in frames and p[1] in frames]
    out = imd.analyse_images(frames, pairs, np.asarray(res.static.x[:13], float), ref, instrument.detector,
                             (int(st[0]), int(st[-1])), progress=say)
    out["problems"] = problems
    return out


def image_sentence(img: dict) -> str:
    if not img.get("performed"):
        return ""
    if not img["findings"]:
        lim = img["terms"]
        return (f" Image level: nothing named (no detector lag above {lim['detector_lag']['limit']:.2g} %, "
                f"no scatter/glare halo above {lim['scatter_glare']['limit']:.2g} %).")
    return " Image level: " + "; ".join(f"{f['name']} {f['value']:.3g} {f['unit']} ({f['significance_sigma']:.1f} sigma)"
                                        for f in img["findings"]) + "."


def write_report(out: dict, tmp: pathlib.Path, plots: list, recording) -> None:
    fb, fa = out["fit_before"], out["fit_after"]
    nf = out["noise_floor"]
    lines = [f"# Discrepancy report: {recording}", "", f"**{out['verdict']}**", "",
             f"Adequate (no significant structure left by the nominal model): **{out['adequate']}**", "",
             "## Noise floor (from the data)", "",
             f"{nf['method']}: independent {nf['independent_sd']['u']:.4g} / {nf['independent_sd']['v']:.4g} px "
             f"(u / v), shared per projection {nf['shared_per_projection_sd']['u']:.3g} / "
             f"{nf['shared_per_projection_sd']['v']:.3g} px; the detector stated a median sigma of "
             f"{nf['stated_sigma_median_px']:.4g} px.", "",
             "## Fit", "", "| | rms [px] | chi2/dof vs floor | held-out rms [px] |", "| --- | --- | --- | --- |",
             f"| before (nominal) | {fb['rms']:.5g} | {fb['chi2_dof']:.4g} | {fb['held_out_rms']:.5g} |",
             f"| after | {fa['rms']:.5g} | {fa['chi2_dof']:.4g} | {fa['held_out_rms']:.5g} |", "",
             "## Findings", ""]
    if not out["findings"]:
        lines.append("None.")
    for f in out["findings"]:
        lines += [f"### {f['name']} (`{f['term']}`)", "", f"{f['mechanism']}.", "",
                  f"Significance {f['significance_sigma']:.1f} sigma, delta BIC {f['delta_bic']:.1f}, held-out gain "
                  f"{f['cv_gain']:.4g} (chi2 per residual); magnitude {f['magnitude']:.4g} {f['magnitude_unit']}.", "",
                  "| parameter | value | u | unit |", "| --- | --- | --- | --- |"]
        lines += [f"| {p['name']} | {p['value']:.5g} | {p['u']:.2g} | {p['unit']} |" for p in f["parameters"]]
        if f["degenerate_with"]:
            lines += ["", f"Explains the data as well as: {', '.join(f['degenerate_with'])}."]
        if f["correlated_with_calibrated"]:
            lines += ["", f"Correlated (|r| > 0.9) with the calibrated {', '.join(f['correlated_with_calibrated'])}."]
        if f["separate_by"]:
            lines += ["", "Separate them by: " + "; ".join(f["separate_by"]) + "."]
        lines.append("")
    lines += ["## Structure no catalogue term explains", ""]
    lines += [f"- {u['axis']}: {u['significance_sigma']:.1f} sigma, {u['amplitude_rms_px']:.3g} px rms "
              f"(absorbed by `{u['absorbed_by']}`)" for u in out["unexplained"]] or ["None."]
    img = out.get("image_level") or {}
    lines += ["", "## Image level (difference of recorded and rendered frames)", ""]
    if not img.get("performed"):
        lines.append(f"Not performed: {img.get('why', 'not requested')}.")
    else:
        lines += [f"{len(img['pairs'])} projection pairs, {img['n_shadows']} shadow regions ({img['excluded_shadows']} "
                  f"left out: {img['excluded_rule']}), {img['n_pixels']} px; fitted blur {img['blur_sigma_px']:.3f} px; "
                  f"pixel floor {img['pixel_floor_sqrtT']:.4g} sqrt(T) (from the data). Nuisance: {img['nuisance']}.", "",
                  "| term | value | u | significance [sigma] | detection limit |", "| --- | --- | --- | --- | --- |"]
        for k, t in img["terms"].items():
            if t.get("value") is None:
                lines.append(f"| {k} | - | - | - | not visible: {t.get('cannot_see')} |")
            else:
                lines.append(f"| {k} | {t['value']:.4g} {t['unit']} | {t['u']:.2g} | {t['significance_sigma']:.1f} | "
                             f"{t['limit']:.3g} {t['unit']} |")
        lines += ["", "Residual by distance from the shadow edge (whitened mean, significance): " + "; ".join(
            f"{b['from_px']}..{b['to_px']} px: {b['mean_sigma_units']:+.3f} ({b['significance_sigma']:.1f})"
            for b in img["residual_by_band"])]
    sp = out.get("stage_positions")
    if sp:
        lines += ["", "## Every stage position (each with its own nominal calibration)", "",
                  "| position | SRD [mm] | adequate | named |", "| --- | --- | --- | --- |"]
        lines += [f"| {r['position'] + 1} | {r['srd_reported_m'] * 1e3:.3f} | {r['adequate']} | "
                  + (", ".join(f"{f['term']} {f['magnitude']:.3g} {f['unit']}" for f in r["findings"]) or "-") + " |"
                  for r in sp["positions"]]
        lines += [f"- position {r['position'] + 1} not judged: {r['why']}" for r in sp["not_judged"]]
        lines += [f"- trend of {t['term']} with SRD: {t.get('slope_per_m_srd', float('nan')):.4g} {t['unit']}/m "
                  f"({t.get('slope_significance_sigma', float('nan')):.1f} sigma) over {t['n_positions']} positions"
                  for t in sp["trends"]]
        from ct_calib_nodes.core.ct_discrepancy import campaign_sentence  # noqa: PLC0415

        camp = sp["campaign"]
        lines += ["", "Campaign-long (the focal spot of every position's calibration against time):"
                  + campaign_sentence(camp)]
        if camp.get("performed"):
            lines += [f"- detection limit of {k}: " + (f"{v['limit']:.3g} {v['unit']}" if v.get("limit") else "none")
                      + f"; reveal by: {v['reveal_by']}" for k, v in camp["detection_limits"].items()]
    lines += ["", "## Detection limits of this recording (90 % power)", "", "| term | smallest detectable | reveal by |",
              "| --- | --- | --- |"]
    for k, v in out["detection_limits"].items():
        lim = f"{v['limit']:.3g} {v['unit']}" if v.get("limit") is not None else f"not visible: {v['cannot_see']}"
        lines.append(f"| {k} | {lim} | {v['reveal_by']} |")
    lines += ["", "## Plots", ""] + [f"![{p}]({p})" for p in plots]
    (tmp / "report.md").write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    from ct_calib_nodes.core import ct_discrepancy  # noqa: PLC0415
    from ct_calib_nodes.io.atomic import staged_outputs  # noqa: PLC0415
    from ct_calib_nodes.io.results import write_json_atomic  # noqa: PLC0415
    from ct_calib_nodes.offline import cli_recording_files, solve_recording  # noqa: PLC0415

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("recording", help=".mcap file or rosbag2 directory")
    ap.add_argument("--instrument", help="ct_instrument.yaml")
    ap.add_argument("--reference-object", help="reference_object.yaml")
    ap.add_argument("--out", help="output directory (default <recording>_discrepancy)")
    ap.add_argument("--max-terms", type=int, default=4, help="most catalogue terms added")
    ap.add_argument("--no-plots", action="store_true")
    ap.add_argument("--image-pairs", type=int, default=4,
                    help="consecutive-projection pairs rendered for the image-level checks (0 = off)")
    ap.add_argument("--workers", type=int, default=None,
                    help="detection worker processes (default: the cores available, at most 8)")
    args = ap.parse_args(argv)
    got = cli_recording_files("ct_discrepancy", args)
    if got is None:
        return 2
    rec, f = got
    inst_path, how_i, ref_path, how_r = f.instrument_path, f.instrument_how, f.reference_path, f.reference_how
    instrument, ref, thermal_note = f.instrument, f.ref, f.thermal_note
    say = lambda m: print(f"[discrepancy] {m}", flush=True)  # noqa: E731
    say(f"instrument file {inst_path} ({how_i}); reference object {ref_path} ({how_r}); {thermal_note}")
    t0 = time.perf_counter()
    from ct_calib_nodes.offline import default_workers  # noqa: PLC0415

    workers = default_workers() if args.workers is None else max(1, args.workers)
    replay_cpu = {}
    res = solve_recording(rec, instrument, ref, progress=say, workers=workers, timing=replay_cpu)
    for p in res.problems[:20]:
        say(f"problem: {p}")
    if res.static is None or not np.all(np.isfinite(res.static.x)) or not res.acc.positions:
        say("no static calibration from this recording: nothing written")
        return 1
    t1 = time.perf_counter()
    say(f"nominal calibration: {res.static.outcome} ({t1 - t0:.1f} s); running the engine")
    obs = res.acc.positions[0].observations()
    out = ct_discrepancy.run(obs, res.static, instrument.detector, progress=say, max_terms=args.max_terms)
    t2 = time.perf_counter()
    try:
        out["image_level"] = image_level(rec, res, instrument, ref, args.image_pairs, say)
    except Exception as exc:  # noqa: BLE001 - the feature-level verdict stands; say why the images were not judged
        out["image_level"] = {"performed": False, "why": f"image-level check failed: {exc}"}
    out["verdict"] += image_sentence(out["image_level"])
    t3 = time.perf_counter()
    if len(res.acc.positions) > 1:          # the stage-position axis: the engine at every position, the campaign
        every = [(p.srd_reported_m, p.observations()) for p in res.acc.positions]
        sp = ct_discrepancy.run_positions(every, ref.centres_of_m, instrument.detector, instrument.sdd_reported_m,
                                          max_terms=args.max_terms, progress=say, given={0: (res.static, out)})
        out["stage_positions"] = sp
        bad = [r for r in sp["positions"] if not r["adequate"] and r["position"] > 0]
        n_more = sum(r["position"] > 0 for r in sp["positions"])
        out["verdict"] += (f" Further stage positions: {len(bad)} of {n_more} judged inadequate"
                           + (" (" + "; ".join(f"position {r['position'] + 1}: "
                                                + (", ".join(f['term'] for f in r['findings']) or "unexplained structure")
                                                for r in bad) + ")" if bad else "") + ".")
        out["verdict"] += ct_discrepancy.campaign_sentence(sp["campaign"])
    t3b = time.perf_counter()
    out["recording"] = str(rec)
    out["nominal_outcome"] = res.static.outcome
    out["problems"] = res.problems
    out["timing_s"] = {"replay_and_calibration": t1 - t0, "engine": t2 - t1, "image_level": t3 - t2,
                       "stage_positions": t3b - t3,
                       "replay_cpu_s": replay_cpu, "workers": workers}
    out_dir = pathlib.Path(args.out) if args.out else rec.parent / f"{rec.stem}_discrepancy"
    with staged_outputs(out_dir) as tmp:
        plots = [] if args.no_plots else _plots(out, tmp, instrument.detector)
        arrays = out.pop("_arrays")
        write_json_atomic(tmp / "discrepancy.json", out)
        out["_arrays"] = arrays
        write_report(out, tmp, plots, rec)
    say(out["verdict"])
    say(f"written: {out_dir / 'discrepancy.json'}, {out_dir / 'report.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
