"""What a finished CT calibration campaign leaves on disk: the report and the reconstruction
geometry. Used by the demo (from published results) and the offline solve (from core results)."""

from __future__ import annotations

import pathlib

import numpy as np

from ct_calib_nodes.core import report as rep
from ct_calib_nodes.core.export import export_geometry_files


def write_report_and_export(out_dir, *, names, units, values, covariance, geometry, series, motions,
                            srd_reported_m, detector, reference_path=None, residuals=None, meta=None,
                            n_export_views: int = 360) -> pathlib.Path:
    """Write ``report/`` (PNG + index.html + index.md) and ``geometry_export/`` under out_dir.

    Parameters
    ----------
    names, units, values, covariance : static parameter table (13 names, units, values, (13,13))
    geometry : DetectorFrameGeometry of the static solution
    series : list of error_map.ErrorMap ("multi", "single"; both definitions)
    motions : ndarray of shape (K, 6), multi-projection error motions (row 0 zeros)
    srd_reported_m : ndarray of shape (K,)
    reference_path : optional reference error-map file (CSV/YAML) for the delta plots
    """
    out = pathlib.Path(out_dir)
    reference = rep.read_reference_error_map(reference_path, name="reference") if reference_path else None
    table = rep.ParameterTable.from_covariance(list(names), list(units), np.asarray(values, dtype=float),
                                              np.asarray(covariance, dtype=float),
                                              title="Static geometry at the first stage position")
    index = rep.write_report(out / "report", series, reference=reference, params_table=table,
                             residuals=residuals, meta=meta or {})
    alphas = 2 * np.pi * np.arange(n_export_views) / n_export_views
    export_geometry_files(out / "geometry_export", geometry, np.asarray(motions, dtype=float), alphas, detector,
                          srd_reported_m=np.asarray(srd_reported_m, dtype=float))
    return index
