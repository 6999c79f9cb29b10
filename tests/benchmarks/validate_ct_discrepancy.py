"""Validation of the CT discrepancy engine on rendered recordings with concealed physics (issue 11).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python tests/benchmarks/validate_ct_discrepancy.py [--seeds 3] [--clean 50]
        [--effects focal_spot_drift,detector_bow,...] [--scale 1.0] [--views 72] [--acquisition reveal]

For every effect in tests/ct_discrepancy/campaign.py (magnitudes as quoted there: focal spot drifting 30 um,
detector bowed 0.5 px at the corner, ...) and seed: a random instrument and renderer physics, 72 rendered
projections through detection + identity + static solve, then ct_discrepancy.run, told nothing. Reported per
effect: detection rate, top-1 naming rate (and how often the true term was named only as degenerate with the
top one), estimated / true magnitude, held-out residual before / after against the noise floor, and the
largest bias of an instrument parameter (z_R .. eta) in its standard deviations before and after the refit.
Clean controls give the false-alarm rate. ``--acquisition reveal`` runs everything on the acquisition that
separates the degenerate groups (campaign.ACQUISITIONS: magnification 4.4-5.8, the object raised 20 mm off the
principal ray, two turns). Progress goes to stderr; the last line of stdout is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "ct_discrepancy"))

import numpy as np  # noqa: E402

from campaign import ACQUISITIONS, DETECTORS, EFFECTS, analyse_campaign, analyse_truth_campaign  # noqa: E402

INSTR = slice(0, 7)


def one(seed, effect, scale, views, mode, det=None, image_effect=None, image_pairs=0, acquisition="standard"):
    if mode == "rendered":
        out, truth = analyse_campaign(seed, effect, scale, n_views=views, det=det, image_effect=image_effect,
                                      image_pairs=image_pairs, acquisition=acquisition)
        st = out["_static"]
    else:
        out, truth, st = analyse_truth_campaign(seed, effect, scale, n_views=views, acquisition=acquisition)
        out["_timing"] = {"render_detect_s": 0.0, "static_s": 0.0, "engine_s": 0.0}
    w = truth["w"]
    xb, sb = np.asarray(out["calibration_before"]["x"]), np.asarray(out["calibration_before"]["std"])
    xa = np.asarray(out["calibration_after"]["x"])
    sa = out["calibration_after"]["std"]
    zb = (xb - w)[INSTR] / sb[INSTR]
    za = None if sa is None else (xa - w)[INSTR] / np.asarray(sa)[INSTR]
    f = out["findings"]
    named = [x["term"] for x in f]
    top = f[0] if f else None
    rec = {"seed": seed, "effect": effect, "physics": dict(truth["physics"]), "scale": scale, "outcome": st.outcome, "adequate": out["adequate"],
           "named": named, "top": None if top is None else top["term"],
           "top_degenerate": [] if top is None else top["degenerate_with"],
           "true_magnitude": truth["magnitude"], "est_magnitude": None,
           "held_out_before": out["fit_before"]["held_out_rms"], "held_out_after": out["fit_after"]["held_out_rms"],
           "floor_u": out["noise_floor"]["independent_sd"]["u"], "floor_v": out["noise_floor"]["independent_sd"]["v"],
           "rms_before": out["fit_before"]["rms"], "rms_after": out["fit_after"]["rms"],
           "max_abs_z_before": float(np.max(np.abs(zb))), "param_max_z_before": int(np.argmax(np.abs(zb))),
           "max_abs_z_after": None if za is None else float(np.max(np.abs(za))),
           "unexplained": [u["axis"] for u in out["unexplained"]], "timing": out["_timing"],
           "limit_true_term": None if truth["term"] is None else out["detection_limits"][truth["term"]].get("limit"),
           "verdict": out["verdict"],
           "wrong_name": any(x["term"] != truth["term"] and truth["term"] not in x["degenerate_with"] for x in f[:1])
           or (truth["term"] is not None and any(x["term"] != truth["term"] and truth["term"] not in x["degenerate_with"]
                                                 and x["term"] not in (f[0]["degenerate_with"] if f else [])
                                                 for x in f) and truth["term"] not in named)}
    img = out.get("image_level")
    if img and img.get("performed"):
        rec["image"] = {"named": [x["term"] for x in img["findings"]], "excluded": img["excluded_shadows"],
                        "n_shadows": img["n_shadows"], "blur_px": img["blur_sigma_px"],
                        "terms": {k: {a: t.get(a) for a in ("value", "u", "significance_sigma", "limit")}
                                  for k, t in img["terms"].items()}}
    for x in f:
        if x["term"] == truth["term"]:
            rec["est_magnitude"] = x["magnitude"]
            rec["est_magnitude_u"] = x["magnitude_u"]
    return rec


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--clean", type=int, default=50)
    ap.add_argument("--effects", default=",".join(EFFECTS))
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--views", type=int, default=72, help="projections per turn")
    ap.add_argument("--acquisition", choices=tuple(ACQUISITIONS), default="standard",
                    help="standard: magnification 2.3-3.5, object on the principal ray, one turn; reveal: "
                         "magnification 4.4-5.8, object raised 20 mm, two turns (separates the degenerate groups); "
                         "magnified, raised, two_turns: each part of reveal alone")
    ap.add_argument("--records", help="write every campaign's record to this JSONL file")
    ap.add_argument("--mode", choices=("rendered", "truth"), default="rendered",
                    help="rendered: images through detection (slow); truth: the renderer's exact centres + noise")
    ap.add_argument("--clean-detectors", default="1024",
                    help="rendered clean controls cycle over these detector formats (same 0.41 m field): "
                         "comma-separated from 1024,768,512 (renderer settings varied; 512 renders 4x faster)")
    ap.add_argument("--clean-only", action="store_true", help="only the clean controls")
    ap.add_argument("--clean-start", type=int, default=0, help="first clean seed offset (split a campaign)")
    ap.add_argument("--seed-start", type=int, default=0, help="first effect seed offset (effect seeds 1000 + offset ..)")
    ap.add_argument("--image-pairs", type=int, default=0,
                    help="rendered mode: also run the image-level checks on this many projection pairs")
    ap.add_argument("--image-effects", default="",
                    help="rendered mode: campaigns with hidden image-level physics, name:amplitude,... from "
                         "detector_lag, scatter_glare, source_output_drift (e.g. detector_lag:0.003)")
    args = ap.parse_args()
    dets = {d.cols: d for d in DETECTORS}
    clean_dets = [dets[int(c)] for c in args.clean_detectors.split(",") if c]
    effects = [] if args.clean_only else [e for e in args.effects.split(",") if e]
    t0 = time.perf_counter()
    recs = []
    sink = open(args.records, "a") if args.records else None
    jobs = [] if args.clean_only else [(1000 + s, e) for e in effects
                                       for s in range(args.seed_start, args.seed_start + args.seeds)]
    jobs += [(5000 + s, "clean") for s in range(args.clean_start, args.clean_start + args.clean)]
    img_eff = [(e.split(":")[0], float(e.split(":")[1])) for e in args.image_effects.split(",") if e]
    jobs += [(7000 + s, f"image:{n}:{a}") for n, a in img_eff for s in range(args.seeds)]
    for i, (seed, eff) in enumerate(jobs):
        if args.mode == "truth":
            import time as _t  # noqa: PLC0415
            t_a = _t.perf_counter()
        det = clean_dets[(seed - 5000) % len(clean_dets)] if eff == "clean" else None
        if eff.startswith("image:"):
            _, name, amp = eff.split(":")
            r = one(seed, "clean", 1.0, args.views, args.mode, clean_dets[seed % len(clean_dets)],
                    image_effect=(name, float(amp)), image_pairs=max(args.image_pairs, 1), acquisition=args.acquisition)
            r["effect"] = eff
        else:
            r = one(seed, eff, args.scale if eff != "clean" else 1.0, args.views, args.mode, det,
                    image_pairs=args.image_pairs, acquisition=args.acquisition)
        if args.mode == "truth":
            r["timing"]["engine_s"] = _t.perf_counter() - t_a
        recs.append(r)
        if sink:
            sink.write(json.dumps(r) + "\n")
            sink.flush()
        print(f"[{i + 1}/{len(jobs)}] {eff} seed {seed}: top {r['top']} named {r['named']} mag {r['est_magnitude']} "
              f"(true {r['true_magnitude']:.3g}) held-out {r['held_out_before']:.4f}->{r['held_out_after']:.4f} "
              f"|z| {r['max_abs_z_before']:.1f}->{r['max_abs_z_after']} {r['timing']}", file=sys.stderr, flush=True)
    table = {}
    for e in effects:
        rs = [r for r in recs if r["effect"] == e]
        ratio = [r["est_magnitude"] / r["true_magnitude"] for r in rs if r["est_magnitude"] is not None]
        table[e] = {
            "n": len(rs), "detected": float(np.mean([not r["adequate"] for r in rs])),
            "top1": float(np.mean([r["top"] == e for r in rs])),
            "named_any_or_degenerate": float(np.mean([e in r["named"] or e in r["top_degenerate"] for r in rs])),
            "magnitude_ratio_median": float(np.median(ratio)) if ratio else None,
            "magnitude_within_15pct": float(np.mean([abs(x - 1) < 0.15 for x in ratio])) if ratio else None,
            "magnitude_z_rms": float(np.sqrt(np.mean([((r["est_magnitude"] - r["true_magnitude"]) / r["est_magnitude_u"]) ** 2
                                                      for r in rs if r["est_magnitude"] is not None]))) if ratio else None,
            "magnitude_ratio_range": [float(np.min(ratio)), float(np.max(ratio))] if ratio else None,
            "held_out_before_px": float(np.median([r["held_out_before"] for r in rs])),
            "held_out_after_px": float(np.median([r["held_out_after"] for r in rs])),
            "floor_px": float(np.median([np.hypot(r["floor_u"], r["floor_v"]) / np.sqrt(2) for r in rs])),
            "max_abs_z_before_median": float(np.median([r["max_abs_z_before"] for r in rs])),
            "max_abs_z_after_median": float(np.median([r["max_abs_z_after"] for r in rs
                                                       if r["max_abs_z_after"] is not None]))
            if any(r["max_abs_z_after"] is not None for r in rs) else None,
            "true_magnitude": rs[0]["true_magnitude"] if rs else None,
            "wrong_name_rate": float(np.mean([r["wrong_name"] for r in rs])),
            "limit_above_true_when_missed": float(np.mean([(r["limit_true_term"] or np.inf) > r["true_magnitude"]
                                                           for r in rs if r["adequate"]])) if any(r["adequate"] for r in rs) else None,
            "top_or_degenerate": float(np.mean([r["top"] == e or e in r["top_degenerate"] for r in rs])),
        }
    clean = [r for r in recs if r["effect"] == "clean"]
    image_table = {}
    for e in sorted({r["effect"] for r in recs if "image" in r}):
        rs = [r for r in recs if r["effect"] == e and "image" in r]
        name = e.split(":")[1] if e.startswith("image:") else None
        true = float(e.split(":")[2]) * 100 if name else None
        image_table[e] = {
            "n": len(rs), "tube_n": sum(bool(r["physics"].get("tube")) for r in rs),
            "any_image_finding": float(np.mean([bool(r["image"]["named"]) for r in rs])),
            "any_image_finding_no_tube": float(np.mean([bool(r["image"]["named"]) for r in rs if not r["physics"].get("tube")]))
            if any(not r["physics"].get("tube") for r in rs) else None,
            "true_named": None if name is None else float(np.mean([name in r["image"]["named"] for r in rs])),
            "true_percent": true,
            "estimates_percent": None if name is None else [r["image"]["terms"][name]["value"] for r in rs],
            "u_percent": None if name is None else [r["image"]["terms"][name]["u"] for r in rs],
            "feature_level_adequate": float(np.mean([r["adequate"] for r in rs])),
            "named_terms": sorted({t for r in rs for t in r["image"]["named"]})}
    summary = {"benchmark": "validate_ct_discrepancy", "mode": args.mode, "acquisition": args.acquisition,
               "views_per_turn": args.views, "scale": args.scale, "effects": table,
               "image_level": image_table,
               "clean_by_detector": {str(d): {"n": sum(r["physics"].get("detector_px") == d for r in clean),
                                              "false_alarms": sum((not r["adequate"]) and r["physics"].get("detector_px") == d
                                                                  for r in clean)} for d in (512, 768, 1024)},
               "clean_by_tube": {str(t): {"n": sum(bool(r["physics"].get("tube")) == t for r in clean),
                                          "false_alarms": sum((not r["adequate"]) and bool(r["physics"].get("tube")) == t
                                                              for r in clean)} for t in (False, True)},
               "clean_n": len(clean), "false_alarm_rate": float(np.mean([not r["adequate"] for r in clean])) if clean else None,
               "clean_false_names": sorted({t for r in clean for t in r["named"]}),
               "engine_s_median": float(np.median([r["timing"]["engine_s"] for r in recs])),
               "render_detect_s_median": float(np.median([r["timing"]["render_detect_s"] for r in recs])),
               "wall_s": time.perf_counter() - t0}
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
