"""Markdown + PNG report of a measurement.json (the paper's formats, Gordon and Borenstein
2019, section 4: Figs 13-16, Table 1).

`truth` (optional, demo and validation only) maps feature id -> {"size": float | [sx, sy],
"center_part": [x, y]} and "dots" -> {grid id: {"pitch": p}}; the measuring code never sees it.
"""
from __future__ import annotations

import itertools
import math
import pathlib

import numpy as np


def _um(x):
    return f"{x * 1e6:.2f}"


def _mm(x, nd=5):
    return f"{x * 1e3:.{nd}f}"


def _u_distance(a: dict, b: dict):
    """u of the distance of two fitted centres, from the fits' centre u (cx, cy in the plane).

    The fits use disjoint points, so the two centres are taken as independent; the covariance
    of cx, cy is not kept, so each centre's u along the (unknown in-plane) direction is taken
    as the rms of u_cx, u_cy (exact for a circle's isotropic centre). None when a member has no
    centre u (a dot grid's mean centre). Does not include errors shared by both centres (stage
    scale and error motions, calibrated squareness, camera poses)."""
    ua, ub = a.get("u_center"), b.get("u_center")
    if not ua or not ub or any(v is None or not np.isfinite(v) for v in list(ua) + list(ub)):
        return None
    return float(math.sqrt((ua[0] ** 2 + ua[1] ** 2 + ub[0] ** 2 + ub[1] ** 2) / 2))


def dimension_table(doc: dict) -> list[dict]:
    """Dimensions (Table 1 style): every feature's size(s), the centre distance of every pair of
    features (a dot grid's centre: the mean of its dots), and the circle through >= 3 same-size
    circle centres (bolt circle). Each row: name, value (m), u (m) when known, kind, members."""
    rows = []
    feats = [f for f in doc["features"] if "error" not in f]
    for f in feats:
        if f["type"] == "rectangle":
            for k, ax in enumerate("xy"):
                rows.append({"name": f"{f['id']} s{ax}", "value": f["size"][k], "u": f["u_size"][k], "kind": "size",
                             "members": [f["id"]], "axis": k})
        elif f["type"] == "square":
            rows.append({"name": f"{f['id']} side (mean)", "value": f["size"], "u": f["u_size"], "kind": "size",
                         "members": [f["id"]]})
        else:
            rows.append({"name": f"{f['id']} diameter", "value": f["size"], "u": f["u_size"], "kind": "size",
                         "members": [f["id"]]})
    for a, b in itertools.combinations(feats + [dict(g, type="dot_grid", center_part=np.mean(g["centres_part"], 0))
                                                for g in doc.get("dot_grids", [])], 2):
        d = float(np.hypot(*(np.asarray(a["center_part"]) - np.asarray(b["center_part"]))))
        rows.append({"name": f"{a['id']}-{b['id']} centre distance", "value": d, "u": _u_distance(a, b),
                     "kind": "distance",
                     "members": [a["id"], b["id"]]})
    groups = {}
    for f in feats:
        key = (f["type"], json_key(f.get("nominal")))
        groups.setdefault(key, []).append(f)
    for (typ, _), fs in groups.items():
        if len(fs) < 2:
            continue
        if typ == "circle" and len(fs) >= 3:
            c = np.array([f["center_part"] for f in fs])
            A = np.column_stack([2 * c, np.ones(len(c))])
            s, *_ = np.linalg.lstsq(A, (c ** 2).sum(1), rcond=None)
            r = math.sqrt(s[2] + s[0] ** 2 + s[1] ** 2)
            rows.append({"name": f"circle through {', '.join(f['id'] for f in fs)} (diameter)", "value": 2 * r,
                         "u": None, "kind": "bolt_circle", "members": [f["id"] for f in fs]})
    return rows


def json_key(v):
    return tuple(np.round(np.atleast_1d(np.asarray(v, float)) * 1e7).astype(int).tolist()) if v is not None else None


