"""Per-frame detection on the kept ct_indep recordings, scored against truth (truth used only to score).

python study.py --seeds 7241 7245 ... [--variant NAME] [--out FILE] [--patches]
Prints per seed: visible, found, missed by reason, false; lists refused visible spheres with detail.
Writes a JSON of per-shadow errors (z per axis) for accepted shadows, keyed by (seed, view, sphere)."""
import argparse, json, os, pathlib, sys, time
FRAMES = os.environ.get("BGS_FRAMES", "/tmp/bgs/frames")
import numpy as np
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
import ct_indep_gen as gen
from ct_calib_nodes.core.detect import detect_spheres, DetectionSettings, shadow_diameter_range_px
from ct_calib_nodes.io.ct_files import load_instrument, load_reference_object

ap = argparse.ArgumentParser()
ap.add_argument("--seeds", nargs="+", type=int)
ap.add_argument("--root", default="/tmp/ct512b")
ap.add_argument("--set", nargs="*", default=[], help="DetectionSettings overrides k=v")
ap.add_argument("--out", default=None)
ap.add_argument("--patches", action="store_true")
ap.add_argument("--quiet", action="store_true")
a = ap.parse_args()
kw = {}
for s in a.set:
    k, v = s.split("=")
    kw[k] = None if v == "None" else (v == "True" if v in ("True", "False") else float(v))
st = DetectionSettings(**kw)

def _wrap(x):
    return (np.asarray(x) + np.pi) % (2 * np.pi) - np.pi

rows_out = []
tot = {"visible": 0, "found": 0, "false": 0, "missed": {}, "cpu": 0.0, "frames": 0}
for seed in a.seeds:
    root = pathlib.Path(a.root)
    if not (root / "truth" / f"{seed}.json").exists():
        root = pathlib.Path("/tmp/ct-trackcov-camp")
    rec = root / "recordings" / f"scan_{seed}"
    truth = json.loads((root / "truth" / f"{seed}.json").read_text())
    inst = load_instrument(rec / "ct_instrument.yaml")
    ref = load_reference_object(rec / "reference_object.yaml")
    fr = np.load(f"{FRAMES}/{seed}.npz")
    w_true = np.array(truth["w"])
    ginst = gen.instrument_from(w_true, truth)
    alphas = np.array([v["alpha"] for v in truth["views"]])
    flat = inst.flat_field()
    vis_s = found_s = false_s = 0
    miss_s = {}
    for i in range(len(fr["alpha"])):
        img = fr["images"][i]
        srd = float(fr["srd"][i])
        drange = shadow_diameter_range_px(ref.diameters_m, ref.centres_of_m, inst.sdd_reported_m, srd,
                                          inst.detector.pixel_pitch_m)
        c0 = time.process_time()
        det = detect_spheres(img, encoding=str(fr["encoding"]), flat_field_counts=flat, dark=inst.dark,
                             expected_shape=(inst.detector.rows, inst.detector.cols), diameter_px_range=drange,
                             settings=st)
        tot["cpu"] += time.process_time() - c0
        tot["frames"] += 1
        j = int(np.argmin(np.abs(_wrap(alphas - fr["alpha"][i]))))
        v = truth["views"][j]
        cr, rad, gap = np.array(v["centre_px"]), np.array(v["shadow_radius_px"]), np.array(v["gap_px"])
        vis = gap >= 6.0
        found = np.zeros(len(cr), bool)
        std = det.centre_std_px
        corner = det.on_corner if det.on_corner is not None else np.zeros(len(det.centre_px), bool)
        for m, (col, row) in enumerate(det.centre_px):
            dist = np.linalg.norm(cr - [col, row], axis=1)
            k = int(np.argmin(dist))
            if dist[k] > 0.5 * rad[k]:
                false_s += 1
                print(f"  FALSE seed {seed} view {j} at {col:.1f},{row:.1f}")
                continue
            found[k] = True
            b = det.semi_axes_px[m, 1]
            e_true = ginst.ellipse_centre_px(cr[k], b)
            e = np.array([col, row]) - e_true
            rows_out.append({"seed": seed, "view": j, "sphere": k, "vis": bool(vis[k]), "err": e.tolist(),
                             "std": std[m].tolist(), "corner": bool(corner[m]),
                             "edge": bool(det.on_background_edge[m]) if det.on_background_edge is not None else None,
                             "centre": [float(col), float(row)]})
        rj = det.rejected
        for k in np.flatnonzero(vis & ~found):
            near = [(r_, d_) for (x_, y_), r_, d_ in zip(rj.centre_px, rj.reason, rj.detail)
                    if np.hypot(x_ - cr[k, 0], y_ - cr[k, 1]) < 0.5 * rad[k]]
            reason = near[0][0] if near else "no detection"
            miss_s[reason] = miss_s.get(reason, 0) + 1
            if not a.quiet:
                print(f"  MISS seed {seed} view {j} sph {k} at {cr[k,0]:.1f},{cr[k,1]:.1f} r {rad[k]:.2f}: "
                      f"{near[0][0] + ': ' + near[0][1] if near else 'no detection'}")
            if a.patches:
                import cv2
                x, y = int(round(cr[k, 0])), int(round(cr[k, 1]))
                h = 20
                p = img[max(y - h, 0):y + h + 1, max(x - h, 0):x + h + 1].astype(np.float64)
                p = (255 * (p - p.min()) / max(np.ptp(p), 1e-9)).astype(np.uint8)
                p = cv2.resize(p, None, fx=8, fy=8, interpolation=cv2.INTER_NEAREST)
                cv2.imwrite(f"{FRAMES}/../patch_{seed}_{j:02d}_{k:02d}.png", p)
        vis_s += int(vis.sum())
        found_s += int((found & vis).sum())
    print(f"seed {seed}: visible {vis_s} found {found_s} missed {miss_s} false {false_s}", flush=True)
    tot["visible"] += vis_s
    tot["found"] += found_s
    tot["false"] += false_s
    for k_, v_ in miss_s.items():
        tot["missed"][k_] = tot["missed"].get(k_, 0) + v_
tot["cpu_ms_per_frame"] = 1e3 * tot["cpu"] / max(tot["frames"], 1)
print(json.dumps(tot))
if a.out:
    pathlib.Path(a.out).write_text(json.dumps({"settings": kw, "total": tot, "shadows": rows_out}))
