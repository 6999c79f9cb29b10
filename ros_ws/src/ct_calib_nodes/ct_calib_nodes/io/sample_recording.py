"""Write a small simulated CT recording (rosbag2 directory, MCAP) with its YAML files beside it.

    python -m ct_calib_nodes.io.sample_recording OUT_DIR [--positions 3] [--projections 8]
        [--cols 512] [--pixel-pitch 0.0008] [--seed 1] [--namespace /] [--truth FILE]

The frames are rendered by the simulator's renderer (core/render.py, default physics incl. the
support tube and blur) of the default misaligned instrument and stage errors (core/scenario.py),
published as INTERFACES.md says: ``<ns>/ct/detector/image`` (mono16) and
``<ns>/ct/stage/joint_states`` with identical stamps. ``ct_instrument.yaml`` (the reduced detector)
and ``reference_object.yaml`` are written beside the recording; the truth only to ``--truth``
(tests), never into the recording directory. Used for bags/samples and the archive tests.
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib
import shutil

import numpy as np


def write_sample_recording(out_dir, *, positions: int = 3, projections: int = 8, cols: int = 512,
                           pixel_pitch_m: float = 0.0008, step_m: float = 0.072, seed: int = 1, namespace: str = "/",
                           truth_path=None, start_ns: int = 1_700_000_000_000_000_000, compression: str = "zstd"):
    from sensor_msgs.msg import JointState  # noqa: PLC0415

    from ct_calib_nodes.core.phantom import CarbonTube  # noqa: PLC0415
    from ct_calib_nodes.core.render import RenderSettings, render_projection  # noqa: PLC0415
    from ct_calib_nodes.core.scenario import default_campaign  # noqa: PLC0415
    from ct_calib_nodes.io import ct_files  # noqa: PLC0415
    from ct_calib_nodes.io.convert import image_from_array  # noqa: PLC0415
    from ct_calib_nodes.io.mcap_io import Rosbag2McapWriter  # noqa: PLC0415
    from ct_calib_nodes.io.namespaces import topic  # noqa: PLC0415
    from ct_calib_nodes.io.truth_files import write_truth  # noqa: PLC0415
    from builtin_interfaces.msg import Time  # noqa: PLC0415

    out = pathlib.Path(out_dir)
    if out.exists():
        shutil.rmtree(out)
    inst_default = ct_files.load_instrument(ct_files.default_instrument_path())
    sdd = inst_default.sdd_reported_m
    inst_yaml = {"units": "SI", "source_to_detector": float(sdd),
                 "detector": {"cols": int(cols), "rows": int(cols), "pixel_pitch": float(pixel_pitch_m),
                              "flat_field_counts": float(inst_default.flat_field_counts)}}
    tmp_files = out.parent / (out.name + ".yaml_tmp")
    tmp_files.mkdir(parents=True, exist_ok=True)
    ct_files.write_yaml(tmp_files / "ct_instrument.yaml", inst_yaml)
    instrument = ct_files.load_instrument(tmp_files / "ct_instrument.yaml")
    ref = ct_files.load_reference_object(ct_files.default_reference_object_path())
    ref = dataclasses.replace(ref, tube=CarbonTube(outer_radius_m=0.036, inner_radius_m=0.035, height_m=0.110))
    truth = default_campaign(positions, step_m, 0.364, sdd)
    settings = RenderSettings(flat_field_counts=float(inst_default.flat_field_counts))
    rng = np.random.default_rng(seed)
    alphas = 2 * np.pi * np.arange(projections) / projections
    img_t, js_t = topic(namespace, "ct/detector/image"), topic(namespace, "ct/stage/joint_states")
    with Rosbag2McapWriter(out, compression=compression) as w:
        w.add_topic(js_t, "sensor_msgs/msg/JointState")
        w.add_topic(img_t, "sensor_msgs/msg/Image")
        n = 0
        for k in range(positions):
            for j, a in enumerate(alphas):
                t_ns = start_ns + n * 125_000_000
                stamp = Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
                frame = render_projection(truth.static_w, truth.motions[k], a, ref, instrument.detector, settings, rng,
                                          time_s=n * 0.125)
                js = JointState(name=["rotary", "magnification"], position=[float(a), float(truth.srd_reported_m[k])])
                js.header.stamp = stamp
                js.header.frame_id = "ct_stage"
                w.write(js_t, js, t_ns)
                w.write(img_t, image_from_array(frame.image, stamp, "ct_detector"), t_ns)
                n += 1
    for f in tmp_files.iterdir():
        f.replace(out / f.name)
    tmp_files.rmdir()
    shutil.copy(ct_files.default_reference_object_path(), out / "reference_object.yaml")
    if truth_path:
        write_truth(truth_path, truth, settings, projections)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out")
    ap.add_argument("--positions", type=int, default=3)
    ap.add_argument("--projections", type=int, default=8)
    ap.add_argument("--cols", type=int, default=512)
    ap.add_argument("--pixel-pitch", type=float, default=0.0008)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--namespace", default="/")
    ap.add_argument("--truth")
    a = ap.parse_args(argv)
    out = write_sample_recording(a.out, positions=a.positions, projections=a.projections, cols=a.cols,
                                 pixel_pitch_m=a.pixel_pitch, seed=a.seed, namespace=a.namespace, truth_path=a.truth)
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    print(f"wrote {out} ({size / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
