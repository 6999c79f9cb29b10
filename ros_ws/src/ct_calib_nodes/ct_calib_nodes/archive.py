"""Re-solve an archive of CT recordings in parallel on Dask, storing every result in the history.

    ct_archive_solve DIR [--scheduler tcp://host:8786] [--workers N] [--history DB] [--json FILE]
                     [--instrument FILE] [--reference-object FILE] [--namespace /cell_a] [--loss linear]

Every ``*.mcap`` file and rosbag2 directory directly in DIR is one task: the offline solve
(offline.solve_recording: detection, identity, static geometry, error maps; no report files).
Without ``--scheduler`` the tasks run on Dask's local process pool (``--workers``, default the CPU
count; ``--workers 1`` runs them one after another in this process); with a scheduler address they
run on that Dask distributed cluster (the workers need this package and read access to the
recordings at the same paths). Workers return compact, picklable results; only this process writes
the history database (a cluster's workers need no access to it), as ``source = archive``.

Exit status: 0 every recording solved usably; 1 some were not (each is listed with its reason);
2 bad arguments or no recording found.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time


def find_recordings(root) -> list:
    root = pathlib.Path(root)
    out = []
    for p in sorted(root.iterdir()):
        if p.is_file() and p.suffix == ".mcap":
            out.append(p)
        elif p.is_dir() and ((p / "metadata.yaml").is_file() or any(p.glob("*.mcap"))):
            out.append(p)
    return out


def solve_one(path, instrument_file=None, reference_file=None, namespace=None, loss="linear", init_frames=6) -> dict:
    """One recording -> a plain dict (picklable, JSON-able): status, results with uncertainties, the
    history records, timing. Never raises: a recording that cannot be solved says why."""
    from ct_calib_nodes.io.ct_history import offline_records  # noqa: PLC0415
    from ct_calib_nodes.io.history import content_hash, plain  # noqa: PLC0415
    from ct_calib_nodes.io.namespaces import find_namespace  # noqa: PLC0415
    from ct_calib_nodes.offline import load_recording_files, solve_recording  # noqa: PLC0415

    t0 = time.perf_counter()
    rec = pathlib.Path(path)
    out = {"recording": str(rec), "host": os.uname().nodename, "pid": os.getpid()}
    try:
        f = load_recording_files(rec, instrument_file, reference_file)
        inst_path, ref_path, instrument, ref, note = (f.instrument_path, f.reference_path, f.instrument, f.ref,
                                                      f.thermal_note)
        ns = find_namespace(rec, namespace)
        res = solve_recording(rec, instrument, ref, init_frames=init_frames, loss=loss, namespace=ns)
        res.notes.append(note)
    except Exception as exc:  # noqa: BLE001 - one bad recording never stops the archive
        out.update(ok=False, status="failed", reason=f"{type(exc).__name__}: {exc}", records=[],
                   seconds=time.perf_counter() - t0)
        return out
    files = {"instrument": inst_path, "reference_object": ref_path}
    records = offline_records(res, recording=rec, files=files, cell=ns, source="archive",
                              recording_hash=content_hash(rec))
    for r in records:
        r.result = plain(r.result)
    ok = res.static is not None and res.static.success
    out.update(ok=ok, status="success" if ok else (records[0].status if records else "insufficient_data"),
               reason="" if ok else "; ".join(res.problems[-3:]) or "nothing to solve", namespace=ns,
               frames=res.counts.get("frames", 0), problems=list(res.problems),
               static={"names": list(res.static.names), "x": plain(res.static.x), "std": plain(res.static.std)}
               if res.static is not None else None,
               maps={mode: plain(by_def["travel"].to_dict()) for mode, by_def in res.maps.items()},
               records=records, seconds=time.perf_counter() - t0)
    return out


def run(paths, *, scheduler=None, workers=None, progress=None, **kw) -> list:
    """solve_one over paths: sequentially (workers == 1), on Dask's local process pool, or on the
    Dask distributed cluster at ``scheduler`` (an address, or a distributed.Client / LocalCluster).
    Results in the order of ``paths``."""
    say = progress or (lambda _m: None)
    paths = [str(p) for p in paths]
    if scheduler is None and workers == 1:
        out = []
        for p in paths:
            out.append(solve_one(p, **kw))
            say(f"{pathlib.Path(p).name}: {out[-1]['status']} ({out[-1]['seconds']:.1f} s)")
        return out
    if scheduler is None:
        import dask  # noqa: PLC0415
        from dask import delayed  # noqa: PLC0415

        tasks = [delayed(solve_one)(p, **kw) for p in paths]
        out = list(dask.compute(*tasks, scheduler="processes", num_workers=workers or os.cpu_count()))
        for r in out:
            say(f"{pathlib.Path(r['recording']).name}: {r['status']} ({r['seconds']:.1f} s)")
        return out
    from distributed import Client, as_completed  # noqa: PLC0415

    own = isinstance(scheduler, str)
    client = Client(scheduler) if own else (scheduler if isinstance(scheduler, Client) else Client(scheduler))
    try:
        futures = client.map(solve_one, paths, **kw, pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        out = [None] * len(paths)
        for fut in as_completed(futures):
            r = fut.result()
            out[index[fut.key]] = r
            say(f"{pathlib.Path(r['recording']).name}: {r['status']} ({r['seconds']:.1f} s on {r['host']})")
        return out
    finally:
        if own or not isinstance(scheduler, Client):
            client.close()


def store(results, history_path=None) -> int:
    from ct_calib_nodes.io.ct_history import store_offline  # noqa: PLC0415
    from ct_calib_nodes.io.history import open_history  # noqa: PLC0415

    h = open_history(history_path or None, logger=lambda m: print(f"[archive] {m}"))
    if h is None:
        return 0
    n = 0
    try:
        for r in results:
            n += len(store_offline(h, r["records"]))
    finally:
        h.close()
    return n


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="ct_archive_solve", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("directory")
    ap.add_argument("--scheduler", help="Dask distributed scheduler address (default: local processes)")
    ap.add_argument("--workers", type=int, help="local worker processes (default: CPU count; 1 = sequential)")
    ap.add_argument("--history", default="", help="history database (default $METRO_HISTORY_DB or "
                                                  "~/.local/share/metro_cell/history.sqlite; none = off)")
    ap.add_argument("--json", help="write a summary of every recording here")
    ap.add_argument("--instrument")
    ap.add_argument("--reference-object")
    ap.add_argument("--namespace")
    ap.add_argument("--loss", default="linear")
    a = ap.parse_args(argv)
    root = pathlib.Path(a.directory)
    if not root.is_dir():
        print(f"ct_archive_solve: {root} is not a directory", file=sys.stderr)
        return 2
    paths = find_recordings(root)
    if not paths:
        print(f"ct_archive_solve: no .mcap file or rosbag2 directory in {root}", file=sys.stderr)
        return 2
    where = a.scheduler or (f"{a.workers or os.cpu_count()} local process(es)" if a.workers != 1 else "this process")
    print(f"[archive] {len(paths)} recording(s) on {where}")
    t0 = time.perf_counter()
    results = run(paths, scheduler=a.scheduler, workers=a.workers, progress=lambda m: print(f"[archive] {m}"),
                  instrument_file=a.instrument, reference_file=a.reference_object, namespace=a.namespace,
                  loss=a.loss)
    wall = time.perf_counter() - t0
    n = store(results, a.history)
    bad = [r for r in results if not r["ok"]]
    cpu = sum(r["seconds"] for r in results)
    print(f"[archive] {len(results) - len(bad)} of {len(results)} solved usably in {wall:.1f} s wall "
          f"({cpu / len(results):.1f} s per recording in the workers; {n} history record(s))")
    for r in bad:
        print(f"[archive] NOT USABLE {r['recording']}: {r['status']}: {r['reason']}")
    if a.json:
        from ct_calib_nodes.io.history import plain  # noqa: PLC0415
        summary = [{k: v for k, v in r.items() if k != "records"} for r in results]
        pathlib.Path(a.json).write_text(json.dumps(plain({"wall_s": wall, "recordings": summary}), indent=1))
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
