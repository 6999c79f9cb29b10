"""Fuzzing of recordings against the offline tools of a cell: a generic engine.

A *cell* (see reliab_cells.py) gives a short valid recording, the messages it holds (rclpy
objects, for message-level rewrites) and its offline tools: an in-process entry point
``"module:function"`` that takes argv and returns an exit status, how to build argv, and the
exit statuses its documentation promises. Adding the Pixel Probe cell = one more CellSpec there.

Mutants (fixed seed; every kind is deterministic given the seed):
- ``truncate_boundary``: the file cut at every top-level record boundary;
- ``truncate_mid``: cut inside every chunk (a quarter, half, three quarters in);
- ``bitflip``: one bit flipped anywhere; ``garbage``: 4-64 bytes overwritten with random bytes;
- ``schema``: a topic written with another topic's schema, with no schema, with a garbled or
  truncated schema text, with an unknown schema encoding;
- ``encoding``: a channel whose message encoding is not cdr (json, ros1, empty);
- ``field``: one field of one or several messages set to a hostile value chosen by its type
  (NaN, +-inf, -1, 1e300, 10**9 / 2**32-1 for sizes such as Image.height, empty or shortened
  arrays, an extra element, unknown or empty strings, truncated byte payloads);
- ``stamps``: duplicate header stamps, reversed file order, all stamps equal, zero stamps;
- ``combo``: a field mutation and then a truncation or a bit flip.

Every (mutant, tool) pair runs in a worker process (the tools in-process there: imports paid
once) under a per-run timeout enforced from outside (a hung worker is killed and replaced). The
worker resets the kernel's peak-RSS mark (/proc/self/clear_refs) before each run and reports the
growth of the peak over the resident size before it; an address-space limit stops a runaway
before it takes the machine down. Outcomes:
- ``exit_N``: the tool returned a documented status N and printed a message (one line at least);
- ``traceback``: an exception escaped the tool; ``bad_exit``: an undocumented status or a
  non-zero status with no message; ``hang``: the timeout; ``memory``: peak RSS growth beyond
  the bound (``mem_factor`` x file size, at least ``mem_floor``).
The tools are deterministic in the messages they read: a mutant whose decoded content (every
readable message's topic, schema, encoding, log time and bytes, and the damaged spans' count)
equals an earlier one's shares its tool outcome unless ``dedup=False`` (counted separately).
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import io
import json
import math
import os
import pathlib
import resource
import select
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass, field

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent


# --- mutants ---------------------------------------------------------------------------------------

@dataclass
class Mutant:
    kind: str
    name: str
    build: object           # callable(base_bytes) -> bytes


def record_offsets_of(data: bytes):
    """(offset, opcode, length) of every top-level record of MCAP bytes (an intact file)."""
    out, o = [], 8
    while o + 9 <= len(data):
        op, ln = data[o], int.from_bytes(data[o + 1:o + 9], "little")
        out.append((o, op, ln))
        if op == 2:
            break
        o += 9 + ln
    return out


def write_mcap(path, entries, chunk_size=48 * 1024, schema_mode=None, encoding_mode=None):
    """Write ``entries`` [(topic, type name, rclpy message or bytes, log time)] with the schema and
    channel records possibly made wrong: ``schema_mode`` = (topic, how) with how in
    {"other", "none", "garbled", "truncated", "encoding"}; ``encoding_mode`` = (topic, encoding)."""
    from mcap.writer import CompressionType, Writer

    from ct_calib_nodes.io.mcap_io import message_definition, serialize_exact

    types = {}
    for topic, tname, _m, _t in entries:
        types.setdefault(topic, tname)
    with open(path, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD, chunk_size=chunk_size)
        w.start(profile="ros2", library="reliab fuzz")
        chan = {}
        others = sorted(set(types.values()))
        for topic, tname in types.items():
            sname, senc, text = tname, "ros2msg", message_definition(tname).encode()
            how = schema_mode[1] if schema_mode and schema_mode[0] == topic else None
            if how == "other":
                alt = [t for t in others if t != tname] or ["std_msgs/msg/String"]
                sname, text = alt[0], message_definition(alt[0]).encode()
            elif how == "garbled":
                text = text[: len(text) // 3] + b"\x00\xff\xfe float64[] ??? !!\n" + text[len(text) // 3:]
            elif how == "truncated":
                text = text[: len(text) // 5]
            elif how == "encoding":
                senc = "ros1msg"
            sid = 0 if how == "none" else w.register_schema(name=sname, encoding=senc, data=text)
            menc = encoding_mode[1] if encoding_mode and encoding_mode[0] == topic else "cdr"
            chan[topic] = w.register_channel(topic=topic, message_encoding=menc, schema_id=sid, metadata={})
        for i, (topic, _tname, msg, t) in enumerate(entries):
            data = msg if isinstance(msg, (bytes, bytearray)) else serialize_exact(msg)
            w.add_message(channel_id=chan[topic], log_time=int(t), publish_time=int(t), data=bytes(data), sequence=i)
        w.finish()


def _hostile(value, type_str, rng):
    """A hostile replacement for one field value, chosen by the field's type."""
    floats = ("float", "double", "float32", "float64")
    if type_str in floats:
        return float(rng.choice([math.nan, math.inf, -math.inf, -1.0, 1e300, 0.0]))
    if type_str in ("uint32", "int32", "uint16", "int16", "uint64", "int64", "uint8", "int8", "octet"):
        lim = {"uint8": 255, "int8": 127, "octet": 255, "uint16": 65535, "int16": 32767, "uint32": 2**32 - 1,
               "int32": 2**31 - 1, "uint64": 2**63, "int64": 2**62}[type_str]
        opts = [0, min(10**9, lim), lim, 1]
        if type_str.startswith("int"):
            opts.append(-1)
        return int(rng.choice(opts))
    if type_str == "boolean":
        return not value
    if type_str.startswith("string"):
        return str(rng.choice(["", "garbage", "rgb8", "\u00e9\u00e8", "x" * 300]))
    if type_str.startswith("sequence<") or type_str.endswith("]"):
        elem = type_str[9:-1] if type_str.startswith("sequence<") else type_str.split("[")[0]
        seq = list(value) if not isinstance(value, (bytes, bytearray)) else value
        how = rng.integers(0, 5)
        if type_str.endswith("]") and not type_str.startswith("sequence"):   # fixed array: values only
            if elem in floats and len(seq):
                seq = list(seq)
                seq[int(rng.integers(0, len(seq)))] = float(rng.choice([math.nan, math.inf, 1e300]))
            return seq
        if how == 0:
            return b"" if isinstance(seq, (bytes, bytearray)) else []
        if how == 1 and len(seq):
            return seq[: int(rng.integers(0, len(seq)))]
        if elem in floats:
            seq = [float(x) for x in seq] + ([0.0] if how == 2 else [])
            if seq:
                seq[int(rng.integers(0, len(seq)))] = float(rng.choice([math.nan, math.inf, -math.inf, -1.0, 1e300]))
            return seq
        if elem.startswith("string"):
            return [str(x) for x in seq][::-1][:1] + ["unknown_joint"] if how == 2 else ["a", "b", "c", "d"]
        if isinstance(seq, (bytes, bytearray)) or elem in ("uint8", "octet", "byte"):
            b = bytes(seq)
            return b[: len(b) // 2] + (b"\x00" * 7 if how == 2 else b"")
        return seq[:-1] if len(seq) else seq
    return None


def _mutable_fields(msg, prefix=""):
    """(path, type string) of every leaf field of an rclpy message (nested messages walked)."""
    out = []
    for name, t in msg.get_fields_and_field_types().items():
        v = getattr(msg, name)
        if hasattr(v, "get_fields_and_field_types") and not t.startswith("sequence"):
            out += _mutable_fields(v, prefix + name + ".")
        else:
            out.append((prefix + name, t))
    return out


def _set_path(msg, path, value):
    parts = path.split(".")
    obj = msg
    for p in parts[:-1]:
        obj = getattr(obj, p)
    cur = getattr(obj, parts[-1])
    if isinstance(cur, np.ndarray):
        value = np.asarray(value, dtype=cur.dtype) if len(value) else np.zeros(0, cur.dtype)
    elif isinstance(cur, (bytes, bytearray)) and not isinstance(value, (bytes, bytearray)):
        value = bytes(value)
    try:
        setattr(obj, parts[-1], value)
        return True
    except (AssertionError, TypeError, ValueError, OverflowError):
        return False       # rclpy refuses the value at assignment: a publisher could not send it either


def _get_path(msg, path):
    obj = msg
    for p in path.split("."):
        obj = getattr(obj, p)
    return obj


def _copy_entries(entries):
    return [(tp, tn, copy.deepcopy(m), t) for tp, tn, m, t in entries]


MIX = {"bitflip": 0.35, "garbage": 0.15, "field": 0.35, "combo": 0.15}


def make_mutants(base: bytes, entries, n_target=2000, seed=20261125, mix=None):
    """The mutant list: truncations, schema, encoding and stamp kinds in full, the random kinds
    (``mix``: kind -> share) filling up to ``n_target``."""
    mix = dict(MIX if mix is None else mix)
    rng = np.random.default_rng(seed)
    muts: list[Mutant] = []
    recs = record_offsets_of(base)
    for o, op, _ln in recs:
        muts.append(Mutant("truncate_boundary", f"cut@{o}(op{op})", lambda b, o=o: b[:o]))
    for o, op, ln in recs:
        if op == 6:
            for f in (0.25, 0.5, 0.75):
                c = o + 9 + int(ln * f)
                muts.append(Mutant("truncate_mid", f"cut@{c}", lambda b, c=c: b[:c]))
    topics = sorted({e[0] for e in entries})
    for topic in topics:
        for how in ("other", "none", "garbled", "truncated", "encoding"):
            muts.append(Mutant("schema", f"{topic}:{how}",
                               lambda b, t=topic, h=how: ("write", dict(schema_mode=(t, h)))))
        for enc in ("json", "ros1", ""):
            muts.append(Mutant("encoding", f"{topic}:{enc or 'empty'}",
                               lambda b, t=topic, e=enc: ("write", dict(encoding_mode=(t, e)))))

    def stamps(kind):
        def build(_b):
            es = _copy_entries(entries)
            if kind == "reversed":
                es = es[::-1]
            for i, (tp, tn, m, t) in enumerate(es):
                if not hasattr(m, "header"):
                    continue
                if kind == "all_equal":
                    m.header.stamp = copy.deepcopy(es[0][2].header.stamp) if hasattr(es[0][2], "header") else m.header.stamp
                elif kind == "zero":
                    m.header.stamp.sec, m.header.stamp.nanosec = 0, 0
                elif kind == "duplicate" and i >= 2 and i % 3 == 0 and hasattr(es[i - 2][2], "header"):
                    m.header.stamp = copy.deepcopy(es[i - 2][2].header.stamp)
            return ("entries", es)
        return build
    for kind in ("duplicate", "reversed", "all_equal", "zero"):
        muts.append(Mutant("stamps", kind, stamps(kind)))

    def field_mutant(seed_i, then=None):
        r = np.random.default_rng(seed_i)

        def build(b):
            es = _copy_entries(entries)
            n_msgs = int(r.choice([1, 1, 1, 3, len(es)]))
            picked = r.choice(len(es), size=min(n_msgs, len(es)), replace=False)
            tp0 = es[int(picked[0])][0]
            fields = _mutable_fields(es[int(picked[0])][2])
            path, tstr = fields[int(r.integers(0, len(fields)))]
            for j in picked:
                tp, tn, m, t = es[int(j)]
                if tp != tp0:
                    continue
                v = _hostile(_get_path(m, path), tstr, r)
                if v is not None:
                    _set_path(m, path, v)
            if then is None:
                return ("entries", es)
            return ("entries_then", es, then)
        return build, None

    n_fixed = len(muts)
    n_random = max(0, n_target - n_fixed)
    names = sorted(mix)
    share = np.array([mix[k] for k in names], dtype=float)
    kinds = rng.choice(names, size=n_random, p=share / share.sum())
    for i, kind in enumerate(kinds):
        s = int(rng.integers(0, 2**31))
        if kind == "bitflip":
            pos, bit = int(rng.integers(0, len(base))), int(rng.integers(0, 8))

            def build(b, pos=pos, bit=bit):
                d = bytearray(b)
                d[pos] ^= 1 << bit
                return bytes(d)
            muts.append(Mutant("bitflip", f"flip@{pos}.{bit}", build))
        elif kind == "garbage":
            pos, n = int(rng.integers(0, len(base))), int(rng.integers(4, 65))
            junk = rng.integers(0, 256, n, dtype=np.uint8).tobytes()

            def build(b, pos=pos, junk=junk):
                d = bytearray(b)
                d[pos:pos + len(junk)] = junk
                return bytes(d[: len(b)])
            muts.append(Mutant("garbage", f"junk@{pos}+{n}", build))
        elif kind == "field":
            muts.append(Mutant("field", f"field#{s}", field_mutant(s)[0]))
        else:
            then = ("flip", float(rng.random()), int(rng.integers(0, 8))) if rng.random() < 0.5 else \
                ("cut", float(rng.random()))
            muts.append(Mutant("combo", f"combo#{s}:{then[0]}", field_mutant(s, then)[0]))
    return muts


def materialise(m: Mutant, base: bytes, entries, path, chunk_size=48 * 1024):
    """Write the mutant's file to ``path``."""
    out = m.build(base)
    if isinstance(out, (bytes, bytearray)):
        pathlib.Path(path).write_bytes(out)
        return
    if out[0] == "write":
        write_mcap(path, entries, chunk_size=chunk_size, **out[1])
        return
    write_mcap(path, out[1], chunk_size=chunk_size)
    if out[0] == "entries_then":
        then = out[2]
        d = bytearray(pathlib.Path(path).read_bytes())
        if then[0] == "flip":
            d[int(then[1] * (len(d) - 1))] ^= 1 << then[2]
        else:
            d = d[: int(then[1] * len(d))]
        pathlib.Path(path).write_bytes(bytes(d))


# --- worker ---------------------------------------------------------------------------------------

def _status_kb(key):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key):
                return int(line.split()[1])
    return 0


