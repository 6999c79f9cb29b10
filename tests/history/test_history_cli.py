"""ct_history: list, show, compare, export (CSV/JSON), trend with change flags and plots."""
import csv
import json
import types

import numpy as np
import pytest

from ct_calib_nodes.core.error_map import ErrorMap
from ct_calib_nodes.core.geometry import STATIC_PARAM_NAMES, STATIC_PARAM_UNITS
from ct_calib_nodes.history_cli import main
from ct_calib_nodes.io.ct_history import error_map_record, geometry_record, status_word
from ct_calib_nodes.io.history import History

U_ZR = 2e-6


def _static(z_r, outcome="success"):
    x = np.zeros(13)
    x[0], x[3] = z_r, 1.0
    std = np.full(13, 1e-6)
    std[0] = U_ZR
    return types.SimpleNamespace(names=STATIC_PARAM_NAMES, units=STATIC_PARAM_UNITS, x=x, std=std, rms_px=0.05,
                                 message=outcome, success=outcome == "success", outcome=outcome,
                                 to_dict=lambda: {"x": x, "std": std})


def _map(pos_um):
    k = len(pos_um)
    z = np.zeros(k)
    u = np.full(k, 0.5e-6)
    u[0] = 0.0
    return ErrorMap(name="multi", definition="travel", srd_reported_m=0.364 + 0.02 * np.arange(k),
                    positioning_m=np.asarray(pos_um) * 1e-6, straightness_x_m=z, straightness_y_m=z,
                    pitch_rad=z, yaw_rad=z, roll_rad=z, u_positioning_m=u, u_straightness_x_m=u,
                    u_straightness_y_m=u, u_pitch_rad=u, u_yaw_rad=u, u_roll_rad=u)


@pytest.fixture
def db(tmp_path):
    path = tmp_path / "h.sqlite"
    # z_R wanders by 0.3 u between solves, then steps by 10 u at the 4th valid solve; one failed solve with a
    # wild value in between must neither be flagged nor shift the trend
    z = [0.4, 0.4 + 0.3 * U_ZR, 0.4, None, 0.4 + 10 * U_ZR, 0.4 + 10.3 * U_ZR]
    with History(path) as h:
        for i, zr in enumerate(z):
            res = _static(0.9, "poor_fit") if zr is None else _static(zr)
            h.record(geometry_record(res, cell="/cell_a", source="offline", campaign_id=f"c{i}"))
            h.record(error_map_record(_map([0, 1.0, 2.0 + (3.0 if i >= 5 else 0.0)]), "multi", status="success",
                                      message="", cell="/cell_a", source="offline", campaign_id=f"c{i}"))
        h.record(geometry_record(_static(0.5), cell="/cell_b", source="live"))
    return path


def test_status_word_one_vocabulary():
    assert status_word(_static(0.4)) == "success"
    assert status_word(_static(0.4, "poor_fit")) == "poor_fit"


def test_list_show_compare(db, capsys):
    assert main(["--db", str(db), "list", "--cell", "/cell_a", "--kind", "ct_geometry"]) == 0
    out = capsys.readouterr().out
    assert "6 solve(s)" in out and "poor_fit" in out
    assert main(["--db", str(db), "show", "1"]) == 0
    assert "z_R = 400 mm  u = 2 um" in capsys.readouterr().out
    # solve ids: geometry at 1, 3, 5, 7 (failed), 9, 11
    assert main(["--db", str(db), "compare", "1", "3"]) == 0
    out = capsys.readouterr().out
    assert "0 of 14 quantities changed" in out
    assert main(["--db", str(db), "compare", "3", "9"]) == 0
    out = capsys.readouterr().out
    assert "1 of 14 quantities changed" in out and [ln for ln in out.splitlines() if "CHANGED" in ln][0].startswith("z_R")
    assert main(["--db", str(db), "compare", "1", "2"]) == 2     # geometry vs error map


def test_export_csv_json(db, tmp_path):
    assert main(["--db", str(db), "export", "--format", "csv", "--out", str(tmp_path / "h.csv"),
                 "--cell", "/cell_a", "--kind", "ct_geometry", "--status", "success"]) == 0
    rows = list(csv.DictReader(open(tmp_path / "h.csv")))
    zr = [float(r["value"]) for r in rows if r["quantity"] == "z_R"]
    assert zr == pytest.approx([0.4, 0.4 + 0.3 * U_ZR, 0.4, 0.4 + 10 * U_ZR, 0.4 + 10.3 * U_ZR], abs=1e-15)
    assert {float(r["u"]) for r in rows if r["quantity"] == "z_R"} == {U_ZR}
    assert main(["--db", str(db), "export", "--format", "json", "--full", "--out", str(tmp_path / "h.json")]) == 0
    d = json.load(open(tmp_path / "h.json"))
    assert len(d["solves"]) == 13 and d["solves"][0]["result"]["static"]["x"][0] == 0.4


def test_trend_flags_steps_beyond_uncertainty_and_plots(db, tmp_path, capsys):
    assert main(["--db", str(db), "trend", "--cell", "/cell_a", "--plot", str(tmp_path / "plots")]) == 0
    out = capsys.readouterr().out
    flagged = [ln for ln in out.splitlines() if "CHANGED" in ln]
    # z_R: the 10 u step (solve 9); positioning at position 2: the 3 um step (6 u) at solve 12; nothing else
    assert len(flagged) == 2, out
    assert flagged[0].split()[1] == "z_R" and "CHANGED at solve 9" in flagged[0]
    assert "positioning_m[2]" in flagged[1] and "CHANGED at solve 12" in flagged[1]
    assert "2 change(s)" in out
    for f in ("trend_ct_geometry.png", "trend_ct_error_map.png"):
        assert (tmp_path / "plots" / f).stat().st_size > 10_000


def test_missing_database_is_a_clear_error(tmp_path, capsys):
    assert main(["--db", str(tmp_path / "none.sqlite"), "list"]) == 2
    assert "no history database" in capsys.readouterr().err
