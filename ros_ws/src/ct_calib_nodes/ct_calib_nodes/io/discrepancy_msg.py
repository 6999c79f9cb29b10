"""discrepancy.json dict (core/ct_discrepancy.run) -> metro_msgs/DiscrepancyReport, and the history record."""

from __future__ import annotations

import json
import math

KIND_DISCREPANCY = "discrepancy"
SUCCESS, INSUFFICIENT_DATA, FAILED, POOR_FIT = 0, 3, 4, 5


def report_json(out: dict) -> str:
    """The report as JSON text (private arrays dropped, numpy values made plain)."""
    from ct_calib_nodes.io.results import _plain  # noqa: PLC0415

    return json.dumps(_plain({k: v for k, v in out.items() if not k.startswith("_")}))


def status_of(out: dict) -> tuple[int, str]:
    """(SolveStatus code, message) of a verdict: SUCCESS when adequate, POOR_FIT when the model was found inadequate."""
    if out["adequate"]:
        return SUCCESS, "model adequate: " + out["verdict"]
    return POOR_FIT, "model inadequate (discrepancy engine): " + out["verdict"]


def _f(x) -> float:
    return float("nan") if x is None else float(x)


#: the report's single-fit figures (NaN where there is no one fit to give them from)
_FIT_FIELDS = ("noise_floor_u_px", "noise_floor_v_px", "shared_floor_u_px", "shared_floor_v_px", "rms_before_px",
               "rms_after_px", "held_out_rms_before_px", "held_out_rms_after_px", "chi2_dof_before", "chi2_dof_after")


def _report(stamp, campaign_id: str, calibration_topic: str):
    """An empty metro_msgs/DiscrepancyReport with its header and campaign fields filled."""
    from metro_msgs.msg import DiscrepancyReport  # noqa: PLC0415

    m = DiscrepancyReport()
    m.header.stamp = stamp
    m.header.frame_id = "ct_detector"
    m.campaign_id = campaign_id or ""
    m.calibration_topic = calibration_topic
    return m


def _finding_msg(f: dict, name: str, cv_gain: float):
    """metro_msgs/DiscrepancyFinding of one finding of discrepancy.json (shown as ``name``)."""
    from metro_msgs.msg import DiscrepancyFinding  # noqa: PLC0415

    d = DiscrepancyFinding(term=f["term"], name=name, mechanism=f["mechanism"],
                           significance_sigma=_f(f["significance_sigma"]), delta_bic=_f(f["delta_bic"]),
                           cv_gain=cv_gain, magnitude=_f(f["magnitude"]), u_magnitude=_f(f.get("magnitude_u")),
                           magnitude_unit=f["magnitude_unit"])
    d.parameter_names = [p["name"] for p in f["parameters"]]
    d.values = [_f(p["value"]) for p in f["parameters"]]
    d.u_values = [_f(p["u"]) for p in f["parameters"]]
    d.parameter_units = [p["unit"] for p in f["parameters"]]
    d.degenerate_with = [str(x) for x in f["degenerate_with"]]
    d.correlated_with_calibrated = [str(x) for x in f.get("correlated_with_calibrated", [])]
    d.separate_by = [str(x) for x in f["separate_by"]]
    return d


def _add_limits(m, limits: dict, prefix: str = "") -> None:
    """Append detection limits (NaN = cannot be seen here) to the report's parallel arrays."""
    for k, v in limits.items():
        m.limit_terms.append(prefix + k)
        lim = v.get("limit")
        m.limit_values.append(float("nan") if lim is None or not math.isfinite(lim) else float(lim))
        m.limit_units.append(v["unit"])