def content_digest(path) -> str:
    """Digest of what a reader can get out of a recording (see the module docstring)."""
    import mmap

    from ct_calib_nodes.io.mcap_io import ReadReport, RecordingError, _FileReader, recording_files

    h = hashlib.sha1()
    rep = ReadReport()
    try:
        for file in recording_files(path):
            with open(file, "rb") as fh:
                if os.fstat(fh.fileno()).st_size == 0:
                    h.update(b"empty")
                    continue
                mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
                try:
                    fr = _FileReader(file, mm, rep)
                    for _op, cid, t, _p, data in fr.records():
                        topic, sid, enc = fr.channels.get(cid, ("?", -1, "?"))
                        s = fr.schemas.get(sid)
                        h.update(repr((topic, enc, t, s.name if s else None, s.encoding if s else None,
                                       hashlib.sha1(s.data).hexdigest() if s else None)).encode())
                        h.update(bytes(data))
                finally:
                    fr = None
                    mm.close()
    except RecordingError as exc:
        h.update(str(type(exc)).encode())
    h.update(f"lost{len(rep.lost)}".encode())
    return h.hexdigest()


def worker_main():
    """Read jobs (JSON lines) from stdin, run each tool in-process, answer one JSON line each."""
    import importlib

    headroom = int(os.environ.get("RELIAB_AS_HEADROOM", str(3 << 30)))
    vm = _status_kb("VmSize:") * 1024
    resource.setrlimit(resource.RLIMIT_AS, (vm + headroom, resource.RLIM_INFINITY))
    loaded = {}
    for line in sys.stdin:
        job = json.loads(line)
        if job.get("digest"):
            print(json.dumps({"digest": content_digest(job["path"])}), flush=True)
            continue
        mod, fn = job["entry"].split(":")
        if job["entry"] not in loaded:
            loaded[job["entry"]] = getattr(importlib.import_module(mod), fn)
        main = loaded[job["entry"]]
        out, err = io.StringIO(), io.StringIO()
        rss0 = _status_kb("VmRSS:")
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        t0 = time.monotonic()
        tb = None
        try:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                try:
                    rc = main(job["argv"])
                except SystemExit as exc:       # argparse and friends: a documented exit path
                    rc = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
        except MemoryError:
            rc, tb = None, "MemoryError"
        except BaseException as exc:  # noqa: BLE001 - this is what the fuzzing looks for
            rc, tb = None, "".join(traceback.format_exception(exc))[-3000:]
        dt = time.monotonic() - t0
        peak = _status_kb("VmHWM:")
        text = (out.getvalue() + err.getvalue()).strip().splitlines()
        print(json.dumps({"rc": rc, "traceback": tb, "seconds": dt, "peak_growth_kb": max(0, peak - rss0),
                          "last": text[-1][:300] if text else "", "lines": len(text)}), flush=True)


