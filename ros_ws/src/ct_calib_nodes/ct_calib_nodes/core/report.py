"""Calibration report: error-map figures like Ferrucci et al. 2020 Figs 7-12.

Inputs are plain arrays (no solver objects), so the report can be written
from a live solve, an offline replay or a test alike:

* error maps are :class:`error_map.ErrorMap` (the one type of the project): a
  solved map (positioning, X/Y straightness, pitch, yaw, roll vs
  instrument-reported SRD, with standard uncertainties; "multi" and "single",
  in the "travel" (ISO 230-1) or "detector" (the paper's) definition) or an
  independent reference (laser interferometer / electronic level, without
  uncertainties, :func:`read_reference_error_map`).
* :class:`ParameterTable`: names, units, values, standard uncertainties and
  the correlation matrix of solved parameters.
* :class:`ReprojectionResiduals`: observed minus modelled centre projections
  [px] with their view / sphere / stage indices.

:func:`write_report` writes one PNG per error component (plus residual and
correlation figures) and ``index.html`` / ``index.md`` that reference them by
relative path. Error bars are expanded uncertainties U = 2u (k = 2).

matplotlib (Agg backend) is imported lazily inside the plotting functions so
importing this module stays cheap and never needs a display.

Error-map definitions and sign: see error_map.py. Every figure and table says
which definition it shows; positive positioning = the stage travelled less
than indexed (the paper's sign, section 4.1). Angles are about the {DF} axes;
yaw contains the rotary table's zero-index error (paper, section 4.3).
"""

from __future__ import annotations

import csv
import html
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .error_map import ErrorMap

__all__ = [
    "COMPONENTS",
    "ParameterTable",
    "ReprojectionResiduals",
    "read_reference_error_map",
    "write_report",
]

ARCSEC_RAD = math.pi / (180.0 * 3600.0)

#: (field, title, display unit, factor SI -> display, paper figure)
COMPONENTS = (
    ("positioning_m", "Positioning error", "µm", 1e6, "Fig. 7"),
    ("straightness_x_m", "X straightness error", "µm", 1e6, "Fig. 8"),
    ("straightness_y_m", "Y straightness error", "µm", 1e6, "Fig. 9"),
    ("pitch_rad", "Pitch (about X)", "arcsec", 1.0 / ARCSEC_RAD, "Fig. 10"),
    ("roll_rad", "Roll (about Z)", "arcsec", 1.0 / ARCSEC_RAD, "Fig. 11"),
    ("yaw_rad", "Yaw (about Y)", "arcsec", 1.0 / ARCSEC_RAD, "Fig. 12"),
)
#: components that depend on the definition (the angles do not)
_DEFINITION_DEPENDENT = ("positioning_m", "straightness_x_m", "straightness_y_m")
_DEFINITION_LABEL = {"travel": "along the stage travel (ISO 230-1)",
                     "detector": "detector frame (the paper's definition)"}
_FIELDS = tuple(c[0] for c in COMPONENTS)


def _vec(x, name, n=None, allow_nan=False) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim != 1 or (n is not None and a.shape[0] != n):
        want = f"({n},)" if n is not None else "(K,)"
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    bad = np.isinf(a) if allow_nan else ~np.isfinite(a)
    if np.any(bad):
        raise ValueError(f"{name} contains {'inf' if allow_nan else 'NaN or inf'}")
    return a


