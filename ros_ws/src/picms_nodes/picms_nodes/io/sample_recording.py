"""Write a small simulated Pixel Probe calibration recording (rosbag2 directory, MCAP, zstd) with its
``picms_cell.yaml`` beside it.

    python -m picms_nodes.io.sample_recording OUT_DIR [--seed 8] [--window-margin 36] [--binning 2]
        [--namespace /] [--truth FILE]

A full calibration session of the simulated cell (core/campaign.simulate_session: the Appendix A
pattern, one settled frame per camera and station, a frame mid-move, tracker round-robin at 60
readings/s, joint_states at 50 Hz) whose frames are cut to a **reduced sensor window**: per camera
the smallest window (plus a margin) holding the SMR* disc in every frame, found from the rendered
images themselves (dark pixels). The window is what a camera's ROI readout gives: CameraInfo carries
it as the sensor (``width``, ``height``) and K with the principal point moved by the window offset,
so every pixel keeps its ray (plumb_bob distortion is about the principal point, so it is
unchanged). mono8 frames, zstd chunks: a few MB instead of ~120 MB of full 5 MP frames.

Topics per INTERFACES.md (PiCMS), in ``--namespace`` (default the root). The truth (X* image in
the window, camera poses) only goes to ``--truth``, never into the recording directory.
"""
from __future__ import annotations

import argparse
import pathlib
import shutil

import numpy as np


