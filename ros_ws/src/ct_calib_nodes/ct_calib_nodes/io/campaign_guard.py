"""One campaign at a time: identity of a campaign and refusal of interleaved or non-monotonic data.

A campaign is a sequence of stage positions visited once each, in one direction of travel, with
frame stamps that do not go back. Observations that break this (a second cell publishing on the
same topics, a replay started while a campaign runs, the stage returning to a position already
left) would silently merge into one error map; the guard refuses them with a reason, and the node
counts and logs them (a second frame at a rotary angle already seen at the current position is
refused too: two campaigns at the same positions). The campaign id is ``<cell>@<first stamp ns>``, carried into the history
with every result of the campaign.
"""

from __future__ import annotations


class CampaignGuard:
    def __init__(self, cell: str = "/", srd_tolerance_m: float = 1e-6):
        self.cell = cell
        self.tol = float(srd_tolerance_m)
        self.srds: list = []          # reported SRD of each position, in visiting order
        self.first_ns = None
        self.angles: set = set()      # rotary angles seen at the current position (rounded to 1 nrad)
        self.refused = 0

    @property
    def campaign_id(self) -> str | None:
        return None if self.first_ns is None else f"{self.cell}@{self.first_ns}"

    def check(self, stamp_ns: int, srd_m: float, alpha_rad: float) -> str | None:
        """None when the frame belongs to the campaign, else why it is refused (counted). Nothing is
        recorded: call :meth:`accept` once the frame was taken (a message refused for another reason
        must not block its valid repetition). Frames of one position may arrive in any stamp order."""
        srd_m = float(srd_m)
        key = round(float(alpha_rad) * 1e9)
        why = None
        if self.srds and abs(srd_m - self.srds[-1]) > self.tol:
            earlier = [k for k, s in enumerate(self.srds[:-1]) if abs(s - srd_m) <= self.tol]
            direction = (self.srds[-1] - self.srds[-2]) if len(self.srds) >= 2 else 0.0
            if earlier:
                why = (f"SRD {srd_m * 1e3:.3f} mm returns to position {earlier[0] + 1} after the stage left it: "
                       "interleaved or repeated campaign")
            elif direction and (srd_m - self.srds[-1]) * direction < 0:
                why = (f"SRD {srd_m * 1e3:.3f} mm reverses the direction of travel "
                       f"({self.srds[-2] * 1e3:.3f} -> {self.srds[-1] * 1e3:.3f} mm): non-monotonic campaign")
        elif self.srds and key in self.angles:
            why = (f"a second frame at rotary angle {alpha_rad:.6f} rad at position {len(self.srds)} "
                   f"(SRD {srd_m * 1e3:.3f} mm): another campaign or cell on these topics")
        if why is not None:
            self.refused += 1
        return why

    def accept(self, stamp_ns: int, srd_m: float, alpha_rad: float) -> None:
        """Record a frame the node took (after :meth:`check` returned None)."""
        srd_m = float(srd_m)
        if not self.srds or abs(srd_m - self.srds[-1]) > self.tol:
            self.srds.append(srd_m)
            self.angles = set()
        self.angles.add(round(float(alpha_rad) * 1e9))
        self.first_ns = int(stamp_ns) if self.first_ns is None else min(self.first_ns, int(stamp_ns))

    def reset(self):
        self.__init__(self.cell, self.tol)
