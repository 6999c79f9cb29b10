"""The cells whose offline tools are fuzzed, for reliab_fuzz.

A CellSpec gives ``make(folder) -> (recording path, entries)`` (entries: the messages written, as
(topic, type name, rclpy message, log time), for message-level rewrites) and its offline tools.
To add the Pixel Probe cell: write its small-recording function (a few frames of each camera and
the tracker readings, its YAML files beside the .mcap) and a CellSpec listing its offline entry
points (e.g. ``picms_nodes.offline:main``) with their documented exit statuses; the engine, the
mutant kinds and the outcome table need no change.
"""

from __future__ import annotations

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

CELLS = {"ct": CT}
