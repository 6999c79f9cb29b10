"""A CT recording written by software the project has never seen, replayed into the offline solve.

INTERFACES.md fixes the raw-data contract so that recordings from other software replay unchanged.
Here the recording is written by an independent implementation (the `rosbags` package: its own
type store, its own CDR serializer, its own MCAP writer, rosbag2 directory layout) with choices the
project's own writer never makes: 32FC1 transmission frames with a padded row step, a different
frame_id, best-effort QoS metadata, stage readings written before some frames and after others,
unrelated topics in the same file, and YAML files with other key order, flow style and the
optional keys. The frames are rendered with known truth; the solve must recover it.
"""

import json
import pathlib
import subprocess

import numpy as np
import pytest
import yaml

from ct_calib_nodes.core.geometry import DetectorSpec
from ct_calib_nodes.core.phantom import CarbonTube, helix49
from ct_calib_nodes.core.render import RenderSettings, render_projection
from ct_calib_nodes.core.scenario import default_campaign

from ct_foreign_writer import write_ct_recording

pytestmark = pytest.mark.ros
ROOT = pathlib.Path(__file__).resolve().parents[2]
BIN = ROOT / "ros_ws" / "install" / "ct_calib_nodes" / "lib" / "ct_calib_nodes"
N_POS, N_PROJ = 3, 12
SDD = 1.04821
DET = DetectorSpec(1024, 1024, 0.0004)


def _write_foreign_recording(bag_dir: pathlib.Path, camp):
    ref = helix49()                                   # spheres + the carbon-fibre tube
    assert isinstance(ref.tube, CarbonTube)
    rng = np.random.default_rng(404)
    settings = RenderSettings()
    alphas = np.linspace(0.0, 2 * np.pi, N_PROJ, endpoint=False) + 0.05
    t0 = 1_700_000_000_000_000_000

    def frames():
        for k in range(N_POS):
            for j, a in enumerate(alphas):
                fr = render_projection(camp.static_w, camp.motions[k], a, ref, DET, settings, rng,
                                       output="transmission")
                yield (t0 + (k * N_PROJ + j) * 250_000_000, np.asarray(fr.image, dtype=np.float32), a,
                       camp.srd_reported_m[k])

    # 64 bytes of padding at the end of every row, another frame_id, an unrelated topic, images logged
    # 1 ms after their stamp and every third stage reading logged after its frame
    write_ct_recording(bag_dir, frames(), frame_id="xray_panel_2", row_pad_bytes=64, log_topic=True,
                       stage_late_every=3, image_delay_ns=1_000_000)


def _write_foreign_yaml(bag_dir: pathlib.Path, ref):
    inst = {"detector": {"pixel_pitch": 0.0004, "rows": 1024, "cols": 1024, "flat_field_counts": 50000},
            "source_to_detector": SDD, "units": "SI", "vendor_note": "written by another program"}
    (bag_dir / "ct_instrument.yaml").write_text(yaml.safe_dump(inst, default_flow_style=True))
    spheres = [{"diameter": float(d), "center": [float(v) for v in c], "id": int(i), "center_uncertainty": 5e-7}
               for i, c, d in zip(ref.ids, ref.centres_of_m, ref.diameters_m)]
    obj = {"units": "SI", "frame": "object", "spheres": spheres, "temperature": 293.15, "name": "helix49 (CMM 2026)",
           "sphere_material": "steel"}
    (bag_dir / "reference_object.yaml").write_text(yaml.safe_dump(obj, sort_keys=True))


def test_foreign_recording_replays_and_recovers_truth(tmp_path):
    camp = default_campaign(N_POS, 0.072, 0.364, SDD)
    bag = tmp_path / "foreign_ct_run"
    _write_foreign_recording(bag, camp)
    _write_foreign_yaml(bag, helix49())
    out = tmp_path / "solved"
    res = subprocess.run([str(BIN / "ct_offline_solve"), str(bag), "--out", str(out)],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert "found beside the recording" in res.stdout
    r = json.loads((out / "results.json").read_text())
    assert r["counts"]["frames"] == N_POS * N_PROJ and not r["problems"], (r["counts"], r["problems"])
    # static geometry: every parameter within 4.5 of its own reported sd of the truth
    assert r["static"]["success"], r["static"]["message"]
    x = np.asarray(r["static"]["x"])
    sd = np.asarray(r["static"]["std"])
    z = (x[:13] - camp.static_w) / sd[:13]
    assert np.all(np.abs(z) < 4.5), dict(zip(r["static"]["names"], np.round(z, 2)))
    # error map (multi): within the tolerances and explained by the reported uncertainty
    for definition in ("travel", "detector"):
        truth = camp.error_map(definition)
        em = r["error_maps"]["multi"][definition]
        assert em["positions"] == list(range(N_POS)) and em["definition"] == definition
        for key, tol, scale in (("positioning_m", 10e-6, 1.0), ("straightness_x_m", 3e-6, 1.0),
                                ("straightness_y_m", 3e-6, 1.0), ("pitch_rad", 3.0, 206264.8),
                                ("yaw_rad", 5.0, 206264.8), ("roll_rad", 3.0, 206264.8)):
            err = (np.asarray(em[key]) - truth[key]) * scale
            u = np.asarray(em["u_" + key]) * scale
            assert np.max(np.abs(err)) < tol, (definition, key, err)
            assert np.all(np.abs(err[1:]) < 4.5 * u[1:] + 1e-3 * tol), (definition, key, err, u)