@dataclass(frozen=True)
class ParameterTable:
    """Solved parameters with standard uncertainties.

    Attributes
    ----------
    names : tuple of str, length P
    units : tuple of str, length P
        SI units ("m", "rad", or anything else, shown as given).
    values : ndarray of shape (P,)
    std_uncertainties : ndarray of shape (P,)
        Standard uncertainties (k = 1), same units as values.
    correlation : ndarray of shape (P, P) or None
        Correlation matrix of the estimates.
    title : str
    """

    names: tuple
    units: tuple
    values: np.ndarray
    std_uncertainties: np.ndarray
    correlation: np.ndarray | None = None
    title: str = "Parameters"

    def __post_init__(self):
        names = tuple(str(n) for n in self.names)
        units = tuple(str(u) for u in self.units)
        p = len(names)
        if p == 0 or len(units) != p:
            raise ValueError(f"names and units must be non-empty and of equal length, got {p} and {len(units)}")
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "units", units)
        object.__setattr__(self, "values", _vec(self.values, "values", p))
        u = _vec(self.std_uncertainties, "std_uncertainties", p, allow_nan=True)
        if np.any(u < 0):
            raise ValueError("std_uncertainties must be non-negative")
        object.__setattr__(self, "std_uncertainties", u)
        if self.correlation is not None:
            c = np.asarray(self.correlation, dtype=float)
            if c.shape != (p, p) or not np.all(np.isfinite(c)):
                raise ValueError(f"correlation must be a finite ({p}, {p}) matrix, got {c.shape}")
            if not (np.allclose(c, c.T, atol=1e-9) and np.all(np.abs(c) <= 1 + 1e-9)):
                raise ValueError("correlation must be symmetric with entries in [-1, 1]")
            object.__setattr__(self, "correlation", c)

    @classmethod
    def from_covariance(cls, names, units, values, covariance, title="Parameters"):
        """Build from a covariance matrix (P, P): u = sqrt(diag), corr = cov / (u u^T)."""
        cov = np.asarray(covariance, dtype=float)
        p = len(names)
        if cov.shape != (p, p) or not np.all(np.isfinite(cov)):
            raise ValueError(f"covariance must be a finite ({p}, {p}) matrix, got {cov.shape}")
        u = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = cov / np.outer(u, u)
        corr = np.where(np.isfinite(corr), corr, 0.0)
        np.fill_diagonal(corr, 1.0)
        return cls(tuple(names), tuple(units), values, u, np.clip(corr, -1.0, 1.0), title)


@dataclass(frozen=True)
class ReprojectionResiduals:
    """Reprojection residuals (observed minus modelled centre projection).

    Attributes
    ----------
    residuals_px : ndarray of shape (n, 2)
        (d_col, d_row) [px].
    view_index : ndarray of shape (n,), int
        Projection (view) index j of each observation.
    sphere_index : ndarray of shape (n,), int
        Sphere index i (as matched by the detector, not simulator ids).
    stage_index : ndarray of shape (n,), int, optional
        Stage position index k (0-based); all zero if omitted.
    label : str
    """

    residuals_px: np.ndarray
    view_index: np.ndarray
    sphere_index: np.ndarray
    stage_index: np.ndarray | None = None
    label: str = "residuals"

    def __post_init__(self):
        r = np.asarray(self.residuals_px, dtype=float)
        if r.ndim != 2 or r.shape[1] != 2 or r.shape[0] == 0:
            raise ValueError(f"residuals_px must have shape (n, 2) with n >= 1, got {r.shape}")
        if not np.all(np.isfinite(r)):
            raise ValueError("residuals_px contains NaN or inf")
        n = r.shape[0]
        object.__setattr__(self, "residuals_px", r)
        for name in ("view_index", "sphere_index", "stage_index"):
            v = getattr(self, name)
            if v is None and name == "stage_index":
                v = np.zeros(n, dtype=int)
            if v is None:
                raise ValueError(f"{name} is required")
            v = np.asarray(v)
            if v.shape != (n,) or not np.issubdtype(v.dtype, np.integer):
                raise ValueError(f"{name} must be an integer array of shape ({n},), got {v.dtype} {v.shape}")
            object.__setattr__(self, name, v)

    def rms_px(self) -> float:
        """Root mean square of the residual vector length [px]."""
        return float(np.sqrt(np.mean(np.sum(self.residuals_px ** 2, axis=1))))


# ----------------------------------------------------------------------------- error map