def discrepancy_msg(out: dict, stamp, *, campaign_id: str = "", calibration_topic: str = ""):
    """metro_msgs/DiscrepancyReport of a run() result; ``stamp`` is the analysed calibration's stamp."""
    m = _report(stamp, campaign_id, calibration_topic)
    code, text = status_of(out)
    m.status.code = code
    m.status.message = text
    m.status.observations = 2 * int(out.get("n_observations", 0))
    m.status.rms_residual = _f(out["fit_before"]["rms"])
    m.verdict = out["verdict"]
    m.adequate = bool(out["adequate"])
    nf = out["noise_floor"]
    m.noise_floor_u_px, m.noise_floor_v_px = _f(nf["independent_sd"]["u"]), _f(nf["independent_sd"]["v"])
    m.shared_floor_u_px = _f(nf["shared_per_projection_sd"]["u"])
    m.shared_floor_v_px = _f(nf["shared_per_projection_sd"]["v"])
    fb, fa = out["fit_before"], out["fit_after"]
    m.rms_before_px, m.rms_after_px = _f(fb["rms"]), _f(fa["rms"])
    m.held_out_rms_before_px, m.held_out_rms_after_px = _f(fb["held_out_rms"]), _f(fa["held_out_rms"])
    m.chi2_dof_before, m.chi2_dof_after = _f(fb["chi2_dof"]), _f(fa["chi2_dof"])
    m.findings = [_finding_msg(f, f["name"], _f(f["cv_gain"])) for f in out["findings"]]
    m.unexplained_axes = [u["axis"] for u in out["unexplained"]]
    m.unexplained_sigma = [_f(u["significance_sigma"]) for u in out["unexplained"]]
    _add_limits(m, out["detection_limits"])
    m.report_json = report_json(out)
    return m


def failed_msg(stamp, code: int, text: str, *, campaign_id: str = "", calibration_topic: str = ""):
    """A report that says the engine could not judge (INSUFFICIENT_DATA / FAILED): adequate false, no verdict."""
    m = _report(stamp, campaign_id, calibration_topic)
    m.status.code = int(code)
    m.status.message = text
    m.verdict = "No verdict: " + text
    m.adequate = False
    for f in _FIT_FIELDS:
        setattr(m, f, float("nan"))
    m.report_json = json.dumps({"verdict": m.verdict, "adequate": False, "error": text})
    return m


def discrepancy_record(out: dict | None, *, cell: str, source: str, campaign_id=None, inputs=(), data_start_ns=None,
                       data_end_ns=None, status: str | None = None, message: str = ""):
    """Calibration-history record of kind 'discrepancy' (quantities: the findings' parameters and the fit)."""
    from ct_calib_nodes.io.history import Quantity, SolveRecord  # noqa: PLC0415
    from ct_calib_nodes.io.results import _plain  # noqa: PLC0415

    q = []
    if out is not None:
        code, text = status_of(out)
        status = status or ("success" if code == SUCCESS else "poor_fit")
        message = message or text
        for f in out["findings"]:
            for p in f["parameters"]:
                q.append(Quantity(name=f"{f['term']}.{p['name']}", value=float(p["value"]), u=float(p["u"]),
                                  unit=p["unit"]))
        for side in ("before", "after"):
            q.append(Quantity(name=f"held_out_rms_{side}_px", value=_f(out[f"fit_{side}"]["held_out_rms"]), unit="px"))
        result = _plain({k: v for k, v in out.items() if not k.startswith("_")})
    else:
        result = {"error": message}
    return SolveRecord(cell=cell, kind=KIND_DISCREPANCY, status=status or "failed", message=message, result=result,
                       source=source, campaign_id=campaign_id, data_start_ns=data_start_ns, data_end_ns=data_end_ns,
                       inputs=list(inputs), quantities=q)


# --------------------------------------------------------------------------- every stage position (error map)
KIND_DISCREPANCY_POSITIONS = "discrepancy_error_map"


def positions_verdict(sp: dict) -> str:
    """Verdict sentence of a run_positions / across_positions result (every stage position and the campaign)."""
    from ct_calib_nodes.core.ct_discrepancy import campaign_sentence  # noqa: PLC0415

    rows = sp["positions"]
    bad = [r for r in rows if not r["adequate"]]
    if not rows:
        text = "No stage position could be judged"
    elif not bad:
        text = f"The nominal model explains every one of the {len(rows)} stage positions judged down to its noise floor"
    else:
        text = (f"The nominal model is inadequate at {len(bad)} of {len(rows)} stage positions: "
                + "; ".join(f"position {r['position'] + 1} (SRD {r['srd_reported_m'] * 1e3:.1f} mm): {r['verdict']}"
                            for r in bad))
    if sp["not_judged"]:
        text += " Not judged: " + "; ".join(f"position {s['position'] + 1} ({s['why']})" for s in sp["not_judged"])
    text = text.rstrip(".") + "."
    return text + campaign_sentence(sp["campaign"])


def positions_status(sp: dict) -> tuple[int, str]:
    """(SolveStatus code, message): SUCCESS when every judged position and the campaign are adequate."""
    if not sp["positions"]:
        return INSUFFICIENT_DATA, "no stage position could be judged"
    if sp["adequate"]:
        return SUCCESS, "model adequate at every stage position"
    where = [f"position {k + 1}" for k in sp["inadequate_positions"]]
    if not sp["campaign"].get("adequate", True):
        where.append("over the campaign")
    return POOR_FIT, "model inadequate (discrepancy engine) " + ", ".join(where)


