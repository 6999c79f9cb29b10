"""The cells whose offline tools are fuzzed, for reliab_fuzz.

A CellSpec gives ``make(folder) -> (recording path, entries)`` (entries: the messages written, as
(topic, type name, rclpy message, log time), for message-level rewrites) and its offline tools.
A cell is its small-recording function (its YAML files beside the .mcap) and a CellSpec listing
its offline entry points with their documented exit statuses; the engine, the mutant kinds and
the outcome table are the same for every cell. Cells: ``ct`` (ct_offline_solve) and ``picms``
(picms_calibrate_offline).
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass

from reliab_fuzz import ToolSpec


@dataclass
class CellSpec:
    name: str
    make: object            # callable(folder, **size) -> (path, entries)
    tools: list
    chunk_size: int = 48 * 1024


def _ct_make(folder, full=True):
    from reliab_recordings import ct_recording

    entries = []
    path = ct_recording(folder, n_positions=2 if full else 1, n_proj=5 if full else 8, messages=entries)
    return path, entries


CT = CellSpec(
    name="ct",
    make=_ct_make,
    tools=[ToolSpec("ct_offline_solve", "ct_calib_nodes.offline:main",
                    lambda rec, out: [rec, "--out", out],
                    {0: "results written", 1: "nothing usable", 2: "bad arguments or files"})],
)

def _picms_make(folder, full=True):
    from reliab_recordings import picms_recording

    entries = []
    # full: the reduced sensor at 480x360; small: 320x240 (same field of view), fewer tracker readings
    kw = {} if full else {"width": 320, "height": 240, "tracker_rate_hz": 10.0, "joint_rate_hz": 5.0}
    path = picms_recording(folder, messages=entries, **kw)
    return path, entries


PICMS = CellSpec(
    name="picms",
    make=_picms_make,
    tools=[ToolSpec("picms_calibrate_offline", "picms_nodes.offline:main",
                    lambda rec, out: [rec, "--cell", str(pathlib.Path(rec).parent / "picms_cell.yaml"),
                                      "--out", str(pathlib.Path(out) / "picms_calibration.yaml")],
                    {0: "calibrated and written", 1: "no calibration (reason printed)",
                     2: "bad arguments or unreadable cell file",
                     3: "calibrated, POOR_FIT: not written"})],
)

CELLS = {"ct": CT, "picms": PICMS}
