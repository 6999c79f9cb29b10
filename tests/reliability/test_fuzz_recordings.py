"""Reduced fuzz run of the CT offline tool (the full run: tests/benchmarks/fuzz_recordings.py).

Mutants of a short valid recording (every truncation at record boundaries and inside chunks,
bit flips, garbage, wrong or missing schemas, wrong message encodings, hostile field values,
duplicate / reversed / equal / zero stamps; fixed seed) each go through ct_offline_solve in a
worker process. Every run must end with a documented exit status and a message: no traceback,
no hang, no peak-RSS growth beyond the bound.
"""

import collections

import pytest

from reliab_cells import CT
from reliab_fuzz import make_mutants, run_campaign

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def test_fuzzed_recordings_reduced(tmp_path):
    path, entries = CT.make(tmp_path / "cell", full=False)
    base = path.read_bytes()
    # 170 mutants: every fixed kind in full (68) and ~100 random ones (was 300 in all: 75 s of the suite's
    # 15 min; the full run of >= 2000 is the benchmark)
    muts = make_mutants(base, entries, n_target=170, seed=7,
                        mix={"bitflip": 0.55, "garbage": 0.3, "field": 0.1, "combo": 0.05})
    kinds = collections.Counter(m.kind for m in muts)
    assert len(muts) >= 170 and set(kinds) == {"truncate_boundary", "truncate_mid", "schema", "encoding", "stamps",
                                               "bitflip", "garbage", "field", "combo"}
    camp = run_campaign(path, entries, CT.tools, muts, tmp_path, chunk_size=CT.chunk_size)
    table = "\n".join(f"{k}: {v}" for k, v in sorted(camp.counts.items()))
    print(f"\n{table}\nruns {camp.runs}, reused {camp.reused}, max peak RSS growth {camp.max_peak_kb / 1024:.0f} MiB")
    assert not camp.failures, "\n\n".join(f"{f[0]} {f[1]} {f[2]} {f[3]}:\n{f[4]}" for f in camp.failures[:5])
    assert sum(sum(c.values()) for c in camp.counts.values()) == len(muts)
    # the damage is survived, not just refused: cut files and damaged ones still give results
    assert camp.counts["truncate_boundary"].get("exit_0", 0) >= 3
    assert camp.counts["bitflip"].get("exit_0", 0) >= 0.2 * sum(camp.counts["bitflip"].values())
    assert camp.counts["schema"].get("exit_1", 0) >= 1 and camp.counts["field"].get("exit_0", 0) >= 1


def test_fuzzed_picms_recordings_reduced(tmp_path):
    """The Pixel Probe cell through picms_calibrate_offline: one mutant of every kind, two bit flips (seeded draw; the
    full run of >= 2000: tests/benchmarks/fuzz_recordings.py --cell picms). Documented exit statuses
    only, and the damage survived: a cut after the last image chunk and a flipped bit still calibrate."""
    import numpy as np

    from reliab_cells import PICMS

    path, entries = PICMS.make(tmp_path / "cell", full=False)
    base = path.read_bytes()
    muts = make_mutants(base, entries, n_target=420, seed=11,
                        mix={"bitflip": 0.5, "garbage": 0.3, "field": 0.12, "combo": 0.08})
    rng = np.random.default_rng(3)
    by_kind = collections.defaultdict(list)
    for m in muts:
        by_kind[m.kind].append(m)
    assert set(by_kind) == {"truncate_boundary", "truncate_mid", "schema", "encoding", "stamps", "bitflip",
                            "garbage", "field", "combo"}
    # the last record boundaries (cuts inside the summary: every message is there) and two random draws
    picked = by_kind["truncate_boundary"][-1:]
    for kind, ms in sorted(by_kind.items()):
        n = 2 if kind == "bitflip" else 1
        picked += [ms[int(i)] for i in rng.choice(len(ms), size=min(n, len(ms)), replace=False)]
    camp = run_campaign(path, entries, PICMS.tools, picked, tmp_path, chunk_size=PICMS.chunk_size)
    table = "\n".join(f"{k}: {v}" for k, v in sorted(camp.counts.items()))
    print(f"\n{table}\nruns {camp.runs}, reused {camp.reused}, max peak RSS growth {camp.max_peak_kb / 1024:.0f} MiB")
    assert not camp.failures, "\n\n".join(f"{f[0]} {f[1]} {f[2]} {f[3]}:\n{f[4]}" for f in camp.failures[:5])
    assert sum(sum(c.values()) for c in camp.counts.values()) == len(picked)
    assert camp.counts["truncate_boundary"].get("exit_0", 0) >= 1
    assert sum(c.get("exit_0", 0) for k, c in camp.counts.items() if k in ("bitflip", "garbage")) >= 1