class Worker:
    """A worker process (started here, killed here on a timeout)."""

    def __init__(self):
        env = dict(os.environ)
        self.proc = subprocess.Popen([sys.executable, __file__, "--worker"], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, bufsize=1,
                                     env=env)

    def ask(self, job: dict, timeout: float):
        self.proc.stdin.write(json.dumps(job) + "\n")
        self.proc.stdin.flush()
        r, _, _ = select.select([self.proc.stdout], [], [], timeout)
        if not r:
            self.kill()
            return None
        line = self.proc.stdout.readline()
        if not line:
            self.kill()
            return {"rc": None, "traceback": "worker died (killed by a signal or the address-space limit)",
                    "seconds": 0, "peak_growth_kb": 0, "last": "", "lines": 0}
        return json.loads(line)

    def kill(self):
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)

    def close(self):
        try:
            self.proc.stdin.close()
            self.proc.wait(10)
        except Exception:  # noqa: BLE001
            self.kill()


@dataclass
class ToolSpec:
    name: str
    entry: str                      # "module:function", called with argv, returns the exit status
    argv: object                    # callable(recording path, output dir) -> list of str
    exit_codes: dict                # documented status -> meaning
    timeout_s: float = 120.0


@dataclass
class Campaign:
    counts: dict = field(default_factory=dict)      # kind -> outcome -> n
    failures: list = field(default_factory=list)    # (kind, mutant, tool, outcome, detail)
    runs: int = 0
    reused: int = 0
    max_peak_kb: int = 0
    max_seconds: float = 0.0
    n_mutants: int = 0


