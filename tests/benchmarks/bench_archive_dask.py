"""Archive re-solve throughput: sequential vs a Dask LocalCluster of 1 and 2 worker processes, on the
same N small simulated recordings (2 positions x 6 projections, 384 x 384 mono16), in one run so the
machine's load affects all alike. Ends with one JSON line.

    python tests/benchmarks/bench_archive_dask.py [N]
"""
import json
import os
import sys
import tempfile
import time
import pathlib

from distributed import Client, LocalCluster

from ct_calib_nodes.archive import find_recordings, run
from ct_calib_nodes.io.sample_recording import write_sample_recording


def main():
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 4
    with tempfile.TemporaryDirectory() as tmp:
        root = pathlib.Path(tmp) / "archive"
        root.mkdir()
        for seed in range(n):
            write_sample_recording(root / f"rec_{seed}", positions=2, projections=6, cols=384, pixel_pitch_m=0.00107,
                                   seed=seed + 1)
        paths = find_recordings(root)
        fig = {"recordings": n, "frames_per_recording": 12, "cpu_count": os.cpu_count(),
               "note": "2-core machine shared with other jobs: wall times include their load"}
        t0 = time.perf_counter()
        seq = run(paths, workers=1)
        fig["sequential_s"] = time.perf_counter() - t0
        fig["per_recording_s"] = fig["sequential_s"] / n
        fig["per_recording_task_s"] = [round(r["seconds"], 2) for r in seq]
        for w in (1, 2):
            with LocalCluster(n_workers=w, threads_per_worker=1, processes=True, dashboard_address=None) as c, \
                    Client(c) as client:
                run(paths[:1], scheduler=client)          # warm the workers (imports)
                t0 = time.perf_counter()
                par = run(paths, scheduler=client)
                fig[f"dask_{w}_workers_s"] = time.perf_counter() - t0
            assert all(a["static"] == b["static"] and a["maps"] == b["maps"] for a, b in zip(seq, par))
        fig["speedup_2_vs_1_worker"] = fig["dask_1_workers_s"] / fig["dask_2_workers_s"]
        fig["speedup_2_workers_vs_sequential"] = fig["sequential_s"] / fig["dask_2_workers_s"]
        fig["identical_to_sequential"] = True
    print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in fig.items()}))


if __name__ == "__main__":
    main()
