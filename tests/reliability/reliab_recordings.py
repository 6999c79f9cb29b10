"""Small CT recordings for the reliability tests and benchmarks (written in a temporary folder).

``synthetic_recording``: random 64x64 frames and stage readings, many small chunks; fast, for
reader tests (nothing is solved from it). ``ct_recording``: a short rendered CT campaign that
ct_offline_solve solves (reduced detector, few spheres, few frames), with its YAML files beside it.
"""

from __future__ import annotations

import pathlib

import numpy as np

T0_NS = 1_700_000_000_000_000_000
IMAGE, STAGE = "/ct/detector/image", "/ct/stage/joint_states"


def _stamp(t):
    from builtin_interfaces.msg import Time

    return Time(sec=int(t) // 10**9, nanosec=int(t) % 10**9)


def synthetic_recording(path, n_frames=30, shape=(64, 64), chunk_size=16 * 1024, compression="zstd", seed=0):
    """Frames i = 0..n-1 (pixel [0, 0] holds i) and stage readings (rotary = 0.1 i), paired by stamp
    T0_NS + i * 0.1 s. Returns the path."""
    from sensor_msgs.msg import JointState

    from ct_calib_nodes.io.convert import image_from_array
    from ct_calib_nodes.io.mcap_io import Rosbag2McapWriter

    rng = np.random.default_rng(seed)
    with Rosbag2McapWriter(path, compression=compression, chunk_size=chunk_size) as w:
        for i in range(n_frames):
            t = T0_NS + i * 100_000_000
            img = rng.integers(0, 60000, shape).astype(np.uint16)   # incompressible
            img[0, 0] = i
            w.write(IMAGE, image_from_array(img, _stamp(t), "ct_detector"), t)
            js = JointState(name=["rotary", "magnification"], position=[0.1 * i, 0.364])
            js.header.stamp = _stamp(t)
            w.write(STAGE, js, t + 1)
    return pathlib.Path(path)


def small_reference_object(n=8, diameter_m=0.006):
    from ct_calib_nodes.core.phantom import ReferenceObject, multi_helix_centres

    return ReferenceObject(name=f"reliab{n}", ids=np.arange(1, n + 1),
                           centres_of_m=multi_helix_centres(n, 0.0375, -0.04, 0.04, 3.07),
                           diameters_m=np.full(n, diameter_m), material="steel", center_uncertainty_m=1e-6,
                           temperature_K=293.15)


def ct_recording(folder, n_positions=2, n_proj=5, det_px=128, pitch_m=0.0032, n_spheres=8, seed=1,
                 chunk_size=48 * 1024, step_m=0.05, messages=None):
    """A short rendered campaign, solvable by ct_offline_solve: ``folder/rec.mcap`` with
    ``ct_instrument.yaml`` and ``reference_object.yaml`` beside it. Returns the .mcap path;
    ``messages`` (a list) receives (topic, type name, message, log time) of what was written."""
    messages = [] if messages is None else messages
    from sensor_msgs.msg import JointState

    from ct_calib_nodes.core.geometry import DetectorSpec
    from ct_calib_nodes.core.render import RenderSettings, render_projection
    from ct_calib_nodes.core.scenario import default_campaign
    from ct_calib_nodes.io import ct_files
    from ct_calib_nodes.io.convert import image_from_array
    from ct_calib_nodes.io.mcap_io import Rosbag2McapWriter

    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    det = DetectorSpec(det_px, det_px, pitch_m)
    camp = default_campaign(n_positions, step_m)
    ref = small_reference_object(n_spheres)
    rng = np.random.default_rng(seed)
    path = folder / "rec.mcap"
    i = 0
    with Rosbag2McapWriter(path, chunk_size=chunk_size) as w:
        for k in range(n_positions):
            for a in np.linspace(0, 2 * np.pi, n_proj, endpoint=False) + 0.1:
                fr = render_projection(camp.static_w, camp.motions[k], a, ref, det, RenderSettings(oversample=2), rng)
                t = T0_NS + i * 100_000_000
                i += 1
                img = image_from_array(fr.image, _stamp(t), "ct_detector")
                w.write(IMAGE, img, t)
                js = JointState(name=["rotary", "magnification"], position=[float(a), float(camp.srd_reported_m[k])])
                js.header.stamp = _stamp(t)
                w.write(STAGE, js, t + 1)
                messages += [(IMAGE, "sensor_msgs/msg/Image", img, t), (STAGE, "sensor_msgs/msg/JointState", js, t + 1)]
    ct_files.write_yaml(folder / "ct_instrument.yaml",
                        {"units": "SI", "source_to_detector": float(camp.sdd_reported_m),
                         "detector": {"cols": det_px, "rows": det_px, "pixel_pitch": pitch_m,
                                      "flat_field_counts": 50000}})
    ct_files.write_yaml(folder / "reference_object.yaml", ref.to_yaml_dict())
    return path


def record_offsets(path):
    """(offset, opcode, length) of every top-level record of an MCAP file (an intact one)."""
    from reliab_fuzz import record_offsets_of  # noqa: PLC0415

    return record_offsets_of(pathlib.Path(path).read_bytes())


def picms_recording(folder, seed=3, width=480, height=360, tracker_rate_hz=15.0, joint_rate_hz=8.0,
                    chunk_size=48 * 1024, messages=None, truth_out=None):
    """A short simulated Pixel Probe session, calibratable by picms_calibrate_offline: the Appendix A
    stations (one settled frame of each camera per station, reduced sensor of the same field of view),
    CameraInfo, stage joint_states and tracker readings as INTERFACES.md gives them:
    ``folder/rec.mcap`` with ``picms_cell.yaml`` beside it. Returns the .mcap path; ``messages``
    receives (topic, type name, message, log time) of what was written."""
    messages = [] if messages is None else messages
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import Image, JointState

    from ct_calib_nodes.io import ct_files
    from ct_calib_nodes.io.mcap_io import Rosbag2McapWriter
    from picms_nodes.core import campaign, cell
    from picms_nodes.nodes.picms_camera_sim import camera_info_msg

    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    scale = 2592 / width            # same field of view, fewer (larger) pixels
    truth = cell.make_cell(rng, cell.make_physics(rng, width=width, height=height, pixel_m=2.2e-6 * scale,
                                                  psf_sigma_px=float(rng.uniform(0.5, 1.0))))
    rec, st = campaign.simulate_session(truth, rng, frames_per_station=1, mid_move_frames=0,
                                        tracker_rate_hz=tracker_rate_hz, joint_rate_hz=joint_rate_hz)
    if truth_out is not None:
        truth_out.append((rec, st))
    ev = []
    for t, q in zip(rec.joint_stamps_ns.tolist(), rec.joint_positions):
        js = JointState(name=["x", "y", "z"], position=[float(v) for v in q])
        js.header.stamp = _stamp(T0_NS + t)
        ev.append(("/picms/stage/joint_states", "sensor_msgs/msg/JointState", js, T0_NS + t))
    for t, name, p in rec.tracker:
        m = PointStamped()
        m.header.stamp, m.header.frame_id = _stamp(T0_NS + t), "tracker"
        m.point.x, m.point.y, m.point.z = (float(v) for v in p)
        ev.append((f"/picms/tracker/smr/{name}", "geometry_msgs/msg/PointStamped", m, T0_NS + t + 1))
    for t, cam, img in rec.frames:
        m = Image(height=img.shape[0], width=img.shape[1], encoding="mono8", is_bigendian=0, step=img.shape[1],
                  data=img.tobytes())
        m.header.stamp, m.header.frame_id = _stamp(T0_NS + t), f"{cam}_optical"
        ev.append((f"/picms/{cam}/camera_info", "sensor_msgs/msg/CameraInfo",
                   camera_info_msg(rec.camera_info[cam], _stamp(T0_NS + t), f"{cam}_optical"), T0_NS + t + 2))
        ev.append((f"/picms/{cam}/image_raw", "sensor_msgs/msg/Image", m, T0_NS + t + 3))
    ev.sort(key=lambda e: e[3])
    path = folder / "rec.mcap"
    with Rosbag2McapWriter(path, chunk_size=chunk_size) as w:
        for topic, typ, msg, t in ev:
            w.write(topic, msg, t)
            messages.append((topic, typ, msg, t))
    ct_files.write_yaml(folder / "picms_cell.yaml", rec.cell)
    return path
