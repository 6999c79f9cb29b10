"""A node's campaign journal (io/journal.py) on the ROS side: what it accepted, replayed at restart.

Parameters (JOURNAL_PARAMS): ``journal_dir`` (empty = ``$METRO_JOURNAL_DIR`` or ``journal/``
beside the history database; ``none`` = no journal), ``journal_fsync`` (fsync every record: survives
a power cut of the host, costs a disk sync per message), ``resume_gap_s``.

At start a journal that is not final is replayed through the node's own message callback (the
node's state is rebuilt exactly as it was) and the node logs which data it needs again: the
frames stamped after the journal's last one that were published while it was down. The first
live message then decides: it continues the journaled campaign (stamp not before the journal's
first, at most ``resume_gap_s`` after its last, the campaign guard does not see the stage return
or reverse, and a frame at a rotary angle already held is a re-sent one: same stamp), or a new campaign has begun: the old journal is set aside (the node's
``reset_campaign()`` is called, the file replaced) and the message starts the new one.
"""

from __future__ import annotations

JOURNAL_PARAMS = {
    "journal_dir": ("", "campaign journal folder (restart recovery); empty = $METRO_JOURNAL_DIR or journal/ "
                        "beside the history database; none = off [path]"),
    "journal_fsync": (False, "fsync every journal record (survives a host power cut; one disk sync per message)"),
    "resume_gap_s": (600.0, "a journaled campaign is resumed when the first new observation is stamped at most "
                            "this long after the journal's last one [s]"),
}


def _stamp_ns(msg) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


class CampaignJournal:
    def __init__(self, node, node_name: str, msg_type, history_db: str = ""):
        from ct_calib_nodes.io.journal import DISABLED, Journal, JournalError, default_dir, journal_path  # noqa: PLC0415

        self.node, self.msg_type = node, msg_type
        self.log = node.get_logger()
        self.replaying = False
        self.pending_check = False        # the first live message after a resume decides
        self.first_ns = self.last_ns = None
        self.stamps: set = set()
        self.j = None
        d = str(node.get_parameter("journal_dir").value or "").strip()
        if d.lower() in DISABLED:
            return
        from ct_calib_nodes.io.history import cell_name  # noqa: PLC0415

        path = journal_path(d or default_dir(history_db), cell_name(node.get_namespace()), node_name)
        j = Journal(path, node_name, cell_name(node.get_namespace()),
                    fsync=bool(node.get_parameter("journal_fsync").value))
        try:
            j.read()
        except (JournalError, OSError, ValueError) as exc:      # unreadable: kept aside, a new one begun
            self.log.error(f"campaign journal unreadable, not resumed: {exc}")
            try:
                path.replace(path.with_suffix(".journal.bad"))
            except OSError:
                pass
            j = Journal(path, node_name, cell_name(node.get_namespace()), fsync=j.fsync)
        if j.damaged:
            self.log.warning(j.damaged)
        self.j = j
        self.resume = [] if (j.final or not j.messages) else list(j.messages)
        try:
            if self.resume:
                j.open_append()
            else:
                j.start_new()
        except OSError as exc:
            self.log.error(f"campaign journal {path} cannot be written ({exc}): no restart recovery")
            self.j = None
        if self.j is not None:
            self.log.info(f"campaign journal: {path}")

    # --- replay ----------------------------------------------------------------------------------
    def replay(self, on_msg) -> int:
        """Feed the journaled messages to ``on_msg``; returns how many."""
        if not self.resume:
            return 0
        from rclpy.serialization import deserialize_message  # noqa: PLC0415

        self.replaying = True
        n = 0
        try:
            for data in self.resume:
                msg = deserialize_message(data, self.msg_type)
                stamp = _stamp_ns(msg)
                self.first_ns = stamp if self.first_ns is None else min(self.first_ns, stamp)
                self.last_ns = stamp if self.last_ns is None else max(self.last_ns, stamp)
                self.stamps.add(stamp)
                on_msg(msg)
                n += 1
        finally:
            self.replaying = False
        self.pending_check = True
        self.log.warning(
            f"resumed the journaled campaign: {n} accepted message(s) replayed, stamps "
            f"{self.first_ns / 1e9:.3f} .. {self.last_ns / 1e9:.3f} s. Needed again: every frame stamped after "
            f"{self.last_ns / 1e9:.3f} s published while this node was down (re-send them, e.g. replay the "
            f"recording from that stamp); a campaign that does not continue within {self._gap():.0f} s of it "
            "starts anew")
        self.resume = []
        return n

    def _gap(self) -> float:
        return float(self.node.get_parameter("resume_gap_s").value)

    def continues(self, msg, guard) -> bool:
        """Called for the live messages: False when ``msg`` begins a new campaign instead of continuing
        the resumed one (only the first live message after a resume is checked)."""
        if not self.pending_check:
            return True
        self.pending_check = False
        try:
            stamp = _stamp_ns(msg)
            why = guard.check(stamp, msg.srd_reported_m, msg.rotary_angle_rad)
        except (TypeError, ValueError, AttributeError):
            self.pending_check = True      # a bad message decides nothing
            return True
        if why is not None:
            guard.refused -= 1             # only a question here; the node's own check counts
        gap = self._gap()
        # a frame at an angle already held is a re-send when its stamp is a journaled one (refused by the guard
        # as a duplicate, harmless), else the first frame of another campaign at the same positions
        new = stamp < self.first_ns or stamp > self.last_ns + gap * 1e9 or (
            why is not None and (why.startswith("SRD") or stamp not in self.stamps))
        self.stamps = set()
        if new:
            self.log.warning(f"a new campaign begins (first observation stamped {stamp / 1e9:.3f} s; journaled "
                             f"campaign {self.first_ns / 1e9:.3f} .. {self.last_ns / 1e9:.3f} s"
                             + (f"; {why}" if why else "") + "): the journaled one is closed unfinished")
            if self.j is not None:
                try:
                    self.j.start_new()
                except OSError as exc:
                    self.log.error(f"campaign journal cannot be renewed ({exc}): no restart recovery")
                    self.j = None
            return False
        return True

    # --- appends ---------------------------------------------------------------------------------
    def accepted(self, msg):
        if self.j is None or self.replaying:
            return
        from rclpy.serialization import serialize_message  # noqa: PLC0415
        try:
            self.j.append_message(serialize_message(msg))
        except (OSError, ValueError) as exc:
            self.log.error(f"campaign journal append failed ({exc}): restart recovery off from here")
            self.j.close()
            self.j = None

    def event(self, event: str, **info):
        if self.j is None or self.replaying:
            return
        try:
            self.j.append_event(event, n_messages=len(self.j.messages), **info)
        except (OSError, ValueError) as exc:
            self.log.error(f"campaign journal append failed ({exc}): restart recovery off from here")
            self.j.close()
            self.j = None

    def events(self, event: str) -> list:
        return [] if self.j is None else [e for e in self.j.events if e.get("event") == event]

    def close(self):
        if self.j is not None:
            self.j.close()
