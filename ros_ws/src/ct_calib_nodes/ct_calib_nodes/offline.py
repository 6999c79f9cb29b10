"""Offline CT calibration from a recording, without DDS: the same core as the live nodes.

    ct_offline_solve RECORDING --instrument ct_instrument.yaml --reference-object reference_object.yaml
                     [--out DIR] [--reference-error-map FILE] [--init-frames 6] [--loss linear]
                     [--position-tolerance 1e-4] [--workers N] [--track N]

RECORDING is one ``.mcap`` file or a rosbag2 directory that follows INTERFACES.md
(``/ct/detector/image`` + ``/ct/stage/joint_states`` paired by stamp). Without
``--instrument`` / ``--reference-object`` the files are looked for beside the
recording, then the package defaults are used (and the choice is printed).

Frames go through ct_pipeline.FrameProcessor (detection + identity) and
CampaignAccumulator in the order their pairs complete, exactly as in the
sphere-detector node; the static geometry and the error motions are solved with
the functions the solver nodes call, and the error-motion solves start from the
static estimate as the node receives it. Live and offline results on the same
recording therefore agree to numerical precision.

Writes to ``--out`` (default: ``<recording>_calibration``): ``results.json`` (all
estimates with names, units, covariances, status), ``results.mcap`` (the result
topics /ct/observations, /ct/geometry, /ct/error_map, /ct/error_map/single),
``report/`` and ``geometry_export/``. Every file is written to a temporary name
and renamed, so existing good results are never replaced by partial ones; nothing
is written when nothing usable came out.

Exit status: 0 results written (possibly from a partly readable recording: the
problems are printed); 1 nothing usable; 2 bad arguments or files.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np

from ct_calib_nodes.core.ct_pipeline import (DEFAULT_POSITION_TOLERANCE_M, CampaignAccumulator, FrameProcessor,
                                             campaign_error_map, repeatability, solve_campaign_position,
                                             solve_campaign_static, static_result_from_estimate)
from ct_calib_nodes.core.detect import FrameError
from ct_calib_nodes.io import ct_files
from ct_calib_nodes.io.convert import MessageError, array_from_image, stage_from_joint_state, stamp_ns
from ct_calib_nodes.io.mcap_io import ReadReport, RecordingError, iter_recording

IMAGE, STAGE = "/ct/detector/image", "/ct/stage/joint_states"
MODES = ("multi", "single")


@dataclass
class OfflineResult:
    """Everything an offline solve produced."""

    static: object = None                       # StaticResult
    motions: dict = field(default_factory=dict)  # mode -> {k: MotionResult}
    maps: dict = field(default_factory=dict)     # mode -> {definition: ErrorMap} ("travel", "detector")
    map_positions: dict = field(default_factory=dict)  # mode -> position indices ks of the maps
    repeatability: dict = field(default_factory=dict)  # mode -> {definition: [revisit group dicts]}
    frames: list = field(default_factory=list)   # FrameResult per processed frame, in order
    acc: CampaignAccumulator | None = None
    read_report: ReadReport | None = None
    counts: dict = field(default_factory=dict)
    problems: list = field(default_factory=list)
    notes: list = field(default_factory=list)      # what was applied to the inputs (thermal expansion, ...)
    identity: list = field(default_factory=list)   # (reported SRD, message) of every identity initialisation
    detection_modes: dict = field(default_factory=dict)  # windowed detection: frames 'full', 'window', 'fallback'


class _StageClock:
    """CPU seconds per pipeline stage (``timing`` dict of solve_recording), summed over processes."""

    def __init__(self, timing):
        self.t = timing if timing is not None else {}
        for k in ("read", "decode", "detect", "identify", "solve"):
            self.t.setdefault(k, 0.0)

    def add(self, stage, seconds):
        self.t[stage] += seconds


# --- worker processes (parallel replay): decode + detect one frame ---------------------------------
_WORKER: dict = {}
# what a worker imports (FrameProcessor builds a SphereIdentifier: scipy.optimize), for the fork
# server to import once
_WORKER_MODULES = ["ct_calib_nodes.offline", "ct_calib_nodes.core.ct_pipeline", "ct_calib_nodes.core.detect",
                   "ct_calib_nodes.core.identify", "ct_calib_nodes.core.phantom", "ct_calib_nodes.core.track",
                   "ct_calib_nodes.io.raw_replay", "cv2"]


def _worker_init(ref, detector, sdd, flat, init_frames, tolerance, dark=None, track=None):
    try:
        import cv2  # noqa: PLC0415

        cv2.setNumThreads(1)        # one process per core: no thread pool on top
    except ImportError:
        pass
    _WORKER["proc"] = FrameProcessor(ref, detector, sdd, flat, init_frames=init_frames, srd_tolerance_m=tolerance,
                                     dark=dark)
    _WORKER["track"] = _tracker(_WORKER["proc"], track) if track is not None else None


def _tracker(proc, settings):
    from ct_calib_nodes.core.track import TrackingDetector  # noqa: PLC0415

    return TrackingDetector(proc.flat, proc.dark, (proc.detector.rows, proc.detector.cols), settings,
                            proc.detection_settings)


def _decode_detect(proc, tracker, data, srd, key):
    """One frame's CDR bytes or Image message -> (detections or None, problem or None, decode s,
    detect s, detection mode). The mode is 'full', 'window' or 'fallback' with windowed detection
    (``tracker``, ``key``: does a block start here), None without it or when the frame did not
    reach detection."""
    from ct_calib_nodes.io.raw_replay import ImageView  # noqa: PLC0415

    c0 = time.process_time()
    try:
        msg = ImageView.from_cdr(data) if isinstance(data, (bytes, bytearray, memoryview)) else data
        image, enc = array_from_image(msg, (proc.detector.rows, proc.detector.cols))
    except (MessageError, ValueError) as exc:
        return None, str(exc), time.process_time() - c0, 0.0, None
    c1 = time.process_time()
    before = dict(tracker.counts) if tracker is not None else {}
    try:
        if tracker is None:
            det = proc.detect(image, enc, srd)
        else:
            det = tracker.detect(image, enc, proc.diameter_range_px(srd), key=key)
    except FrameError as exc:
        return None, str(exc), c1 - c0, time.process_time() - c1, None
    mode = next((k for k in before if tracker.counts[k] != before[k]), None)
    return det, None, c1 - c0, time.process_time() - c1, mode


def _worker_detect(task):
    """(stamp, CDR bytes of the Image or a _FrameSlots reference, srd, key frame?) in a worker
    process -> ``_decode_detect``'s result. With windowed detection the frames of a block come in
    order to the same worker (its tracker carries the previous frame's shadows)."""
    _t, data, srd, key = task
    if isinstance(data, tuple):
        data = _FrameSlots.view(data)
    res = _decode_detect(_WORKER["proc"], _WORKER["track"], data, srd, key)
    return (*res, (os.getpid(), time.process_time()))      # this process's CPU so far (start-up included)


class _FrameSlots:
    """Fixed-size slots of a shared file in memory (/dev/shm) through which the main process hands
    the frames' CDR bytes to the worker processes: one copy in, read in place there. Sending the
    bytes with the task pickles them through the pool's pipe instead, which cost about 3 ms CPU per
    2 MB frame between the two processes (more than the main process's whole read). A slot is
    reused once its frame's result is back; a frame larger than a slot, or with every slot busy,
    goes through the pipe as before (the same bytes: the same results), and so does every frame
    when the shared file cannot be made (no room in /dev/shm)."""

    MAX_BYTES = 512 << 20

    def __init__(self, n_slots: int, slot_bytes: int):
        import mmap  # noqa: PLC0415

        self.size = -(-int(slot_bytes) // 4096) * 4096
        n = max(1, min(int(n_slots), self.MAX_BYTES // self.size))
        self.mm, self.path, self.free = None, None, []
        shm = "/dev/shm"
        self.sweep_orphans(shm)
        try:
            fd, self.path = tempfile.mkstemp(prefix=f"metro_replay_{os.getpid()}_",
                                             dir=shm if os.path.isdir(shm) else None)
        except OSError:
            return                      # no slots: every frame through the pipe
        try:
            # reserved up front: a tmpfs too small for it (a container's 64 MB /dev/shm) refuses
            # here (ENOSPC) instead of killing the process with SIGBUS at a later write
            os.posix_fallocate(fd, 0, n * self.size)
            self.mm = mmap.mmap(fd, n * self.size)
            self.free = list(range(n - 1, -1, -1))
        except OSError:
            self.close()
        finally:
            os.close(fd)

    def put(self, data):
        """(path, slot, offset, length) of ``data`` copied into a free slot, or None."""
        n = len(data)
        if n > self.size or not self.free:
            return None
        k = self.free.pop()
        self.mm[k * self.size:k * self.size + n] = data
        return self.path, k, k * self.size, n

    def release(self, ref):
        if ref is not None:
            self.free.append(ref[1])

    def close(self):
        if self.mm is not None:
            self.mm.close()
            self.mm = None
        self.free = []
        if self.path is not None:
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass
            self.path = None

    @staticmethod
    def sweep_orphans(shm: str = "/dev/shm") -> list[str]:
        """Remove slot files that a killed replay left (SIGKILL runs no clean-up): their name holds
        the creating process's id; a file of ours whose process is gone is deleted. Returns them."""
        removed = []
        try:
            names = os.listdir(shm)
        except OSError:
            return removed
        for name in names:
            parts = name.split("_")
            if not name.startswith("metro_replay_") or len(parts) < 4 or not parts[2].isdigit():
                continue
            path = os.path.join(shm, name)
            try:
                if os.stat(path).st_uid != os.getuid():
                    continue
                os.kill(int(parts[2]), 0)      # the owner still runs (or is another user's): keep
            except ProcessLookupError:
                try:
                    os.unlink(path)
                    removed.append(path)
                except OSError:
                    pass
            except OSError:
                continue
        return removed

    @staticmethod
    def view(ref):
        """A worker's read-only view of a slot (the file mapped once per process)."""
        import mmap  # noqa: PLC0415

        path, _k, off, n = ref
        maps = _WORKER.setdefault("slots", {})
        if path not in maps:
            with open(path, "rb") as fh:
                maps[path] = memoryview(mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ))
        return maps[path][off:off + n]


def solve_recording(recording, instrument, ref, *, init_frames: int = 6, loss: str = "linear",
                    progress=None, namespace: str = "/",
                    position_tolerance_m: float = DEFAULT_POSITION_TOLERANCE_M,
                    workers: int = 1, timing: dict | None = None, tracking=None) -> OfflineResult:
    """Replay a recording through detection, identity and the solvers (no files written).

    ``namespace``: the cell's namespace in the recording (its raw topics are ``<ns>/ct/...``).
    ``position_tolerance_m``: the stage position segmenter's tolerance (ct_pipeline.PositionSegmenter).
    ``workers`` > 1: image decoding and sphere detection run in that many worker processes
    (the images read as raw bytes and viewed without a copy, io/raw_replay.py); identity, the
    accumulation and the solvers stay in this process and take the frames in recording order,
    so the results are bit for bit those of ``workers`` = 1.
    ``timing``: a dict filled with CPU seconds per stage (read, decode, detect, identify, solve), and
    with ``workers`` > 1 ``worker_processes``: the worker processes' whole CPU time (start-up,
    receiving the frames, decode and detect) up to their last frame.
    ``tracking``: None / False: the full detector on every frame; True or a core.track.TrackSettings:
    windowed detection (core/track.py): the full detector on the whole frame at a key frame (the
    first of a stage position, then every ``block_frames`` frames), on a crop round the previous
    frame's shadows in between, the whole frame again when the crop may have missed something.
    A block (key frame and its followers) goes to one worker, so ``workers`` > 1 gives the same
    results bit for bit as ``workers`` = 1 with the same ``tracking``.
    """
    from ct_calib_nodes.io import namespaces  # noqa: PLC0415

    image_topic, stage_topic = (namespaces.topic(namespace, t) for t in namespaces.CT_RAW)
    say = progress or (lambda _m: None)
    clock = _StageClock(timing)
    out = OfflineResult(read_report=ReadReport(), acc=CampaignAccumulator(position_tolerance_m))
    counts = {"images": 0, "stage_readings": 0, "frames": 0, "bad_frames": 0, "bad_stage": 0, "unpaired": 0}
    proc = FrameProcessor(ref, instrument.detector, instrument.sdd_reported_m, instrument.flat_field(),
                          init_frames=init_frames, srd_tolerance_m=position_tolerance_m, dark=instrument.dark)
    images, stages = {}, {}
    t0 = time.monotonic()
    if tracking is not None and tracking is not False:
        from ct_calib_nodes.core.track import TrackSettings  # noqa: PLC0415

        track = tracking if isinstance(tracking, TrackSettings) else TrackSettings()
        out.detection_modes = {"full": 0, "window": 0, "fallback": 0}
    else:
        track = None
    block = {"n": 0, "srd": None}

    def key_frame(srd):
        """Does a new block start at this frame? (the same rule whichever process detects)"""
        if block["srd"] is None or abs(srd - block["srd"]) > position_tolerance_m \
                or block["n"] >= track.block_frames:
            block["srd"], block["n"] = srd, 0
        block["n"] += 1
        return block["n"] == 1

    def take(results):
        for fr in results:
            out.frames.append(fr)
            ids, uv, sig, minor = fr.accepted()
            idx = np.searchsorted(ref.ids, ids) if len(ids) else np.zeros(0, np.int64)
            out.acc.add_frame(fr.stamp_ns, fr.alpha_rad, fr.srd_reported_m, idx, uv, sig,
                              int(np.count_nonzero(fr.flag)), minor, fr.accepted_systematic())

    def bad_frame(t, text):
        counts["bad_frames"] += 1
        out.problems.append(f"frame {t} ns: skipped: {text}")

    def identify(t, det, alpha, srd):
        c = time.process_time()
        take(proc.push_detections(t, det, alpha, srd))
        clock.add("identify", time.process_time() - c)

    def tick():
        if counts["frames"] % 25 == 0:
            rate = counts["frames"] / max(time.monotonic() - t0, 1e-9)
            say(f"{counts['frames']} frames ({rate:.1f}/s), {len(out.acc.positions)} stage position(s)")

    def paired(t):
        """The stage reading (alpha, srd) of a completed pair, the image; None if unusable."""
        if t not in images or t not in stages:
            return None
        img, js = images.pop(t), stages.pop(t)
        counts["frames"] += 1
        try:
            alpha, srd = stage_from_joint_state(js)
        except MessageError as exc:
            counts["bad_stage"] += 1
            out.problems.append(f"frame {t} ns: bad stage reading: {exc}")
            return None
        try:
            proc.check_stage(alpha, srd)
        except FrameError as exc:
            bad_frame(t, exc)
            return None
        return img, alpha, srd

    types = {image_topic: "sensor_msgs/msg/Image", stage_topic: "sensor_msgs/msg/JointState"}

    def messages(raw):
        if raw:
            from ct_calib_nodes.io.raw_replay import ImageView, iter_recording_raw  # noqa: PLC0415

            it = iter_recording_raw(recording, topics=(image_topic, stage_topic), raw_topics=(image_topic,),
                                    report=out.read_report, types=types)
        else:
            it = iter_recording(recording, topics=(image_topic, stage_topic), report=out.read_report, types=types)
        while True:
            c = time.process_time()
            m = next(it, None)
            if m is None:
                clock.add("read", time.process_time() - c)
                return
            if m.topic == image_topic and raw:
                try:
                    head = ImageView.from_cdr(m.msg)
                except ValueError as exc:
                    out.read_report.messages_undecodable += 1
                    out.problems.append(f"undecodable image at {m.log_time_ns} ns: {exc}")
                    clock.add("read", time.process_time() - c)
                    continue
                t = stamp_ns(head.header.stamp)
                msg = m.msg.obj                         # the message's bytes, not copied
            else:
                t = stamp_ns(m.msg.header.stamp)
                msg = m.msg
            clock.add("read", time.process_time() - c)
            if m.topic == image_topic:
                counts["images"] += 1
                images[t] = msg
            else:
                counts["stage_readings"] += 1
                stages[t] = msg
            yield t

    def detected(t, alpha, srd, res):
        """A frame's ``_decode_detect`` result, taken in recording order: identity, accumulation."""
        det, problem, c_dec, c_det, mode = res
        clock.add("decode", c_dec)
        clock.add("detect", c_det)
        if mode is not None:
            out.detection_modes[mode] += 1
        if problem is not None:
            bad_frame(t, problem)
        else:
            identify(t, det, alpha, srd)

    def frames(raw):
        """(stamp, image message or CDR bytes, alpha, srd, key frame?) of every usable pair, in order."""
        for t in messages(raw=raw):
            n0 = counts["frames"]
            got = paired(t)
            if got is not None:
                img, alpha, srd = got
                yield t, img, alpha, srd, (key_frame(srd) if track is not None else None)
            if counts["frames"] != n0:
                tick()

    if workers <= 1:            # one process: the generic message decoder, detection here
        tracker = _tracker(proc, track) if track is not None else None
        for t, img, alpha, srd, key in frames(raw=False):
            detected(t, alpha, srd, _decode_detect(proc, tracker, img, srd, key))
    else:
        import collections  # noqa: PLC0415
        import multiprocessing  # noqa: PLC0415
        from concurrent.futures import ProcessPoolExecutor  # noqa: PLC0415

        window = collections.deque()            # (stamp, alpha, srd, future, slot), recording order
        slots = None
        worker_cpu = {}                         # pid -> its CPU seconds at its latest frame

        def drain(keep):
            while len(window) > keep:
                t, alpha, srd, fut, slot = window.popleft()
                res = fut.result()
                slots.release(slot)
                worker_cpu[res[5][0]] = res[5][1]
                detected(t, alpha, srd, res[:5])

        ctx = multiprocessing.get_context("forkserver")
        # the fork server imports the workers' modules once; each worker forked from it then starts
        # without importing numpy, scipy, OpenCV and the detector again (no effect once it runs)
        ctx.set_forkserver_preload(_WORKER_MODULES)
        initargs = (ref, instrument.detector, instrument.sdd_reported_m, instrument.flat_field(), init_frames,
                    position_tolerance_m, instrument.dark, track)
        # without tracking one pool shares the frames out; with it, one single-process pool per worker,
        # a whole block (key frame and its followers) to the same one (the one least busy when the
        # block starts: which worker runs a block does not change its results),
        # enough frames in flight that every worker has a block to work on
        if track is None:
            pools = [ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init, initargs=initargs)]
            depth = 4 * workers
        else:
            pools = [ProcessPoolExecutor(1, mp_context=ctx, initializer=_worker_init, initargs=initargs)
                     for _ in range(workers)]
            depth = 3 * workers * (track.block_frames + 1)      # slack for uneven workers
        n_block = 0
        busy = [0] * workers          # frames submitted to each worker and not yet done
        done = collections.deque()    # worker of each finished frame (callbacks; thread-safe appends)
        try:
            for t, img, alpha, srd, key in frames(raw=True):
                if slots is None:       # sized on the first frame: a frame in flight per slot
                    slots = _FrameSlots(depth + 1, len(img))
                slot = slots.put(img)
                data = slot if slot is not None else img
                if track is None:
                    fut = pools[0].submit(_worker_detect, (t, data, srd, None))
                else:
                    while done:
                        busy[done.popleft()] -= 1
                    if key:     # a new block to the worker with the fewest frames in flight
                        n_block = min(range(workers), key=lambda i: busy[i])
                    busy[n_block] += 1
                    fut = pools[n_block].submit(_worker_detect, (t, data, srd, key))
                    fut.add_done_callback(lambda _f, i=n_block: done.append(i))
                window.append((t, alpha, srd, fut, slot))
                drain(depth)
            drain(0)
        finally:
            for pool in pools:
                pool.shutdown(wait=True, cancel_futures=True)
            if slots is not None:
                slots.close()
            clock.t["worker_processes"] = sum(worker_cpu.values())
    c = time.process_time()
    take(proc.flush())
    clock.add("identify", time.process_time() - c)
    out.identity = list(proc.init_messages)
    counts["unpaired"] = len(images) + len(stages)
    if counts["unpaired"]:
        out.problems.append(f"{len(images)} image(s) and {len(stages)} stage reading(s) without a partner")
    out.counts = counts
    out.problems += out.read_report.errors
    say(f"{counts['frames']} frames in {time.monotonic() - t0:.1f} s; "
        f"observations per position {[p.n_obs for p in out.acc.positions]}"
        + (f"; windowed detection, frames by mode {out.detection_modes}" if out.detection_modes else ""))
    from ct_calib_nodes.io.ct_history import incomplete_positions  # noqa: PLC0415
    warn = incomplete_positions(p.n_frames for p in out.acc.positions)
    if warn:
        out.problems.append(warn)
    if not out.acc.positions or out.acc.positions[0].n_frames < 3:
        out.problems.append("fewer than 3 usable frames at the first stage position: nothing to solve")
        return out
    c_solve = time.process_time()
    try:
        return _solve_positions(out, instrument, ref, loss, say)
    finally:
        clock.add("solve", time.process_time() - c_solve)


def _solve_positions(out, instrument, ref, loss, say) -> OfflineResult:
    out.static = solve_campaign_static(out.acc, ref.centres_of_m, instrument.detector,
                                       instrument.sdd_reported_m, loss=loss,
                                       centre_uncertainty_m=ref.center_uncertainty_m)
    say(f"static geometry: {out.static.message}; rms {out.static.rms_px:.4f} px")
    if not out.static.success:
        out.problems.append(f"static geometry not usable: {out.static.message}")
        return out
    # the error-motion node receives the static estimate as published: start from the same thing
    published = static_result_from_estimate(out.static.x, out.static.covariance, ref.centres_of_m,
                                            rms_px=out.static.rms_px, obs=out.acc.positions[0].observations(),
                                            detector=instrument.detector,
                                            centre_uncertainty_m=ref.center_uncertainty_m)
    for mode in MODES:
        out.motions[mode] = {}
        for k in range(1, len(out.acc.positions)):
            try:
                out.motions[mode][k] = solve_campaign_position(out.acc, k, published, instrument.detector,
                                                               mode=mode, loss=loss,
                                                               multi=out.motions.get("multi", {}).get(k))
            except ValueError as exc:
                out.problems.append(f"position {k + 1} ({mode}): {exc}")
        if out.motions[mode]:
            out.maps[mode] = {}
            for definition in ("travel", "detector"):
                em, ks = campaign_error_map(out.acc, out.motions[mode], published, definition=definition, name=mode,
                                            index_repeatability_rad=instrument.index_repeatability_rad)
                out.maps[mode][definition] = em
                out.map_positions[mode] = ks
                out.repeatability.setdefault(mode, {})[definition] = repeatability(em, ks,
                                                                                   out.acc.srd_tolerance_m)
    say(f"error motions solved at {len(out.motions.get('multi', {}))} position(s)")
    return out


def _result_dict(res, instrument, ref, recording, files) -> dict:
    from ct_calib_nodes.core.geometry import MOTION_PARAM_UNITS  # noqa: PLC0415

    d = {"recording": str(recording), "files": {k: str(v) for k, v in files.items()},
         "units": "SI (m, rad); covariance in products of the parameter units",
         "counts": res.counts, "problems": res.problems, "notes": res.notes,
         "stage_positions": [{"index": k, "srd_reported_m": p.srd_reported_m, "frames": p.n_frames,
                              "srd_reading_range_m": float(np.ptp(p.srd_readings_m)),
                              "first_stamp_ns": int(min(p.stamps_ns)), "last_stamp_ns": int(max(p.stamps_ns)),
                              "observations": p.n_obs, "rejected_detections": p.n_rejected}
                             for k, p in enumerate(res.acc.positions)],
         "stage_position_rule": (f"positions split on motion in time: a reported SRD more than "
                                 f"{res.acc.srd_tolerance_m:g} m from the current position's median reading starts "
                                 f"a new position; a return to an earlier SRD is a new position (a revisit)"),
         "repeatability": res.repeatability,
         "detection": ({"windowed": True, "frames_by_mode": res.detection_modes} if res.detection_modes
                       else {"windowed": False}),
         "identity": [{"srd_reported_m": srd, "message": m} for srd, m in res.identity],
         "static": res.static.to_dict() if res.static is not None else None, "error_motions": {}, "error_maps": {}}
    for mode, by_k in res.motions.items():
        d["error_motions"][mode] = {str(k): dict(r.to_dict(), units=list(MOTION_PARAM_UNITS))
                                    for k, r in sorted(by_k.items())}
    for mode, by_def in res.maps.items():
        d["error_maps"][mode] = {definition: dict(em.to_dict(), positions=res.map_positions[mode])
                                 for definition, em in by_def.items()}
    return d


def offline_campaign_id(namespace, res):
    """The campaign id of an offline solve, as the live nodes form it: ``<cell>@<first frame stamp ns>``."""
    from ct_calib_nodes.io.ct_history import campaign_id_of  # noqa: PLC0415

    return campaign_id_of(namespace, res)


def _write_result_mcap(path, res, instrument, namespace: str = "/"):
    """The result topics, as the live graph publishes them (in the cell's namespace)."""
    from ct_calib_nodes.io.namespaces import topic as ns_topic  # noqa: PLC0415

    from builtin_interfaces.msg import Time  # noqa: PLC0415

    from ct_calib_nodes.io.mcap_io import QOS_RELIABLE_LATCHED, Rosbag2McapWriter  # noqa: PLC0415
    from ct_calib_nodes.io.observations_out import observation_array_msg  # noqa: PLC0415
    from ct_calib_nodes.io.results import error_map_msg, estimate_msg, geometry_msg  # noqa: PLC0415

    def stamp(ns):
        return Time(sec=int(ns) // 1_000_000_000, nanosec=int(ns) % 1_000_000_000)

    last = max(fr.stamp_ns for fr in res.frames)
    campaign_id = offline_campaign_id(namespace, res)
    with Rosbag2McapWriter(path) as w:
        w.add_topic(ns_topic(namespace, "ct/observations"), "metro_msgs/msg/SphereObservationArray")
        for fr in res.frames:
            w.write(ns_topic(namespace, "ct/observations"), observation_array_msg(fr, stamp(fr.stamp_ns), instrument.detector), fr.stamp_ns)
        w.add_topic(ns_topic(namespace, "ct/geometry"), "metro_msgs/msg/CtGeometry", QOS_RELIABLE_LATCHED)
        p0 = res.acc.positions[0]
        w.write(ns_topic(namespace, "ct/geometry"), geometry_msg(res.static, p0.srd_reported_m, instrument.sdd_reported_m,
                                             instrument.detector, stamp(last), n_rejected=p0.n_rejected,
                                             campaign_id=campaign_id), last)
        for mode, topic in (("multi", ns_topic(namespace, "ct/error_map")),
                            ("single", ns_topic(namespace, "ct/error_map/single"))):
            if mode not in res.maps:
                continue
            em, ks = res.maps[mode]["travel"], res.map_positions[mode]
            motions = [estimate_msg(res.motions[mode][k], f"ct_error_motion/{mode}", stamp(last)) for k in ks[1:]]
            w.add_topic(topic, "metro_msgs/msg/ErrorMap", QOS_RELIABLE_LATCHED)
            w.write(topic, error_map_msg(em, mode, motions, stamp(last), campaign_id=campaign_id,
                                         geometry_stamp=stamp(last), final=True), last)


def write_outputs(out_dir, res: OfflineResult, instrument, ref, recording, files, reference_path=None,
                  namespace: str = "/"):
    """Write everything into a temporary directory, then move each file into out_dir."""
    from ct_calib_nodes.core.ct_pipeline import campaign_residuals  # noqa: PLC0415
    from ct_calib_nodes.io.atomic import staged_outputs  # noqa: PLC0415
    from ct_calib_nodes.io.campaign_outputs import write_report_and_export  # noqa: PLC0415
    from ct_calib_nodes.io.results import write_json_atomic  # noqa: PLC0415

    out_dir = pathlib.Path(out_dir)
    with staged_outputs(out_dir) as tmp:
        write_json_atomic(tmp / "results.json", _result_dict(res, instrument, ref, recording, files))
        _write_result_mcap(tmp / "results.mcap", res, instrument, namespace)
        if "multi" in res.maps:
            series = [res.maps[mode]["travel"] for mode in MODES if mode in res.maps] + [res.maps["multi"]["detector"]]
            em, ks = res.maps["multi"]["travel"], res.map_positions["multi"]
            motions = np.zeros((len(ks), 6))
            for i, k in enumerate(ks[1:], start=1):
                motions[i] = res.motions["multi"][k].x
            resid = campaign_residuals(res.acc, res.static.x, res.static.centres_of_m, instrument.detector,
                                       {k: m.x for k, m in res.motions["multi"].items() if m.success},
                                       terms=res.static.terms,
                                       label="static model (k = 1) and multi-projection error motions (k > 1)")
            s = res.static
            write_report_and_export(
                tmp, names=s.names, units=s.units, values=s.x, covariance=s.covariance, geometry=s.geometry,
                series=series, motions=motions, srd_reported_m=em.srd_reported_m, detector=instrument.detector,
                reference_path=reference_path, residuals=resid,
                meta={"recording": str(recording), "instrument file": str(files["instrument"]),
                      "reference object file": str(files["reference_object"]),
                      "frames": res.counts.get("frames"), "problems": len(res.problems),
                      "stage positions": f"{len(res.acc.positions)} (split on motion in time, tolerance "
                                         f"{res.acc.srd_tolerance_m:g} m)",
                      "repeatability (revisits, multi, travel)": repeatability_text(
                          res.repeatability.get("multi", {}).get("travel", []))})
    return out_dir


def repeatability_text(groups) -> str:
    """One line per revisited nominal SRD: positioning and straightness differences to the first visit."""
    if not groups:
        return "no stage position was revisited"
    parts = []
    for g in groups:
        d = []
        for f, lab in (("positioning_m", "positioning"), ("straightness_x_m", "straightness x"),
                       ("straightness_y_m", "straightness y")):
            u = g["u_" + f] or [float("nan")] * len(g[f])
            d.append(lab + " " + ", ".join(f"{v * 1e6:+.2f} um (u {s * 1e6:.2f})" for v, s in zip(g[f], u)))
        pos = ", ".join(str(k + 1) for k in g["positions"])
        parts.append(f"SRD {g['srd_reported_m'][0] * 1e3:.3f} mm, positions {pos}: " + "; ".join(d))
    return " | ".join(parts)


def _track_settings(n: int):
    if n <= 0:
        return None
    from ct_calib_nodes.core.track import TrackSettings  # noqa: PLC0415

    return TrackSettings(block_frames=n)


def default_workers() -> int:
    """Worker processes for detection: the cores this process may use, at most 8."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:
        n = os.cpu_count() or 1
    return max(1, min(8, n))


def _find_file(given, recording: pathlib.Path, name: str, default):
    if given:
        return pathlib.Path(given), "given"
    base = recording if recording.is_dir() else recording.parent
    if (base / name).is_file():
        return base / name, "found beside the recording"
    return default(), "package default (no file beside the recording)"


@dataclass
class RecordingFiles:
    """The YAML files a recording is solved with, where each came from, the thermal note."""

    instrument_path: pathlib.Path
    instrument_how: str
    reference_path: pathlib.Path
    reference_how: str
    instrument: object
    ref: object
    thermal_note: str


def load_recording_files(recording: pathlib.Path, instrument=None, reference_object=None) -> RecordingFiles:
    """The instrument and reference-object files of a recording: given, else beside it, else the
    package defaults; the reference object at the scan temperature. Raises ct_files.CtFileError."""
    inst_path, how_i = _find_file(instrument, recording, "ct_instrument.yaml", ct_files.default_instrument_path)
    ref_path, how_r = _find_file(reference_object, recording, "reference_object.yaml",
                                 ct_files.default_reference_object_path)
    inst = ct_files.load_instrument(inst_path)
    ref, note = ct_files.reference_at_scan(ct_files.load_reference_object(ref_path), inst)
    return RecordingFiles(inst_path, how_i, ref_path, how_r, inst, ref, note)


def cli_recording_files(prog: str, args):
    """The command-line tools' first step: (recording path, RecordingFiles) from ``args.recording``,
    ``args.instrument`` and ``args.reference_object``, or None after saying on stderr, as ``prog``,
    what is missing or wrong (the caller exits 2)."""
    rec = pathlib.Path(args.recording)
    if not rec.exists():
        print(f"{prog}: no recording at {rec}", file=sys.stderr)
        return None
    try:
        return rec, load_recording_files(rec, args.instrument, args.reference_object)
    except ct_files.CtFileError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return None


def _store_history(db, res, rec, files, namespace, source="offline"):
    """Every offline solve (usable or not) goes into the calibration history; a history that cannot be
    written is reported, the results are still written."""
    from ct_calib_nodes.io.ct_history import offline_records, store_offline  # noqa: PLC0415
    from ct_calib_nodes.io.history import open_history  # noqa: PLC0415

    if res.static is None:
        return []
    h = open_history(db or None, logger=lambda m: print(f"[offline] {m}"))
    if h is None:
        return []
    try:
        stored = store_offline(h, offline_records(res, recording=rec, files=files, cell=namespace, source=source))
        print(f"[offline] history {h.path}: solve(s) {[s.id for s in stored]} (cell {namespace})")
        return stored
    except Exception as exc:  # noqa: BLE001
        print(f"[offline] calibration history not recorded: {exc}")
        return []
    finally:
        h.close()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("recording", help=".mcap file or rosbag2 directory")
    ap.add_argument("--instrument", help="ct_instrument.yaml")
    ap.add_argument("--reference-object", help="reference_object.yaml")
    ap.add_argument("--reference-error-map", help="independent reference error map (CSV/YAML) for delta plots")
    ap.add_argument("--out", help="output directory (default <recording>_calibration)")
    ap.add_argument("--init-frames", type=int, default=6, help="frames used to initialise sphere identity")
    ap.add_argument("--position-tolerance", type=float, default=DEFAULT_POSITION_TOLERANCE_M,
                    help="a reported SRD further than this from the current stage position's median reading "
                         "starts a new position [m] (above the read-back jitter, below the smallest step)")
    ap.add_argument("--workers", type=int, default=default_workers(),
                    help="processes that decode and detect frames (1 = all in this process; the results are "
                         "the same bit for bit) [default: the usable cores, at most 8]")
    ap.add_argument("--track", type=int, default=0, metavar="N",
                    help="windowed detection (core/track.py): the whole frame every N frames and at each stage "
                         "position's first frame, a crop round the previous frame's shadows in between (0 = the "
                         "whole frame always; results within a small fraction of the centre sd of it) [default 0]")
    ap.add_argument("--loss", default="linear", help="least-squares loss: linear, huber, soft_l1, cauchy, arctan")
    ap.add_argument("--namespace", help="the CT cell's namespace in the recording (e.g. /cell_a); default: the only "
                                        "one whose <ns>/ct/detector/image is in it")
    ap.add_argument("--history", default="", help="calibration history database (default $METRO_HISTORY_DB or "
                                                  "~/.local/share/metro_cell/history.sqlite; none = do not record)")
    args = ap.parse_args(argv)
    got = cli_recording_files("ct_offline_solve", args)
    if got is None:
        return 2
    rec, f = got
    inst_path, how_i, ref_path, how_r = f.instrument_path, f.instrument_how, f.reference_path, f.reference_how
    instrument, ref, thermal_note = f.instrument, f.ref, f.thermal_note
    from ct_calib_nodes.io import namespaces  # noqa: PLC0415
    try:
        namespace = namespaces.find_namespace(rec, args.namespace)
    except (ValueError, FileNotFoundError) as exc:
        print(f"ct_offline_solve: {exc}", file=sys.stderr)
        return 2
    print(f"[offline] instrument file {inst_path} ({how_i}); reference object {ref_path} ({how_r})")
    if namespace != "/":
        print(f"[offline] CT cell namespace {namespace}")
    print(f"[offline] {thermal_note}")
    out_dir = pathlib.Path(args.out) if args.out else rec.parent / f"{rec.stem}_calibration"
    if not (args.position_tolerance > 0 and np.isfinite(args.position_tolerance)):
        print(f"ct_offline_solve: --position-tolerance must be a positive length [m], got {args.position_tolerance}",
              file=sys.stderr)
        return 2
    try:
        res = solve_recording(rec, instrument, ref, init_frames=args.init_frames, loss=args.loss,
                              progress=lambda m: print(f"[offline] {m}", flush=True), namespace=namespace,
                              position_tolerance_m=args.position_tolerance, workers=max(1, args.workers),
                              tracking=_track_settings(args.track))
    except RecordingError as exc:      # nothing readable at all (empty folder, not MCAP)
        print(f"ct_offline_solve: {exc}", file=sys.stderr)
        return 2
    res.notes.append(thermal_note)
    print(f"[offline] recording: {res.read_report.summary()}")
    for span in res.read_report.lost:
        print(f"[offline] lost: {span.describe()}")
    for p in res.problems[:20]:
        print(f"[offline] problem: {p}")
    if len(res.problems) > 20:
        print(f"[offline] ... and {len(res.problems) - 20} more problems (all in results.json)")
    _store_history(args.history, res, rec, {"instrument": inst_path, "reference_object": ref_path}, namespace)
    if res.static is None or not res.static.success:
        print("[offline] nothing usable: no results written")
        return 1
    write_outputs(out_dir, res, instrument, ref, rec, {"instrument": inst_path, "reference_object": ref_path},
                  reference_path=args.reference_error_map, namespace=namespace)
    print(f"[offline] results: {out_dir / 'results.json'}; report: {out_dir / 'report' / 'index.html'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