def positions_msg(sp: dict, stamp, *, campaign_id: str = "", calibration_topic: str = ""):
    """metro_msgs/DiscrepancyReport of every stage position (the error map's data): status, verdict, findings
    named "stage position k: ..." (campaign-long ones "over the campaign: ..."), the median noise floor; the
    single-fit fields (rms, held-out, chi2) are NaN (one fit per position: report_json has them)."""
    from metro_msgs.msg import DiscrepancyFinding  # noqa: PLC0415

    from ct_calib_nodes.core.ct_discrepancy import CATALOGUE_BY_ID  # noqa: PLC0415
    from ct_calib_nodes.io.results import _plain  # noqa: PLC0415

    m = _report(stamp, campaign_id, calibration_topic)
    code, text = positions_status(sp)
    m.verdict = positions_verdict(sp)
    m.status.code, m.status.message = code, (text + ": " + m.verdict)[:4000]
    m.adequate = code == SUCCESS
    nan = float("nan")
    for f in _FIT_FIELDS:
        setattr(m, f, nan)
    floors = [r["noise_floor_px"] for r in sp["positions"]]
    if floors:
        m.noise_floor_u_px = float(sorted(f["u"] for f in floors)[len(floors) // 2])
        m.noise_floor_v_px = float(sorted(f["v"] for f in floors)[len(floors) // 2])
    camp = sp["campaign"]
    m.findings = [_finding_msg(f, "over the campaign: " + f["name"], nan) for f in camp.get("findings", [])]
    for r in sp["positions"]:
        for f in r["findings"]:
            t = CATALOGUE_BY_ID[f["term"]]
            m.findings.append(DiscrepancyFinding(
                term=f["term"], name=f"stage position {r['position'] + 1}: {t.name}", mechanism=t.mechanism,
                significance_sigma=_f(f["significance_sigma"]), delta_bic=nan, cv_gain=nan,
                magnitude=_f(f["magnitude"]), u_magnitude=_f(f["magnitude_u"]), magnitude_unit=f["unit"],
                degenerate_with=list(f["degenerate_with"])))
        for axis in r["unexplained"]:
            m.unexplained_axes.append(f"stage position {r['position'] + 1}: {axis}")
            m.unexplained_sigma.append(nan)
    for u in camp.get("unexplained", []):
        m.unexplained_axes.append(u["axis"])
        m.unexplained_sigma.append(_f(u["significance_sigma"]))
    _add_limits(m, camp.get("detection_limits", {}), prefix="campaign.")
    m.report_json = json.dumps(_plain({"verdict": m.verdict, "adequate": m.adequate, "stage_positions": sp}))
    return m


def positions_record(sp: dict | None, *, cell: str, source: str, campaign_id=None, inputs=(), data_start_ns=None,
                     data_end_ns=None, status: str | None = None, message: str = ""):
    """Calibration-history record of kind 'discrepancy_error_map' (quantities: the campaign-long findings'
    parameters and, per position, the findings' magnitudes with the position index)."""
    from ct_calib_nodes.io.history import Quantity, SolveRecord  # noqa: PLC0415
    from ct_calib_nodes.io.results import _plain  # noqa: PLC0415

    q = []
    if sp is not None:
        code, text = positions_status(sp)
        status = status or {SUCCESS: "success", POOR_FIT: "poor_fit"}.get(code, "insufficient_data")
        message = message or text
        for f in sp["campaign"].get("findings", []):
            for p in f["parameters"]:
                q.append(Quantity(name=f"campaign.{f['term']}.{p['name']}", value=float(p["value"]), u=float(p["u"]),
                                  unit=p["unit"]))
        for r in sp["positions"]:
            for f in r["findings"]:
                q.append(Quantity(name=f"{f['term']}.magnitude", value=float(f["magnitude"]),
                                  u=float(f["magnitude_u"]), unit=f["unit"], position=int(r["position"])))
        result = {"verdict": positions_verdict(sp), "stage_positions": _plain(sp)}
    else:
        result = {"error": message}
    return SolveRecord(cell=cell, kind=KIND_DISCREPANCY_POSITIONS, status=status or "failed", message=message,
                       result=result, source=source, campaign_id=campaign_id, data_start_ns=data_start_ns,
                       data_end_ns=data_end_ns, inputs=list(inputs), quantities=q)
