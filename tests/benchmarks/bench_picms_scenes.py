"""Rendering time per 5 MP frame of each Pixel Probe scene, side by side in one run: the SMR*
in its nest (the calibration scene), chrome-on-glass targets (bright field) and the flange face
(dark field), at two part poses, against the floor of full-frame shot/read noise alone
(what any frame costs). Ends with ONE JSON line (median seconds per frame, warm).

Usage: python tests/benchmarks/bench_picms_scenes.py [frames_per_case]
"""
import json
import sys
import time

import numpy as np

from picms_nodes.core import cell, render, scenes


def main():
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 3
    c = cell.make_cell(np.random.default_rng(7))
    rng = np.random.default_rng(1)
    poses = [((0.0, 0.0, 0.0), (0.0, 0.0), 0.0), ((0.0012, -0.0008, 0.0006), (0.04, -0.03), 0.4)]
    times = {"noise_only": [], "smr": [], "chrome_targets": [], "flange": []}
    for cam in c.cameras:
        render.render_frame(cam.pose, cam.true_intrinsics, c.physics, rng, sphere_stage=c.smr_star_stage)  # warm
        for _ in range(n):
            t0 = time.perf_counter()
            img = rng.standard_normal((c.physics.height, c.physics.width), dtype=np.float32)
            img *= 2.0
            img += 100.5
            np.clip(img, 0, 255.49, out=img).astype(np.uint8)
            times["noise_only"].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            render.render_frame(cam.pose, cam.true_intrinsics, c.physics, rng, sphere_stage=c.smr_star_stage)
            times["smr"].append(time.perf_counter() - t0)
            for name in ("chrome_targets", "flange"):
                for pose in poses:
                    part = scenes.make_part(name, *pose)
                    t0 = time.perf_counter()
                    render.render_frame(cam.pose, cam.true_intrinsics, c.physics, rng, part=part)
                    times[name].append(time.perf_counter() - t0)
    out = {k + "_s": round(float(np.median(v)), 3) for k, v in times.items()}
    out["frames"] = {k: len(v) for k, v in times.items()}
    out["note"] = "2 shared cores, loaded machine: compare ratios within this line"
    print(json.dumps(out))


if __name__ == "__main__":
    main()