def read_reference_error_map(path, name: str | None = None) -> ErrorMap:
    """Read independent reference measurements of the stage error map.

    Two formats, both in SI units (metres, radians), chosen by extension.

    CSV (``.csv``): optional ``#`` comment lines, then a header row and one
    row per stage position::

        # reference: laser interferometer + electronic level, 2020-03-02
        srd_m,positioning_m,straightness_x_m,straightness_y_m,pitch_rad,yaw_rad,roll_rad
        0.364,0.0,0.0,0.0,0.0,0.0,0.0
        0.384,1.2e-05,...

    YAML (``.yaml`` / ``.yml``)::

        name: laser interferometer        # optional
        units: SI                         # required if present: must be SI
        srd_m: [0.364, 0.384, ...]
        positioning_m: [0.0, 1.2e-05, ...]
        pitch_rad: [...]

    ``srd_m`` (instrument-reported SRD) is required; every other component
    is optional (a missing column, key or empty cell becomes NaN and is not
    plotted). Rows are sorted by SRD.

    Parameters
    ----------
    path : str or Path
    name : str, optional
        Legend label; default the YAML ``name`` or ``"reference"``.

    The reference is taken to measure along the stage travel (what a laser
    interferometer and an electronic level do): definition "travel", with the
    project's sign (positive = travelled less than indexed; negate an ISO 230-2
    actual - target printout).

    Returns
    -------
    ErrorMap
        With all uncertainties None.
    """
    p = Path(path)
    ext = p.suffix.lower()
    data: dict = {}
    label = name
    if ext == ".csv":
        with open(p, newline="") as fh:
            rows = [r for r in csv.reader(line for line in fh if line.strip() and not line.lstrip().startswith("#"))]
        if not rows:
            raise ValueError(f"{p}: no header row")
        header = [h.strip() for h in rows[0]]
        unknown = set(header) - set(_FIELDS) - {"srd_m"}
        if unknown:
            raise ValueError(f"{p}: unknown columns {sorted(unknown)}; expected srd_m and some of {_FIELDS}")
        for j, h in enumerate(header):
            col = []
            for r in rows[1:]:
                cell = r[j].strip() if j < len(r) else ""
                try:
                    col.append(float(cell) if cell else math.nan)
                except ValueError as exc:
                    raise ValueError(f"{p}: column {h}: cannot read {cell!r} as a number") from exc
            data[h] = col
    elif ext in (".yaml", ".yml"):
        import yaml

        doc = yaml.safe_load(p.read_text())
        if not isinstance(doc, dict):
            raise ValueError(f"{p}: expected a mapping at the top level")
        units = doc.get("units", "SI")
        if str(units).upper() != "SI":
            raise ValueError(f"{p}: units must be SI (metres, radians), got {units!r}")
        label = label or doc.get("name")
        unknown = set(doc) - set(_FIELDS) - {"srd_m", "name", "units", "notes"}
        if unknown:
            raise ValueError(f"{p}: unknown keys {sorted(unknown)}")
        for key in ("srd_m",) + _FIELDS:
            if key in doc:
                data[key] = [math.nan if v is None else float(v) for v in doc[key]]
    else:
        raise ValueError(f"{p}: reference file must be .csv, .yaml or .yml")
    if "srd_m" not in data:
        raise ValueError(f"{p}: srd_m is required")
    srd = np.asarray(data["srd_m"], dtype=float)
    if srd.size == 0 or not np.all(np.isfinite(srd)):
        raise ValueError(f"{p}: srd_m must be non-empty and finite")
    order = np.argsort(srd, kind="stable")
    vals = {}
    for f in _FIELDS:
        v = np.asarray(data.get(f, [math.nan] * srd.size), dtype=float)
        if v.shape != srd.shape:
            raise ValueError(f"{p}: {f} has {v.size} values, srd_m has {srd.size}")
        vals[f] = v[order]
    return ErrorMap.reference(str(label or "reference"), srd[order], definition="travel", **vals)


# ----------------------------------------------------------------------------- plotting

_STYLES = (("C0", "o"), ("C1", "s"), ("C2", "D"), ("C3", "v"), ("C4", "P"))


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _reference_at(ref: ErrorMap, comp: str, srd: np.ndarray) -> np.ndarray:
    """Reference values linearly interpolated at ``srd``; NaN outside its range."""
    v = ref.values(comp)
    ok = np.isfinite(v)
    if ok.sum() == 0:
        return np.full(srd.shape, math.nan)
    if ok.sum() == 1:
        return np.where(np.isclose(srd, ref.srd_reported_m[ok][0], rtol=0, atol=1e-9), v[ok][0], math.nan)
    out = np.interp(srd, ref.srd_reported_m[ok], v[ok])
    return np.where((srd >= ref.srd_reported_m[ok][0] - 1e-12) & (srd <= ref.srd_reported_m[ok][-1] + 1e-12),
                    out, math.nan)