def truth_value(row, truth):
    if truth is None:
        return None
    m = row["members"]
    try:
        if row["kind"] == "size":
            v = truth[m[0]]["size"]
            return float(v[row["axis"]]) if "axis" in row else float(np.mean(v))
        if row["kind"] == "distance":
            return float(np.hypot(*(np.asarray(truth[m[0]]["center_part"]) - np.asarray(truth[m[1]]["center_part"]))))
        if row["kind"] == "bolt_circle":
            c = np.array([truth[i]["center_part"] for i in m])
            A = np.column_stack([2 * c, np.ones(len(c))])
            s, *_ = np.linalg.lstsq(A, (c ** 2).sum(1), rcond=None)
            return 2 * math.sqrt(s[2] + s[0] ** 2 + s[1] ** 2)
    except KeyError:
        return None
    return None


def write_report(doc: dict, out_dir, *, truth=None, title=None, extra_md: str = "") -> pathlib.Path:
    """report.md and PNG plots in out_dir; returns the report path."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    L = [f"# {title or 'PiCMS measurement: ' + doc['part']}", ""]
    L.append(f"Mode **{doc['mode']}** (frame `{doc['frame']}`); {doc.get('summary', {}).get('n_ok', '?')} of "
             f"{doc.get('summary', {}).get('n_points', '?')} points measured. Plane normal "
             f"{np.round(doc['plane']['normal'], 6).tolist()}, fixed angles [tx, ty, tz] = "
             f"{np.round(np.degrees(doc['plane']['fixed_angles_rad']), 4).tolist()} deg, flatness "
             f"{_um(doc['plane']['flatness'])} um over {doc['plane'].get('n_points', '?')} points.")
    if doc.get("u_scope"):
        L += ["", f"Uncertainties (u, k = 1): {doc['u_scope']}."]
    sm = doc.get("summary") or {}
    if sm:
        L.append(f"Targeting: {sm.get('iterations_mean', 0):.2f} triangulations and {sm.get('moves_mean', 0):.2f} "
                 f"moves per point on average; {sm.get('time_per_point_s', 0):.2f} s per point "
                 f"(wall, simulated cell incl. rendering); {sm.get('elapsed_s', 0):.0f} s in all.")
    L.append("")
    # shapes (Figs 13-14 text)
    L += ["## Shapes (the paper's section 4: size, mean fit deviation, RMS, pose)", "",
          "| feature | type | n | size (mm) | u (um) | " + ("error vs truth (um) | " if truth else "") +
          "mean dev. from ideal (um) | RMS fit (um) | max (um) | chi2/dof | pose [tx, ty, tz] (deg) |",
          "|---|---|---|---|---|" + ("---|" if truth else "") + "---|---|---|---|---|"]
    for f in doc["features"]:
        if "error" in f:
            L.append(f"| {f['id']} | {f['type']} | {f['n_points']} | fit failed: {f['error']} |")
            continue
        if f["type"] == "square":
            sz = f"{_mm(f['sides'][0])} x {_mm(f['sides'][1])}"
            u = f"{_um(f['u_size'])}"
        elif f["type"] == "rectangle":
            sz = f"{_mm(f['size'][0])} x {_mm(f['size'][1])}"
            u = f"{_um(f['u_size'][0])}, {_um(f['u_size'][1])}"
        else:
            sz, u = _mm(f["size"]), _um(f["u_size"])
        err = ""
        if truth and f["id"] in truth:
            tv = np.atleast_1d(truth[f["id"]]["size"])
            mv = np.atleast_1d(f["sides"] if f["type"] == "square" else f["size"])
            err = ", ".join(_um(a - b) for a, b in zip(mv, np.broadcast_to(tv, mv.shape))) + " | "
        elif truth:
            err = " | "
        ang = np.round(np.degrees(f.get("fixed_angles_rad", [np.nan] * 3)), 3).tolist()
        L.append(f"| {f['id']} | {f['type']} | {f['n_points']} | {sz} | {u} | {err}{_um(f['mean_dev_ideal'])} | "
                 f"{_um(f['form_rms'])} | {_um(f['form_max'])} | {f['chi2_dof']:.2f} | {ang} |")
    L += ["", "Mean deviation from ideal: mean signed distance of the points to the NOMINAL shape placed at the "
          "fitted centre and angle (the paper's mu); RMS fit: residuals of the free fit (size fitted).", ""]
    # dot grids (Fig 16)
    for g in doc.get("dot_grids", []):
        L += [f"## Dot grid {g['id']} ({g['n_dots']} of {g['n_planned']} dots): spacings along the grid directions "
              "(the paper's Fig. 16)", "",
              "| nominal (mm) | n | mean (mm) | mean - nominal (um) | sd (um) |", "|---|---|---|---|---|"]
        for sp in g["spacings"]:
            L.append(f"| {_mm(sp['nominal'], 1)} | {sp['n']} | {_mm(sp['mean'])} | {_um(sp['mean'] - sp['nominal'])} | "
                     f"{_um(sp['sd'])} |")
        L.append("")
    # dimension table (Table 1)
    rows = dimension_table(doc)
    if rows:
        L += ["## Dimensions (the paper's Table 1 format)", "",
              "| dimension | PiCMS (mm) | " + ("true (mm) | diff (um) | " if truth else "") + "u (um) |",
              "|---|---|" + ("---|---|" if truth else "") + "---|"]
        for r in rows:
            tv = truth_value(r, truth)
            tcols = ""
            if truth:
                tcols = (f"{_mm(tv)} | {_um(r['value'] - tv)} | " if tv is not None else "- | - | ")
            L.append(f"| {r['name']} | {_mm(r['value'])} | {tcols}{_um(r['u']) if r['u'] is not None else '-'} |")
        L.append("")
    # plots
    pngs = []
    shapes = [f for f in doc["features"] if "error" not in f]
    if shapes:
        fig, axs = plt.subplots(1, 2, figsize=(12, 5))
        for f in shapes:
            P = np.asarray(f["points_part"])
            axs[0].plot(P[:, 0] * 1e3, P[:, 1] * 1e3, ".", label=f["id"])
        for g in doc.get("dot_grids", []):
            C = np.asarray(g["centres_part"])
            axs[0].plot(C[:, 0] * 1e3, C[:, 1] * 1e3, "k+", ms=4, label=g["id"])
        axs[0].set_aspect("equal")
        axs[0].set_xlabel("part x (mm)")
        axs[0].set_ylabel("part y (mm)")
        axs[0].set_title("measured points (cf. Fig. 13)")
        axs[0].legend(fontsize=7)
        for k, f in enumerate(shapes):
            d = np.asarray(f["deviations_ideal"]) * 1e6
            x = np.arange(len(d))
            axs[1].plot(x, d, "o-", ms=3, label=f"{f['id']} (mu {np.mean(d):.2f} um)")
            axs[1].axhline(np.mean(d), color=axs[1].lines[-1].get_color(), lw=0.8)
        axs[1].set_xlabel("point")
        axs[1].set_ylabel("deviation from ideal shape (um)")
        axs[1].set_title("fit deviations (cf. Fig. 14)")
        axs[1].legend(fontsize=7)
        fig.tight_layout()
        p = out / "fit_deviations.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        pngs.append(p.name)
    for g in doc.get("dot_grids", []):
        fig, ax = plt.subplots(figsize=(8, 4))
        for sp in g["spacings"]:
            v = np.asarray(sp["values"]) * 1e3
            ax.hist(v, bins=12, alpha=0.7, label=f"{sp['nominal'] * 1e3:.1f} mm: mu {sp['mean'] * 1e3:.4f}, "
                    f"sd {sp['sd'] * 1e6:.2f} um (n {sp['n']})")
        ax.set_xlabel("dot spacing (mm)")
        ax.set_ylabel("count")
        ax.set_title(f"{g['id']}: spacings per category (cf. Fig. 16)")
        ax.legend(fontsize=7)
        fig.tight_layout()
        p = out / f"grid_{g['id']}_spacings.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        pngs.append(p.name)
    if pngs:
        L += ["## Plots", ""] + [f"![{n}]({n})" for n in pngs] + [""]
    if doc.get("problems"):
        L += ["## Problems", ""] + [f"- {p}" for p in doc["problems"]] + [""]
    if extra_md:
        L += [extra_md, ""]
    path = out / "report.md"
    path.write_text("\n".join(L))
    return path


def truth_for_report(part) -> dict:
    """Truth dict for the report from a simulated part (demo and validation only)."""
    from .core.scenes import part_truth
    t = part_truth(part)
    out = {}
    for f in t["features"]:
        size = f.get("side", f.get("diameter", f.get("size")))
        out[f["id"]] = {"size": np.asarray(size, float).tolist() if np.ndim(size) else float(size),
                        "center_part": np.asarray(f["center_part"], float).tolist()}
    return out
