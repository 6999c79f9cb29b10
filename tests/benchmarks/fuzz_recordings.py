"""Fuzzed recordings against every offline tool of a cell (issue 10): counts by kind and outcome.

    .venv/bin/python tests/benchmarks/fuzz_recordings.py [--cell ct] [--mutants 2000] [--seed 20261125]
                                                         [--no-dedup] [--timeout 120] [--mix ...] [--small]

Builds a short valid recording of the cell in a temporary folder, derives the mutants (fixed
seed; kinds in tests/reliability/reliab_fuzz.py), runs every offline tool of the cell on each in
a worker process (tools in-process there, a timeout enforced from outside, peak RSS measured per
run) and prints a table of outcomes per mutant kind, the failures (traceback, bad exit, hang,
memory) in full, and ONE JSON line of figures at the end. With dedup (default) a mutant whose
readable content equals an earlier one's shares that outcome (``reused``); --no-dedup runs all.
Exit status 0 when every run ended with a documented status and a message, 1 otherwise.
"""

import argparse
import collections
import json
import pathlib
import sys
import tempfile
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "reliability"))

from reliab_cells import CELLS  # noqa: E402
from reliab_fuzz import make_mutants, run_campaign  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cell", default="ct", choices=sorted(CELLS))
    ap.add_argument("--mutants", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=20261125)
    ap.add_argument("--no-dedup", action="store_true")
    ap.add_argument("--timeout", type=float, default=120.0)
    ap.add_argument("--small", action="store_true",
                    help="the cell's smallest recording (CT: one stage position, 4 frames: no error motions, no report)")
    ap.add_argument("--mix", default="bitflip=0.55,garbage=0.33,field=0.08,combo=0.04",
                    help="shares of the random kinds (field and combo mutants each need a full solve)")
    args = ap.parse_args()
    cell = CELLS[args.cell]
    for t in cell.tools:
        t.timeout_s = args.timeout
    with tempfile.TemporaryDirectory(prefix="fuzz_rec_") as tmp:
        t0 = time.monotonic()
        path, entries = cell.make(pathlib.Path(tmp) / "cell", full=not args.small)
        base = path.read_bytes()
        mix = {k: float(v) for k, v in (kv.split("=") for kv in args.mix.split(","))}
        muts = make_mutants(base, entries, n_target=args.mutants, seed=args.seed, mix=mix)
        print(f"[fuzz] {args.cell}: base recording {len(base)} B, {len(entries)} messages; {len(muts)} mutants "
              f"{dict(collections.Counter(m.kind for m in muts))}", file=sys.stderr, flush=True)
        camp = run_campaign(path, entries, cell.tools, muts, pathlib.Path(tmp), dedup=not args.no_dedup,
                            chunk_size=cell.chunk_size,
                            progress=lambda m: print(f"[fuzz] {m}", file=sys.stderr, flush=True))
        wall = time.monotonic() - t0
    outcomes = sorted({o for c in camp.counts.values() for o in c})
    print(f"{'kind':20s}" + "".join(f"{o:>11s}" for o in outcomes), file=sys.stderr)
    for kind, c in sorted(camp.counts.items()):
        print(f"{kind:20s}" + "".join(f"{c.get(o, 0):11d}" for o in outcomes), file=sys.stderr)
    for f in camp.failures:
        print(f"[fuzz] FAILURE {f[0]} {f[1]} {f[2]}: {f[3]}\n{f[4]}", file=sys.stderr)
    totals = collections.Counter()
    for c in camp.counts.values():
        totals.update(c)
    print(json.dumps({"benchmark": "fuzz_recordings", "cell": args.cell, "seed": args.seed, "mutants": camp.n_mutants, "mix": args.mix, "small": args.small,
                      "tools": [t.name for t in cell.tools], "tool_runs_executed": camp.runs,
                      "tool_runs_reused_identical_content": camp.reused, "outcomes": dict(totals),
                      "by_kind": camp.counts, "failures": len(camp.failures),
                      "max_peak_rss_growth_mb": round(camp.max_peak_kb / 1024, 1),
                      "max_run_seconds": round(camp.max_seconds, 2), "wall_seconds": round(wall, 1),
                      "note": "2-core machine shared with other jobs: times are loaded"}))
    return 0 if not camp.failures else 1


if __name__ == "__main__":
    raise SystemExit(main())