def _plot_component(plt, comp, title, unit, factor, fig_ref, series, reference, path, definition):
    has_ref = (reference is not None and (comp not in _DEFINITION_DEPENDENT or reference.definition == definition)
               and np.any(np.isfinite(reference.values(comp))))
    if has_ref:
        fig, (ax, axd) = plt.subplots(2, 1, figsize=(7.0, 6.2), sharex=True,
                                      gridspec_kw={"height_ratios": [2.2, 1.0]})
    else:
        fig, ax = plt.subplots(1, 1, figsize=(7.0, 4.4))
        axd = None
    for s, (colour, marker) in zip(series, _STYLES * 4):
        x = s.srd_reported_m * 1e3
        y = s.values(comp) * factor
        u = s.uncertainty(comp)
        yerr = None if u is None else 2.0 * u * factor
        ax.errorbar(x, y, yerr=yerr, fmt=marker, color=colour, ms=5, mfc="none" if marker != "o" else colour,
                    capsize=3, elinewidth=1, label=s.name)
        if axd is not None:
            d = (s.values(comp) - _reference_at(reference, comp, s.srd_reported_m)) * factor
            axd.errorbar(x, d, yerr=yerr, fmt="^", color=colour, ms=5, capsize=3, elinewidth=1,
                         label=f"{s.name} − {reference.name}")
    if has_ref:
        ok = np.isfinite(reference.values(comp))
        ax.plot(reference.srd_reported_m[ok] * 1e3, reference.values(comp)[ok] * factor, "-", color="k", lw=1.6,
                label=reference.name)
        axd.axhline(0.0, color="k", lw=0.8)
        axd.set_ylabel(f"Δ [{unit}]")
        axd.set_xlabel("Stage SRD (instrument reading) [mm]")
        axd.grid(True, alpha=0.3)
        axd.legend(fontsize=8, loc="best")
    else:
        ax.set_xlabel("Stage SRD (instrument reading) [mm]")
    ax.set_ylabel(f"{title} [{unit}]")
    what = f"{title}, {_DEFINITION_LABEL[definition]}" if comp in _DEFINITION_DEPENDENT else title
    sign = "; + = travelled less than indexed" if comp == "positioning_m" else ""
    sign += "; includes the rotary zero-index error" if comp == "yaw_rad" else ""
    ax.set_title(f"{what} ({fig_ref} style{sign})\nerror bars: U = 2u (k = 2)", fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=9, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return has_ref


def _rms_by(r, index):
    keys = np.unique(index)
    return keys, np.array([np.sqrt(np.mean(np.sum(r[index == i] ** 2, axis=1))) for i in keys])


def _plot_residuals(plt, res: ReprojectionResiduals, path):
    r = res.residuals_px
    stages = np.unique(res.stage_index)
    fig, axs = plt.subplots(2, 2, figsize=(11.0, 7.6))
    axs = axs.ravel()
    lim = max(float(np.max(np.abs(r))), 1e-12)
    bins = np.linspace(-lim, lim, 41)
    axs[0].hist(r[:, 0], bins=bins, histtype="step", lw=1.5, label=f"Δcol (σ = {r[:, 0].std():.3g} px)")
    axs[0].hist(r[:, 1], bins=bins, histtype="step", lw=1.5, label=f"Δrow (σ = {r[:, 1].std():.3g} px)")
    axs[0].set_xlabel("Reprojection residual [px]")
    axs[0].set_ylabel("Count")
    axs[0].legend(fontsize=8)
    axs[0].set_title("Residual histogram", fontsize=10)
    if stages.size == 1:
        views, rms = _rms_by(r, res.view_index)
        axs[1].plot(views, rms, ".-", ms=3, lw=0.8, color="C0")
        axs[1].set_xlabel("View index j")
        axs[1].set_ylabel("RMS residual per view [px]")
    else:
        views = np.unique(res.view_index)
        grid = np.full((stages.size, views.size), np.nan)
        for a, k in enumerate(stages):
            sel = res.stage_index == k
            vk, rms = _rms_by(r[sel], res.view_index[sel])
            grid[a, np.searchsorted(views, vk)] = rms
        im = axs[1].imshow(grid, aspect="auto", origin="lower", cmap="viridis", interpolation="nearest",
                           extent=(views[0] - 0.5, views[-1] + 0.5, -0.5, stages.size - 0.5))
        axs[1].set_yticks(range(stages.size), [str(k) for k in stages], fontsize=7)
        axs[1].set_xlabel("View index j")
        axs[1].set_ylabel("Stage position index k")
        fig.colorbar(im, ax=axs[1], label="RMS residual per view [px]")
    axs[1].set_title("Per-view RMS", fontsize=10)
    spheres, rms_s = _rms_by(r, res.sphere_index)
    axs[2].bar(spheres, rms_s, color="C2")
    axs[2].set_xlabel("Sphere index i")
    axs[2].set_ylabel("RMS residual per sphere [px]")
    axs[2].set_title("Per-sphere RMS", fontsize=10)
    ks, rms_k = _rms_by(r, res.stage_index)
    axs[3].plot(ks, rms_k, "o-", color="C3")
    axs[3].set_xlabel("Stage position index k")
    axs[3].set_ylabel("RMS residual per stage position [px]")
    axs[3].set_title("Per-stage RMS", fontsize=10)
    axs[3].set_ylim(0.0, 1.15 * float(np.max(rms_k)) + 1e-12)
    axs[3].set_xticks(ks if ks.size <= 25 else ks[:: int(math.ceil(ks.size / 25))])
    for ax in (axs[0], axs[2], axs[3]):
        ax.grid(True, alpha=0.3)
    fig.suptitle(f"{res.label}: {r.shape[0]} observations, RMS {res.rms_px():.4g} px", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_correlation(plt, table: ParameterTable, path):
    p = len(table.names)
    size = max(4.5, 0.42 * p + 2.0)
    fig, ax = plt.subplots(figsize=(size + 1.0, size))
    im = ax.imshow(table.correlation, cmap="RdBu_r", vmin=-1.0, vmax=1.0)
    ax.set_xticks(range(p), table.names, rotation=90, fontsize=8)
    ax.set_yticks(range(p), table.names, fontsize=8)
    if p <= 20:
        for i in range(p):
            for j in range(p):
                c = table.correlation[i, j]
                ax.text(j, i, f"{c:.2f}", ha="center", va="center", fontsize=6,
                        color="white" if abs(c) > 0.6 else "black")
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="Correlation coefficient")
    ax.set_title(f"{table.title}: correlation matrix", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------- tables

def _fmt(x, spec=".9g") -> str:
    return "—" if x is None or not np.isfinite(x) else format(float(x), spec)


def _param_rows(table: ParameterTable):
    """Rows: name, unit, value (SI), u (SI), value (display), u (display)."""
    rows = []
    for n, unit, v, u in zip(table.names, table.units, table.values, table.std_uncertainties):
        if unit == "rad":
            disp = (f"{_fmt(v / (math.pi / 180.0), '.7g')} °", f"{_fmt(u / ARCSEC_RAD, '.4g')} arcsec")
        elif unit == "m":
            disp = (f"{_fmt(v * 1e3, '.9g')} mm", f"{_fmt(u * 1e6, '.4g')} µm")
        else:
            disp = ("", "")
        rows.append([n, unit, _fmt(v), _fmt(u), disp[0], disp[1]])
    return ["parameter", "unit", "value", "u (k=1)", "value (display)", "u (display)"], rows


def _error_map_rows(s: ErrorMap):
    head = ["SRD [mm]"] + [f"{c[1]} [{c[2]}] (± U, k=2)" for c in COMPONENTS]
    rows = []
    for i in range(s.srd_reported_m.size):
        row = [_fmt(s.srd_reported_m[i] * 1e3, ".6g")]
        for comp, _, _, f, _ in COMPONENTS:
            v = s.values(comp)[i] * f
            u = s.uncertainty(comp)
            row.append(_fmt(v, ".4f") + ("" if u is None else f" ± {_fmt(2.0 * u[i] * f, '.4f')}"))
        rows.append(row)
    return head, rows


def _html_table(head, rows, cls="") -> str:
    out = [f'<table class="{cls}">', "<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"]
    for r in rows:
        out.append("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def _md_table(head, rows) -> str:
    def esc(c):
        return str(c).replace("|", "\\|")

    lines = ["| " + " | ".join(esc(h) for h in head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(esc(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


# ----------------------------------------------------------------------------- report

@dataclass(frozen=True)
class _Section:
    title: str
    text: str = ""
    images: tuple = ()
    tables: tuple = field(default_factory=tuple)   # (head, rows)


def write_report(out_dir, series, reference: ErrorMap | None = None, params_table=None,
                 residuals=None, meta: dict | None = None, title: str = "CT stage error-map calibration report"):
    """Write the calibration report (PNGs + index.html + index.md).

    Parameters
    ----------
    out_dir : str or Path
        Output directory (created if needed); existing files are overwritten.
    series : sequence of ErrorMap
        Measured error maps (e.g. "multi", "single"), with uncertainties, in
        one or both definitions ("travel": all six figures; "detector", the
        paper's: its own positioning and straightness figures).
    reference : ErrorMap, optional
        Independent reference measurements; adds the reference line and the
        delta (series minus reference, reference interpolated linearly at the
        series SRDs) sub-plot to each figure.
    params_table : ParameterTable or sequence of them, optional
        Parameter tables; a correlation image is drawn for each that has one.
    residuals : ReprojectionResiduals or sequence of them, optional
    meta : dict, optional
        Metadata shown as a table (input files, observation and rejection
        counts, wall time, ...). Values are shown with ``str()``.
    title : str, optional

    Returns
    -------
    pathlib.Path
        Path of ``index.html``; ``index.md`` is written beside it.
    """
    series = list(series)
    if not series or not all(isinstance(s, ErrorMap) for s in series):
        raise ValueError("series must be a non-empty sequence of ErrorMap")
    if len({(s.name, s.definition) for s in series}) != len(series):
        raise ValueError("series (name, definition) pairs must be unique")
    if reference is not None and not isinstance(reference, ErrorMap):
        raise ValueError("reference must be an ErrorMap or None")
    tables = [] if params_table is None else (
        [params_table] if isinstance(params_table, ParameterTable) else list(params_table))
    if not all(isinstance(t, ParameterTable) for t in tables):
        raise ValueError("params_table must be a ParameterTable or a sequence of them")
    res_list = [] if residuals is None else (
        [residuals] if isinstance(residuals, ReprojectionResiduals) else list(residuals))
    if not all(isinstance(r, ReprojectionResiduals) for r in res_list):
        raise ValueError("residuals must be a ReprojectionResiduals or a sequence of them")
    meta = dict(meta or {})

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plt = _pyplot()
    sections = []

    ref_txt = (f" Reference: {reference.name} (solid line, measured along the stage travel); the lower panels "
               "show series minus reference (reference interpolated linearly at the series' SRD)."
               if reference is not None else "")
    for definition in ("travel", "detector"):
        group = [s for s in series if s.definition == definition]
        if not group:
            continue
        # beside a "travel" map, the paper's definition adds its positioning figure (the Fig. 7
        # comparison): its straightness differs only by the travel-normal angle times the
        # positioning's departure from a line, and its angles are the same
        comps = COMPONENTS if definition == "travel" or not any(s.definition == "travel" for s in series) \
            else COMPONENTS[:1]
        imgs = []
        for comp, ctitle, unit, factor, fig_ref in comps:
            suffix = "" if definition == "travel" else "_detector_frame"
            name = f"error_{comp.rsplit('_', 1)[0]}{suffix}.png"
            has_delta = _plot_component(plt, comp, ctitle, unit, factor, fig_ref, group, reference, out / name,
                                        definition)
            imgs.append((name, f"{ctitle} vs stage SRD" + (" with delta to reference" if has_delta else "")))
        first = group[0]
        angle = first.angle_travel_normal_rad
        extra = ""
        if np.isfinite(angle):
            extra = (f" Angle between the fitted stage travel and the detector normal: "
                     f"{math.degrees(angle):.4f}° (u = {_fmt(first.u_angle_travel_normal_rad / ARCSEC_RAD, '.3g')}"
                     " arcsec).")
        sections.append(_Section(
            f"Stage error map: {_DEFINITION_LABEL[definition]}",
            " ".join(first.notes) + "." + extra + " Error bars are expanded uncertainties U = 2u "
            "(coverage factor k = 2)." + (ref_txt if definition == "travel" else ""),
            tuple(imgs),
            tuple(_error_map_rows(s) + (f"Error map: {s.name} ({_DEFINITION_LABEL[definition]})",) for s in group)))

    for t_i, t in enumerate(tables):
        img = ()
        if t.correlation is not None:
            name = f"correlation_{t_i}.png"
            _plot_correlation(plt, t, out / name)
            img = ((name, f"{t.title}: correlation matrix"),)
        head, rows = _param_rows(t)
        sections.append(_Section(t.title, "Standard uncertainties u (k = 1); angles also in degrees "
                                          "(value) and arcseconds (u), lengths in mm (value) and µm (u).",
                                 img, ((head, rows, t.title),)))

    for r_i, r in enumerate(res_list):
        name = f"residuals_{r_i}.png"
        _plot_residuals(plt, r, out / name)
        stats = [["observations", str(r.residuals_px.shape[0])],
                 ["RMS |residual| [px]", _fmt(r.rms_px(), ".4g")],
                 ["mean Δcol, Δrow [px]", f"{_fmt(r.residuals_px[:, 0].mean(), '.3g')}, "
                                          f"{_fmt(r.residuals_px[:, 1].mean(), '.3g')}"],
                 ["max |residual| [px]", _fmt(np.max(np.hypot(*r.residuals_px.T)), ".4g")]]
        sections.append(_Section(f"Reprojection residuals: {r.label}",
                                 "Observed minus modelled sphere-centre projections.",
                                 ((name, f"Residuals {r.label}"),), ((["statistic", "value"], stats, ""),)))

    if meta:
        sections.append(_Section("Metadata", "", (), ((["key", "value"],
                                                       [[str(k), str(v)] for k, v in meta.items()], ""),)))

    # HTML
    h = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
         f"<title>{html.escape(title)}</title>",
         "<style>body{font-family:sans-serif;max-width:1100px;margin:auto;padding:1em}"
         "table{border-collapse:collapse;margin:0.6em 0;font-size:0.85em}"
         "td,th{border:1px solid #bbb;padding:2px 6px;text-align:right}"
         "th{background:#eee}img{max-width:100%;border:1px solid #ddd;margin:0.4em 0}</style>",
         "</head><body>", f"<h1>{html.escape(title)}</h1>"]
    md = [f"# {title}", ""]
    for s in sections:
        h.append(f"<h2>{html.escape(s.title)}</h2>")
        md += [f"## {s.title}", ""]
        if s.text:
            h.append(f"<p>{html.escape(s.text)}</p>")
            md += [s.text, ""]
        for name, alt in s.images:
            h.append(f'<figure><img src="{html.escape(name)}" alt="{html.escape(alt)}">'
                     f"<figcaption>{html.escape(alt)}</figcaption></figure>")
            md += [f"![{alt}]({name})", ""]
        for head, rows, caption in s.tables:
            if caption:
                h.append(f"<h3>{html.escape(caption)}</h3>")
                md += [f"### {caption}", ""]
            h.append(_html_table(head, rows))
            md += [_md_table(head, rows), ""]
    h.append("</body></html>")
    index = out / "index.html"
    index.write_text("\n".join(h), encoding="utf-8")
    (out / "index.md").write_text("\n".join(md), encoding="utf-8")
    return index
