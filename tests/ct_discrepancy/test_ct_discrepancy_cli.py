"""ct_discrepancy on a recording written by independent software (rosbags), INTERFACES.md only.

A short clean scan (12 frames, one stage position): the command must replay it, write discrepancy.json with the
documented keys and a report that opens with the verdict; a missing recording is a clear error (exit 2).
"""

import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from ct_calib_nodes.core.geometry import DetectorSpec
from ct_calib_nodes.core.phantom import helix49
from ct_calib_nodes.core.render import RenderSettings, render_projection
from ct_calib_nodes.core.scenario import default_static_truth

pytestmark = pytest.mark.ros
ROOT = pathlib.Path(__file__).resolve().parents[2]
DET = DetectorSpec(1024, 1024, 0.0004)
KEYS = {"verdict", "adequate", "noise_floor", "fit_before", "fit_after", "findings", "unexplained",
        "detection_limits", "catalogue"}


def _write(bag_dir, n=12):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    Image, JointState = ts.types["sensor_msgs/msg/Image"], ts.types["sensor_msgs/msg/JointState"]
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    w_true = default_static_truth(0.364, 1.04821)
    rng = np.random.default_rng(8)
    with Writer(bag_dir, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c_js = w.add_connection("/ct/stage/joint_states", "sensor_msgs/msg/JointState", typestore=ts)
        c_img = w.add_connection("/ct/detector/image", "sensor_msgs/msg/Image", typestore=ts)
        for j, a in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False)):
            img = render_projection(w_true, np.zeros(6), a, helix49(), DET, RenderSettings(oversample=2), rng).image
            t = 1_700_000_000_000_000_000 + j * 500_000_000
            stamp = Time(sec=t // 10**9, nanosec=t % 10**9)
            im = Image(header=Header(stamp=stamp, frame_id="det"), height=1024, width=1024, encoding="mono16",
                       is_bigendian=0, step=2048, data=np.asarray(img, "<u2").view(np.uint8).ravel())
            js = JointState(header=Header(stamp=stamp, frame_id=""), name=["rotary", "magnification"],
                            position=np.array([a, 0.364]), velocity=np.zeros(0), effort=np.zeros(0))
            w.write(c_js, t, ts.serialize_cdr(js, "sensor_msgs/msg/JointState"))
            w.write(c_img, t, ts.serialize_cdr(im, "sensor_msgs/msg/Image"))


def _run(*args):
    return subprocess.run([sys.executable, "-m", "ct_calib_nodes.discrepancy_cli", *args], capture_output=True,
                          text=True, timeout=600)


def test_cli_on_a_foreign_recording(tmp_path):
    bag = tmp_path / "scan"
    _write(bag)
    out = tmp_path / "disc"
    res = _run(str(bag), "--out", str(out), "--image-pairs", "2", "--workers", "2")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    d = json.loads((out / "discrepancy.json").read_text())
    assert KEYS <= set(d)
    assert d["noise_floor"]["independent_sd"]["u"] > 0 and d["n_projections"] == 12
    assert set(d["detection_limits"]) == {t["id"] for t in d["catalogue"]}
    report = (out / "report.md").read_text().splitlines()
    assert report[2] == f"**{d['verdict']}**"
    for png in ("residual_vs_angle.png", "residual_vs_time.png", "residual_detector_field.png"):
        assert (out / png).stat().st_size > 1000
    assert "[discrepancy]" in res.stdout                     # progress printed
    # image level: the frames re-read from a recording written by other software, rendered and compared
    img = d["image_level"]
    assert img["performed"], img
    assert img["pairs"] == [[0, 1], [10, 11]] and img["n_shadows"] > 20
    assert 0.3 < img["blur_sigma_px"] < 1.2                  # the renderer's default blur is 0.7 px
    assert all(img["terms"][t]["limit"] > 0 for t in ("scatter_glare", "detector_lag"))
    assert any(line.startswith("## Image level") for line in report)


def test_cli_missing_recording(tmp_path):
    res = _run(str(tmp_path / "nothing_here"))
    assert res.returncode == 2 and "no recording" in res.stderr


def test_cli_on_a_two_turn_reveal_recording(tmp_path):
    """The acquisition that separates the degenerate groups (campaign.ACQUISITIONS["reveal"]: magnification
    4.4-5.8, the object raised 20 mm off the principal ray, two turns of 72 projections), rendered with a hidden
    8 um stage drift and written by other software with the rotary angle wrapped to [0, 2 pi) as a driver may
    publish it: the offline command replays both turns as one scan and names the drift."""
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
    from campaign import ACQUISITIONS, STAMP0_NS, draw_instrument, effect_settings  # noqa: PLC0415
    from ct_foreign_writer import write_ct_recording  # noqa: PLC0415

    acq = ACQUISITIONS["reveal"]
    rng = np.random.default_rng(4310)
    w, srd = draw_instrument(rng, acq["srd_range"])
    n = 72 * acq["turns"]
    kw, term, mag = effect_settings("stage_drift", 1.0, n - 1.0, rng)
    w = w.copy()
    w[8] += acq["raise_m"]
    settings = RenderSettings(**kw)

    def frames():
        for j, a in enumerate(np.linspace(0, 2 * np.pi * acq["turns"], n, endpoint=False)):
            t_s = j - (n - 1) / 2                         # 1 s per frame, time 0 at mid-scan (effect_settings)
            img = render_projection(w, np.zeros(6), a, helix49(), DET, settings, rng, time_s=t_s).image
            yield STAMP0_NS + int(round(t_s * 1e9)), np.asarray(img, np.uint16), a % (2 * np.pi), srd

    bag = tmp_path / "reveal"
    assert write_ct_recording(bag, frames()) == n
    out = tmp_path / "disc"
    res = _run(str(bag), "--out", str(out), "--image-pairs", "0", "--workers", "2")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    d = json.loads((out / "discrepancy.json").read_text())
    assert d["n_projections"] == n and not d["adequate"], d["verdict"]
    top = d["findings"][0]
    # validated at 60 of 63 top-1 on this acquisition (ct_discrepancy.md); otherwise its group must hold the truth
    assert term in {top["term"], *top["degenerate_with"]}, (top["term"], top["degenerate_with"])
    if top["term"] == term:
        assert abs(top["magnitude"] - mag) < 0.15 * mag, (top["magnitude"], mag)
        assert "stage drift" in d["verdict"]
