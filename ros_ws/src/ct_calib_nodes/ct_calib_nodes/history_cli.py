"""ct_history: list, show, compare, export and plot the calibration history (io/history.py).

    ct_history [--db FILE] list [--cell /cell_a] [--kind ct_geometry] [--status success] [--limit 20]
    ct_history [--db FILE] show ID
    ct_history [--db FILE] compare ID_A ID_B [--k 2]
    ct_history [--db FILE] export --format csv|json --out FILE [filters]
    ct_history [--db FILE] trend --cell /cell_a [--k 2] [--plot DIR]

``compare`` and ``trend`` flag a change beyond its uncertainty: |b - a| > k sqrt(u_a^2 + u_b^2)
(k = 2 by default; the two solves taken as independent). ``trend`` looks at the valid (SUCCESS)
solves of one cell in time order: the key geometry parameters (z_R, z_D, x_D, y_D, theta, phi,
eta), every error-map component at every position, and for the other kinds (Pixel Probe
calibrations ``picms_calibration``, ...) every scalar quantity that carries an uncertainty (X* in
the constellation and tracker frames, x_j* per camera, camera centres, squareness); ``--kind``
restricts it to one kind; ``--plot DIR`` writes PNG plots with +-k u bands, one per kind. The database: ``--db``, else ``$METRO_HISTORY_DB``, else
``~/.local/share/metro_cell/history.sqlite``.

Exit status: 0 done (``trend``: also when changes were flagged; they are printed), 2 bad
arguments or no database.
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import json
import math
import pathlib
import re
import sys

from ct_calib_nodes.io.history import History, HistoryError, compare_quantities, default_path, plain

KEY_GEOMETRY = ("z_R", "z_D", "x_D", "y_D", "theta", "phi", "eta")
CT_KINDS = ("ct_geometry", "ct_error_map")
MAP_COMPONENTS = ("positioning_m", "straightness_x_m", "straightness_y_m", "pitch_rad", "yaw_rad", "roll_rad")
DISPLAY = {"m": (1e6, "um"), "rad": (206264.80624709636, "arcsec")}


def _fmt(v, unit):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    scale, u = DISPLAY.get(unit, (1.0, unit))
    if unit == "m" and abs(v) >= 1e-3:
        scale, u = 1e3, "mm"
    return f"{v * scale:.10g} {u}".strip() if u == "mm" else f"{v * scale:.4g} {u}".strip()


def _when(ns):
    return dt.datetime.fromtimestamp(ns / 1e9, dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S")


def cmd_list(h, a):
    recs = h.list(cell=a.cell, kind=a.kind, status=a.status, limit=a.limit, newest_first=True)
    print(f"{'id':>5}  {'time (UTC)':19}  {'cell':10} {'kind':17} {'source':8} {'status':17} {'final':5} campaign")
    for r in recs:
        print(f"{r.id:>5}  {_when(r.created_ns)}  {r.cell:10} {r.kind:17} {r.source:8} {r.status:17} "
              f"{'yes' if r.final else 'no':5} {r.campaign_id or '-'}")
    print(f"{len(recs)} solve(s) in {h.path}")
    return 0


def cmd_show(h, a):
    r = h.get(int(a.id))
    if r is None:
        print(f"ct_history: no solve {a.id}", file=sys.stderr)
        return 2
    print(f"solve {r.id} ({r.uid}) {_when(r.created_ns)} UTC: cell {r.cell}, {r.kind}, {r.source}, "
          f"status {r.status} ({r.status_code}): {r.message}")
    print(f"campaign {r.campaign_id or '-'} final={r.final}; data stamps {r.data_start_ns}..{r.data_end_ns}; "
          f"software {r.software} on {r.host}")
    for i in r.inputs:
        print(f"  input {i.role}: {i.path or ''} {('sha256 ' + i.sha256[:16]) if i.sha256 else ''} "
              f"{('solve ' + i.ref_uid) if i.ref_uid else ''}")
    for q in r.quantities:
        pos = "" if q.position is None else f"[{q.position}]"
        print(f"  {q.name}{pos} = {_fmt(q.value, q.unit)}  u = {_fmt(q.u, q.unit)}")
    return 0


def cmd_compare(h, a):
    ra, rb = h.get(int(a.a)), h.get(int(a.b))
    if ra is None or rb is None:
        print(f"ct_history: no solve {a.a if ra is None else a.b}", file=sys.stderr)
        return 2
    if ra.kind != rb.kind:
        print(f"ct_history: solve {ra.id} is {ra.kind}, {rb.id} is {rb.kind}: not comparable", file=sys.stderr)
        return 2
    rows = compare_quantities(ra, rb, k=a.k)
    n = 0
    print(f"{'quantity':24} {'solve ' + str(ra.id):>14} {'solve ' + str(rb.id):>14} {'change':>14} {'u(change)':>12}")
    for name, pos, unit, va, vb, d, ud, flag in rows:
        n += flag
        label = name + ("" if pos is None else f"[{pos}]")
        print(f"{label:24} {_fmt(va, unit):>14} {_fmt(vb, unit):>14} {_fmt(d, unit):>14} {_fmt(ud, unit):>12}"
              f"{'  CHANGED (> %g u)' % a.k if flag else ''}")
    print(f"{n} of {len(rows)} quantities changed beyond {a.k:g} standard uncertainties")
    return 0


def _export_rows(h, a):
    for r in h.list(cell=a.cell, kind=a.kind, status=a.status, with_details=True):
        yield r


def cmd_export(h, a):
    out = pathlib.Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(out.suffix + ".tmp")
    n = 0
    if a.format == "json":
        recs = []
        for r in _export_rows(h, a):
            d = {k: getattr(r, k) for k in ("id", "uid", "created_utc", "cell", "kind", "source", "campaign_id", "final",
                                            "status", "status_code", "message", "data_start_ns", "data_end_ns",
                                            "software", "host")}
            d["inputs"] = [vars(i) for i in r.inputs]
            d["quantities"] = [vars(q) for q in r.quantities]
            if a.full:
                d["result"] = r.result
            recs.append(d)
        tmp.write_text(json.dumps(plain({"database": h.path, "units": "SI (m, rad)", "solves": recs}), indent=1))
        n = len(recs)
    else:
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["solve_id", "created_utc", "cell", "kind", "source", "campaign_id", "final", "status",
                        "quantity", "position", "unit", "value", "u"])
            for r in _export_rows(h, a):
                n += 1
                for q in r.quantities:
                    w.writerow([r.id, r.created_utc, r.cell, r.kind, r.source, r.campaign_id or "", int(r.final),
                                r.status, q.name, "" if q.position is None else q.position, q.unit,
                                repr(float(q.value)), "" if q.u is None else repr(float(q.u))])
    tmp.replace(out)
    print(f"{n} solve(s) written to {out}")
    return 0


def trend_series(h, cell, k: float = 2.0, kind=None):
    """{(kind, name, position): [(solve id, created_ns, value, u, unit, flagged vs previous)]}"""
    series = {}
    if kind in (None, "ct_geometry"):
        for name in KEY_GEOMETRY:
            series[("ct_geometry", name, None)] = h.trend(name, cell=cell, kind="ct_geometry")
    if kind in (None, "ct_error_map"):
        for rec in h.list(cell=cell, kind="ct_error_map", status="success", limit=1, newest_first=True,
                          with_details=True):
            positions = sorted({q.position for q in rec.quantities if q.position})
            for c in MAP_COMPONENTS:
                for p in positions:
                    series[("ct_error_map", c, p)] = h.trend(c, cell=cell, kind="ct_error_map", position=p)
    kinds = [x for x in h.kinds(cell=cell) if x not in CT_KINDS]
    for other in kinds if kind is None else [kind] if kind not in CT_KINDS else []:
        for rec in h.list(cell=cell, kind=other, status="success", limit=1, newest_first=True, with_details=True):
            for q in rec.quantities:       # the scalar quantities with an uncertainty
                if q.position is None and q.u is not None:
                    series[(other, q.name, None)] = h.trend(q.name, cell=cell, kind=other)
    out = {}
    for key, rows in series.items():
        pts, prev = [], None
        for sid, t, v, u, unit, _camp, _end in rows:
            if v is None:
                continue
            flag = False
            if prev is not None and u is not None and prev[3] is not None:
                ud = math.hypot(u, prev[3])
                flag = ud > 0 and abs(v - prev[2]) > k * ud
            pts.append((sid, t, v, u, unit, flag))
            prev = pts[-1]
        if pts:
            out[key] = pts
    return out


def cmd_trend(h, a):
    series = trend_series(h, a.cell, a.k, a.kind)
    if not series:
        print(f"no valid solves of cell {a.cell} in {h.path}")
        return 0
    n_flag = 0
    for (kind, name, pos), pts in series.items():
        flags = [p for p in pts if p[5]]
        n_flag += len(flags)
        label = name + ("" if pos is None else f"[{pos}]")
        last = pts[-1]
        print(f"{kind:17} {label:24} {len(pts):3} solves, last {_fmt(last[2], last[4])} +- {_fmt(last[3], last[4])}"
              + "".join(f"; CHANGED at solve {p[0]}" for p in flags))
    print(f"{n_flag} change(s) beyond {a.k:g} standard uncertainties between consecutive valid solves")
    if a.plot:
        for f in plot_trends(series, pathlib.Path(a.plot), a.cell, a.k):
            print(f"plot: {f}")
    return 0


def _family(name: str) -> str:
    """x_star_col_camera_1 -> x_star, centre_x_camera_2 -> centre, p_tracker_x -> p_tracker, squareness_xy ->
    squareness: the panel a quantity of a non-CT kind is drawn in."""
    base = re.sub(r"_camera_\d+$", "", name)
    return re.sub(r"_(x|y|z|col|row|xy|xz|yz)$", "", base)


def plot_trends(series, out_dir: pathlib.Path, cell: str, k: float = 2.0):
    import matplotlib  # noqa: PLC0415
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    out_dir.mkdir(parents=True, exist_ok=True)
    files = []
    groups = [("ct_geometry", KEY_GEOMETRY, False), ("ct_error_map", MAP_COMPONENTS, False)]
    for kind in sorted({key[0] for key in series} - set(CT_KINDS)):
        # other kinds: one panel per family of quantities (x_star_col_camera_1, ... -> x_star), each
        # quantity drawn as its change since its first valid solve, so a panel holds several of them
        groups.append((kind, tuple(dict.fromkeys(_family(key[1]) for key in series if key[0] == kind)), True))
    for kind, names, as_change in groups:
        keys = [key for key in series if key[0] == kind]
        if not keys:
            continue
        fig, axes = plt.subplots(len(names), 1, figsize=(8, 2.0 * len(names)), sharex=True, squeeze=False)
        for ax, name in zip(axes[:, 0], names):
            for key in [kk for kk in keys if (_family(kk[1]) if as_change else kk[1]) == name]:
                pts = series[key]
                unit = pts[0][4]
                scale, shown = DISPLAY.get(unit, (1.0, unit))
                t = [dt.datetime.fromtimestamp(p[1] / 1e9, dt.timezone.utc) for p in pts]
                v0 = pts[0][2] * scale if as_change else 0.0
                v = [p[2] * scale - v0 for p in pts]
                u = [(p[3] or 0.0) * scale for p in pts]
                lab = key[1] if as_change else (None if key[2] is None else f"position {key[2]}")
                line, = ax.plot(t, v, "o-", ms=3, label=lab)
                ax.fill_between(t, [a - k * b for a, b in zip(v, u)], [a + k * b for a, b in zip(v, u)],
                                color=line.get_color(), alpha=0.2)
                for p, ti, vi in zip(pts, t, v):
                    if p[5]:
                        ax.plot([ti], [vi], "rx", ms=10, mew=2)
                ax.set_ylabel(f"{name}{' change' if as_change else ''}\n[{shown}]", fontsize=8)
            if as_change or (kind == "ct_error_map" and ax is axes[0, 0]):
                ax.legend(fontsize=6, ncol=3, loc="upper left")
        times = [p[1] for key in keys for p in series[key]]
        if max(times) - min(times) < 60e9:      # one solve (or all within a minute): a readable time axis
            mid = dt.datetime.fromtimestamp(0.5 * (max(times) + min(times)) / 1e9, dt.timezone.utc)
            axes[0, 0].set_xlim(mid - dt.timedelta(hours=1), mid + dt.timedelta(hours=1))
        axes[0, 0].set_title(f"cell {cell}: {kind} over time (bands +-{k:g} u; x = change beyond {k:g} u)")
        fig.autofmt_xdate()
        fig.tight_layout()
        f = out_dir / f"trend_{kind}.png"
        fig.savefig(f, dpi=90)
        plt.close(fig)
        files.append(f)
    return files


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="ct_history", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--db", help=f"history database (default {default_path()})")
    sub = ap.add_subparsers(dest="cmd", required=True)

    def filters(p):
        p.add_argument("--cell", help="cell namespace, e.g. /cell_a ('/' = root)")
        p.add_argument("--kind", help="ct_geometry, ct_error_map, picms_calibration, ...")
        p.add_argument("--status", help="outcome word (success, poor_fit, ...) or SolveStatus code")

    p = sub.add_parser("list", help="list solves, newest first")
    filters(p)
    p.add_argument("--limit", type=int, default=50)
    p = sub.add_parser("show", help="one solve in full")
    p.add_argument("id")
    p = sub.add_parser("compare", help="quantities of two solves, changes beyond k u flagged")
    p.add_argument("a")
    p.add_argument("b")
    p.add_argument("--k", type=float, default=2.0)
    p = sub.add_parser("export", help="export solves as CSV (one row per quantity) or JSON")
    filters(p)
    p.add_argument("--format", choices=("csv", "json"), required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--full", action="store_true", help="JSON: include each solve's full result")
    p = sub.add_parser("trend", help="key quantities of one cell over time, changes flagged, plots")
    p.add_argument("--cell", default="/")
    p.add_argument("--kind", help="one kind only (ct_geometry, ct_error_map, picms_calibration, ...)")
    p.add_argument("--k", type=float, default=2.0)
    p.add_argument("--plot", help="directory for trend PNGs")
    a = ap.parse_args(argv)
    path = a.db or default_path()
    if not pathlib.Path(path).is_file():
        print(f"ct_history: no history database at {path}", file=sys.stderr)
        return 2
    if getattr(a, "status", None) is not None and a.status.isdigit():
        a.status = int(a.status)
    try:
        h = History(path)
    except HistoryError as exc:
        print(f"ct_history: {exc}", file=sys.stderr)
        return 2
    try:
        return {"list": cmd_list, "show": cmd_show, "compare": cmd_compare, "export": cmd_export,
                "trend": cmd_trend}[a.cmd](h, a)
    except ValueError as exc:
        print(f"ct_history: {exc}", file=sys.stderr)
        return 2
    finally:
        h.close()


if __name__ == "__main__":
    raise SystemExit(main())