def classify(res, tool: ToolSpec, file_size: int, mem_factor: float, mem_floor_kb: int):
    if res is None:
        return "hang", f"no answer within {tool.timeout_s} s"
    if res["traceback"]:
        return "traceback", res["traceback"]
    if res["peak_growth_kb"] > max(mem_floor_kb, mem_factor * file_size / 1024):
        return "memory", f"peak RSS grew {res['peak_growth_kb']} kB for a {file_size} B file"
    rc = res["rc"]
    if rc not in tool.exit_codes:
        return "bad_exit", f"exit status {rc} is not documented"
    if rc != 0 and res["lines"] == 0:
        return "bad_exit", f"exit status {rc} without a message"
    return f"exit_{rc}", res["last"]


def run_campaign(base_path, entries, tools, mutants, workdir, dedup=True, mem_factor=50.0,
                 mem_floor_kb=256 * 1024, progress=None, chunk_size=48 * 1024):
    """Every mutant through every tool; returns a Campaign."""
    base_path, workdir = pathlib.Path(base_path), pathlib.Path(workdir)
    base = base_path.read_bytes()
    camp = Campaign(n_mutants=len(mutants))
    worker = Worker()
    seen = {}
    try:
        for i, m in enumerate(mutants):
            mp = base_path.parent / f"mutant{base_path.suffix}"    # beside the YAML files of the cell
            materialise(m, base, entries, mp, chunk_size=chunk_size)
            size = mp.stat().st_size
            digest = None
            if dedup:
                d = worker.ask({"digest": True, "path": str(mp)}, 60.0)
                if d is None:
                    worker = Worker()
                    digest = None
                    camp.counts.setdefault(m.kind, {}).setdefault("hang", 0)
                    camp.counts[m.kind]["hang"] += 1
                    camp.failures.append((m.kind, m.name, "reader", "hang", "content digest timed out"))
                    continue
                digest = d["digest"]
            for tool in tools:
                key = (tool.name, digest)
                if dedup and key in seen:
                    outcome, detail = seen[key]
                    camp.reused += 1
                else:
                    out = workdir / "out"
                    res = worker.ask({"entry": tool.entry, "argv": tool.argv(str(mp), str(out))}, tool.timeout_s)
                    if res is None or (res.get("traceback") or "").startswith("worker died"):
                        worker = Worker()
                    outcome, detail = classify(res, tool, size, mem_factor, mem_floor_kb)
                    camp.runs += 1
                    if res is not None:
                        camp.max_seconds = max(camp.max_seconds, res["seconds"])
                        camp.max_peak_kb = max(camp.max_peak_kb, res["peak_growth_kb"])
                    if dedup:
                        seen[key] = (outcome, detail)
                kc = camp.counts.setdefault(m.kind, {})
                kc[outcome] = kc.get(outcome, 0) + 1
                if not outcome.startswith("exit_"):
                    camp.failures.append((m.kind, m.name, tool.name, outcome, detail))
            if progress and (i + 1) % 50 == 0:
                progress(f"{i + 1}/{len(mutants)} mutants, {camp.runs} runs, {camp.reused} reused, "
                         f"{len(camp.failures)} failures; {json.dumps(camp.counts)}")
    finally:
        worker.close()
    return camp


if __name__ == "__main__" and "--worker" in sys.argv:
    sys.path.insert(0, str(HERE))
    worker_main()
