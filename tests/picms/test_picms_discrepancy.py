"""Pixel Probe discrepancy engine (issue 11): clean controls, a hidden effect, the offline command."""
import importlib.util
import json
import pathlib

import numpy as np
import pytest

from picms_nodes import discrepancy_cli
from picms_nodes.core import campaign, cell, pipeline
from picms_nodes.core import picms_discrepancy as pd
from picms_nodes.core.camera import Intrinsics

KEYS = {"verdict", "adequate", "noise_floor", "fit_before", "fit_after", "findings", "unexplained",
        "detection_limits", "catalogue"}


def test_catalogue_documented_and_complete():
    assert len(pd.CATALOGUE) >= 8 and len({t.id for t in pd.CATALOGUE}) == len(pd.CATALOGUE)
    doc = (pathlib.Path(pd.__file__).parents[2] / "doc" / "picms_discrepancy.md")
    text = doc.read_text() if doc.exists() else ""
    for t in pd.CATALOGUE:
        assert len(t.per_camera) == len(t.units)
        assert f"`{t.id}`" in text, f"{t.id} not documented in {doc}"


def test_appendix_a_sessions_too_small_for_a_verdict(sessions):
    # 7 stations: 6 pose parameters per camera leave too few degrees of freedom for a data-driven
    # floor and held-out folds (on clean data the engine would see spurious 'time' structure)
    rec, _st, res, _ = sessions[0]
    with pytest.raises(ValueError, match="too few for a discrepancy verdict"):
        pd.run(res, rec.camera_info)


def _bag_writer():
    p = pathlib.Path(__file__).with_name("test_picms_foreign_recording.py")
    spec = importlib.util.spec_from_file_location("_picms_foreign", p)
    m = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(m)
    return m._write


def test_offline_command_refuses_small_recording_and_bad_path(tmp_path, sessions, capsys):
    rec, *_ = sessions[0]
    bag = tmp_path / "bag"
    _bag_writer()(bag, rec)
    import yaml
    (tmp_path / "picms_cell.yaml").write_text(yaml.safe_dump({"stage": rec.cell["stage"], "tracker": rec.cell["tracker"]}))
    out = tmp_path / "disc"
    assert discrepancy_cli.main([str(bag), "--cell", str(tmp_path / "picms_cell.yaml"), "--out", str(out)]) == 1
    assert "too few for a discrepancy verdict" in capsys.readouterr().err
    assert not (out / "discrepancy.json").exists()
    assert discrepancy_cli.main([str(tmp_path / "missing"), "--out", str(out)]) == 2


@pytest.fixture(scope="module")
def grid_session():
    # one cell rendered once on the grid acquisition (~15 s)
    rng = np.random.default_rng(31)
    # a rigid stage: the simulator's stage error motions (on by default since round 18) are not in
    # the calibration model nor in the engine's catalogue, and on this grid the engine names them
    # as a pixel aspect-ratio error (9e-5 at 15 sigma): a clean control here means only modelled
    # physics. Stage terms for the catalogue are future work (see picms_discrepancy.md).
    truth = cell.make_cell(rng, cell.make_physics(rng, distortion_k1=-0.3, stage_error_motions=False))
    rec, _ = campaign.simulate_session(truth, rng, pattern=pd.grid_pattern(), dwell_s=1.2, mid_move_frames=0)
    return truth, rec


@pytest.mark.slow
def test_grid_clean_adequate_and_command_output(tmp_path, grid_session):
    truth, rec = grid_session
    res, _ = pipeline.calibrate_recording(rec)
    out = pd.run(res, rec.camera_info)
    assert out["adequate"], out["verdict"]
    assert out["verdict"].startswith("No significant discrepancy")
    f = out["noise_floor"]["factor_of_stated_sigma"]
    assert 0.4 < f["u"] < 2.5 and 0.4 < f["v"] < 2.5
    assert out["detection_limits"]["principal_point_error"]["limit"] is None or \
        out["detection_limits"]["principal_point_error"]["limit"] > 0
    bag = tmp_path / "bag"
    _bag_writer()(bag, rec)
    import yaml
    (tmp_path / "picms_cell.yaml").write_text(yaml.safe_dump({"stage": rec.cell["stage"], "tracker": rec.cell["tracker"]}))
    dest = tmp_path / "disc"
    assert discrepancy_cli.main([str(bag), "--cell", str(tmp_path / "picms_cell.yaml"), "--out", str(dest)]) == 0
    d = json.loads((dest / "discrepancy.json").read_text())
    assert set(d) >= KEYS and d["adequate"]
    assert (dest / "report.md").read_text().splitlines()[0] == d["verdict"]
    assert (dest / "residuals.png").stat().st_size > 1000


@pytest.mark.slow
def test_hidden_lens_distortion_named_and_measured(grid_session):
    # the same rendering; CameraInfo with D = 0 hides a k1 ~ -0.3 lens
    truth, rec = grid_session
    rec = __import__("copy").copy(rec)
    rec.camera_info = {k: Intrinsics(v.K, np.zeros(5), v.width, v.height) for k, v in rec.camera_info.items()}
    res, _ = pipeline.calibrate_recording(rec)
    out = pd.run(res, rec.camera_info)
    assert not out["adequate"]
    f0 = out["findings"][0]
    assert f0["term"] == "lens_radial_k1"
    k1_true = np.array([c.true_intrinsics.D[0] for c in truth.cameras])
    est = np.array([p["value"] for p in f0["parameters"]])
    u = np.array([p["u"] for p in f0["parameters"]])
    # magnitude within 15 %; each camera's k1 within 4 u of the truth (with the floor's scale)
    assert abs(f0["magnitude"] - np.sqrt(np.mean(k1_true ** 2))) < 0.15 * np.sqrt(np.mean(k1_true ** 2))
    assert np.all(np.abs(est - k1_true) < 4 * u + 0.05 * np.abs(k1_true))
    assert out["fit_after"]["held_out_rms"] < 0.75 * out["fit_before"]["held_out_rms"]