def _window(images, margin: int, shape):
    """(x0, y0, x1, y1) holding every dark (disc) pixel of the images, plus margin; even offsets."""
    lo = np.array([shape[1], shape[0]])
    hi = np.array([0, 0])
    for img in images:
        thr = 0.5 * (float(np.percentile(img, 1)) + float(np.percentile(img, 99)))
        ys, xs = np.nonzero(img < thr)
        if xs.size:
            lo = np.minimum(lo, [xs.min(), ys.min()])
            hi = np.maximum(hi, [xs.max(), ys.max()])
    x0, y0 = (np.maximum(lo - margin, 0) // 2 * 2).tolist()
    x1, y1 = np.minimum(hi + margin + 1, [shape[1], shape[0]]).tolist()
    return int(x0), int(y0), int(x1), int(y1)


def write_picms_sample(out_dir, *, seed: int = 8, window_margin: int = 36, namespace: str = "/", binning: int = 2,
                       truth_path=None, start_ns: int = 1_760_000_000_000_000_000, compression: str = "zstd",
                       step_xy_m: float = 0.006, step_z_m: float = 0.004):
    from builtin_interfaces.msg import Time  # noqa: PLC0415
    from geometry_msgs.msg import PointStamped  # noqa: PLC0415
    from sensor_msgs.msg import CameraInfo, Image, JointState  # noqa: PLC0415

    import yaml  # noqa: PLC0415

    from ct_calib_nodes.io.mcap_io import Rosbag2McapWriter  # noqa: PLC0415
    from ct_calib_nodes.io.namespaces import topic  # noqa: PLC0415

    from ..core import campaign, cell  # noqa: PLC0415
    from ..core.camera import Intrinsics  # noqa: PLC0415

    out = pathlib.Path(out_dir)
    if out.exists():
        shutil.rmtree(out)
    rng = np.random.default_rng(seed)
    # a coarser sensor of the same field of view (pixels `binning` times larger, rendered natively)
    phys0 = cell.Physics()
    truth = cell.cell_from_seed(seed, pixel_m=phys0.pixel_m * binning, width=phys0.width // binning,
                                height=phys0.height // binning)
    rec, st = campaign.simulate_session(truth, rng, mid_move_frames=1,
                                        pattern=campaign.appendix_a_pattern(step_xy_m, step_z_m))

    def stamp(t):
        t = int(t) + start_ns
        return Time(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000)

    windows = {}
    for cam in rec.camera_info:
        imgs = [img for _, c, img in rec.frames if c == cam]
        windows[cam] = _window(imgs, window_margin, imgs[0].shape)
    tmp_parent = out.parent / (".tmp_" + out.name)       # written here, then moved: never a partial sample
    if tmp_parent.exists():
        shutil.rmtree(tmp_parent)
    tmp_parent.mkdir(parents=True)
    tmp = tmp_parent / out.name
    events = []
    for t, q in zip(rec.joint_stamps_ns.tolist(), rec.joint_positions):
        m = JointState(name=["x", "y", "z"], position=[float(v) for v in q])
        m.header.stamp, m.header.frame_id = stamp(t), "stage"
        events.append((t, "picms/stage/joint_states", m))
    for t, name, p in rec.tracker:
        m = PointStamped()
        m.header.stamp, m.header.frame_id = stamp(t), "tracker"
        m.point.x, m.point.y, m.point.z = (float(v) for v in p)
        events.append((t, f"picms/tracker/smr/{name}", m))
    infos = {}
    for cam, intr in rec.camera_info.items():
        x0, y0, x1, y1 = windows[cam]
        K = np.array(intr.K, float).copy()
        K[0, 2] -= x0
        K[1, 2] -= y0
        infos[cam] = Intrinsics(K, np.array(intr.D, float), x1 - x0, y1 - y0)
        m = CameraInfo(width=x1 - x0, height=y1 - y0, distortion_model="plumb_bob")
        m.header.stamp, m.header.frame_id = stamp(0), f"{cam}_optical"
        m.d = [float(v) for v in intr.D]
        m.k = [float(v) for v in K.ravel()]
        m.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        m.p = [float(v) for v in np.column_stack([K, np.zeros(3)]).ravel()]
        events.append((0, f"picms/{cam}/camera_info", m))
    for t, cam, img in rec.frames:
        x0, y0, x1, y1 = windows[cam]
        w = np.ascontiguousarray(img[y0:y1, x0:x1])
        m = Image(height=w.shape[0], width=w.shape[1], encoding="mono8", is_bigendian=0, step=w.shape[1])
        m.header.stamp, m.header.frame_id = stamp(t), f"{cam}_optical"
        m.data = w.tobytes()
        events.append((t, f"picms/{cam}/image_raw", m))
    events.sort(key=lambda e: e[0])
    with Rosbag2McapWriter(tmp, compression=compression) as wr:
        for t, rel, m in events:
            wr.write(topic(namespace, rel), m, start_ns + t)
    tmp.mkdir(exist_ok=True)
    (tmp / "picms_cell.yaml").write_text(
        "# Pixel Probe cell (INTERFACES.md, PiCMS): written with the sample recording\n"
        + yaml.safe_dump(rec.cell, sort_keys=False))
    tmp.replace(out)
    tmp_parent.rmdir()
    if truth_path is not None:
        from ..core.camera import project  # noqa: PLC0415
        tr = {"seed": int(seed), "units": "SI; pixels in the recorded (windowed) sensor",
              "probe_point_pixels": {}, "windows": {c: list(w) for c, w in windows.items()},
              "cameras": {}, "p_tracker_stage": truth.p_tracker_stage.tolist(),
              "p_tracker_x_star": truth.to_tracker(truth.probe_point_stage(st.station_q_true[0]))[0].tolist()}
        for j, c in enumerate(truth.cameras):
            x0, y0 = windows[c.name][:2]
            Kt = np.array(c.true_intrinsics.K, float).copy()
            Kt[0, 2] -= x0
            Kt[1, 2] -= y0
            intr_w = Intrinsics(Kt, np.array(c.true_intrinsics.D, float), windows[c.name][2] - x0,
                                windows[c.name][3] - y0)
            tr["probe_point_pixels"][c.name] = project(c.pose, intr_w, truth.smr_star_stage)[0].tolist()
            tr["cameras"][c.name] = {"R_stage_camera": np.asarray(c.pose.R_stage_camera).tolist(),
                                     "p_stage_centre": np.asarray(c.pose.p_stage_centre).tolist()}
        pathlib.Path(truth_path).write_text(yaml.safe_dump(tr, sort_keys=False))
    return out, windows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir")
    ap.add_argument("--seed", type=int, default=8)
    ap.add_argument("--window-margin", type=int, default=36, help="pixels around the disc extent (detection needs 0.15 R + 10) [px]")
    ap.add_argument("--namespace", default="/")
    ap.add_argument("--binning", type=int, default=2, help="pixel size factor of the simulated sensor (same field "
                                                           "of view; 1 = the 5 MP camera)")
    ap.add_argument("--truth", help="write the simulator's truth here (outside the recording)")
    a = ap.parse_args(argv)
    out, windows = write_picms_sample(a.out_dir, seed=a.seed, window_margin=a.window_margin, namespace=a.namespace,
                                      truth_path=a.truth, binning=a.binning)
    size = sum(f.stat().st_size for f in pathlib.Path(out).rglob("*") if f.is_file())
    print(f"{out}: {size / 1e6:.2f} MB; windows {windows}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
