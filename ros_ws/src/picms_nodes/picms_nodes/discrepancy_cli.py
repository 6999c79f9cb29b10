"""Offline sim-to-real discrepancy check of a Pixel Probe recording (issue 11, Pixel Probe part).

    picms_discrepancy RECORDING [--cell picms_cell.yaml] [--namespace NS] [--out DIR] [--max-terms 3]

The recording is read and calibrated exactly as ``picms_calibrate_offline`` does (core.pipeline);
the camera pose fit's disc-centre residuals then go through the discrepancy engine
(core/picms_discrepancy.py). Written to ``--out`` (default ``<recording>_discrepancy``):
``discrepancy.json`` (same keys as the CT command; doc/picms_discrepancy.md), ``report.md`` (the
verdict first) and PNG plots of the residuals before and after, per camera, along station order.
Exit status: 0 verdict written; 1 no calibration from the recording; 2 bad arguments or files.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np


def _plots(out, tmp: pathlib.Path) -> list:
    import matplotlib  # noqa: PLC0415
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415
    a = out["_arrays"]
    fig, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for ax, key, title in ((axes[0], "residual_before", "nominal model"), (axes[1], "residual_after", "with findings")):
        r = np.asarray(a[key])
        for j in sorted(set(a["camera"].tolist())):
            for c, mk in ((0, "o"), (1, "x")):
                s = (a["camera"] == j) & (a["comp"] == c)
                ax.plot(a["station"][s], r[s], mk, ms=3, label=f"camera {j + 1} {'uv'[c]}")
        ax.set_title(f"disc-centre residuals, {title}")
        ax.set_ylabel("px")
    axes[1].set_xlabel("station (acquisition order)")
    axes[0].legend(fontsize=6, ncol=3)
    fig.tight_layout()
    fig.savefig(tmp / "residuals.png", dpi=90)
    plt.close(fig)
    return ["residuals.png"]


def _report(out) -> str:
    lines = [out["verdict"], "", "## Fit", "", "| | rms px | chi2/dof | held-out rms px |", "|---|---|---|---|"]
    for k in ("fit_before", "fit_after"):
        f = out[k]
        lines.append(f"| {k} | {f['rms']:.4g} | {f['chi2_dof']:.3f} | {f['held_out_rms']:.4g} |")
    lines += ["", "## Findings", ""]
    for f in out["findings"]:
        lines.append(f"- **{f['name']}** (`{f['term']}`): {f['magnitude']:.3g} +- {f['magnitude_u']:.2g} "
                     f"{f['magnitude_unit']}, {f['significance_sigma']:.1f} sigma, delta BIC {f['delta_bic']:.1f}"
                     + (f"; degenerate with {f['degenerate_with']}, separate by {f['separate_by']}"
                        if f["degenerate_with"] else ""))
    if not out["findings"]:
        lines.append("none")
    lines += ["", "## Unexplained structure", ""] + [f"- {u['axis']}: {u['significance_sigma']:.1f} sigma"
                                                      for u in out["unexplained"]] + (["none"] if not out["unexplained"] else [])
    lines += ["", "## Detection limits", "", "| term | limit | unit | how to reveal |", "|---|---|---|---|"]
    for k, v in out["detection_limits"].items():
        lim = "not observable: " + v["cannot_see"] if v["limit"] is None else f"{v['limit']:.3g}"
        lines.append(f"| {k} | {lim} | {v['unit']} | {v['reveal_by']} |")
    lines += ["", "![residuals](residuals.png)", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="picms_discrepancy", description=__doc__.split("\n")[0])
    ap.add_argument("recording")
    ap.add_argument("--cell")
    ap.add_argument("--namespace")
    ap.add_argument("--out")
    ap.add_argument("--max-terms", type=int, default=3)
    a = ap.parse_args(argv)
    from ct_calib_nodes.io.atomic import staged_outputs  # noqa: PLC0415

    from .core.calibrate import CalibrationError  # noqa: PLC0415
    from .core.picms_discrepancy import motion_of, run  # noqa: PLC0415
    from .core.pipeline import calibrate_recording  # noqa: PLC0415
    from .io.files import read_cell  # noqa: PLC0415
    from .io.recording import find_namespace, iter_frames, read_recording  # noqa: PLC0415
    from .offline import find_cell_file  # noqa: PLC0415
    rec_path = pathlib.Path(a.recording)
    if not rec_path.exists():
        print(f"picms_discrepancy: no recording at {rec_path}", file=sys.stderr)
        return 2
    try:
        cell = read_cell(find_cell_file(rec_path, a.cell))
        ns = find_namespace(rec_path, a.namespace)
        rec, rep = read_recording(rec_path, cell, ns)
    except (OSError, ValueError) as exc:
        print(f"picms_discrepancy: cannot read {rec_path}: {exc}", file=sys.stderr)
        return 2
    print(f"calibrating {rec_path} ...", flush=True)
    try:
        res, _ = calibrate_recording(rec, frames=iter_frames(rec_path, rep, ns))
        out = run(res, rec.camera_info, progress=lambda m: print(m, flush=True), max_terms=a.max_terms,
                  motion=motion_of(rec))
    except (CalibrationError, ValueError) as exc:
        print(f"picms_discrepancy: no calibration to analyse: {exc}", file=sys.stderr)
        return 1
    dest = pathlib.Path(a.out) if a.out else rec_path.with_name(rec_path.name.rstrip("/") + "_discrepancy")
    with staged_outputs(dest) as tmp:
        _plots(out, tmp)
        (tmp / "report.md").write_text(_report(out))
        js = {k: v for k, v in out.items() if k != "_arrays"}
        (tmp / "discrepancy.json").write_text(json.dumps(js, indent=1, default=float))
    print(out["verdict"])
    print(f"written to {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
