"""Cells under ROS namespaces: the CT cell's topic names, resolved in a namespace, and the namespace
a recording was made under.

Every node of the cell uses relative names (``ct/detector/image``, ``ct/geometry``, ...), so
``--ros-args -r __ns:=/cell_a`` moves a whole cell to ``/cell_a/ct/...``; in the root namespace
the names are INTERFACES.md's (``/ct/detector/image``). Offline tools take ``--namespace`` or
find the one namespace a recording's raw topics are under.
"""

from __future__ import annotations

import pathlib

#: the CT cell's topics, relative names (resolved against the cell's namespace)
CT_RAW = ("ct/detector/image", "ct/stage/joint_states")
CT_RESULTS = ("ct/observations", "ct/geometry", "ct/error_map", "ct/error_map/single")


def normalise(namespace) -> str:
    """'' / '/' -> '/', 'cell_a' / '/cell_a/' -> '/cell_a'."""
    ns = "/" + str(namespace or "").strip().strip("/")
    for part in ns.strip("/").split("/"):
        if part and not (part[0].isalpha() or part[0] == "_") or not all(c.isalnum() or c == "_" for c in part):
            raise ValueError(f"invalid ROS namespace {namespace!r}: parts are letters, digits and _, "
                             "not starting with a digit")
    return ns


def topic(namespace, relative: str) -> str:
    """The fully qualified name of a relative topic in a namespace."""
    ns = normalise(namespace)
    return ("" if ns == "/" else ns) + "/" + relative.lstrip("/")


def recording_topics(path) -> dict:
    """{topic: message count or None} of a recording (.mcap file or rosbag2 directory), from the
    rosbag2 metadata or the MCAP summary, else by scanning the channel records."""
    import yaml  # noqa: PLC0415

    from ct_calib_nodes.io.mcap_io import recording_files  # noqa: PLC0415

    p = pathlib.Path(path)
    meta = p / "metadata.yaml" if p.is_dir() else None
    if meta is not None and meta.is_file():
        try:
            info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
            out = {t["topic_metadata"]["name"]: t.get("message_count") for t in info.get("topics_with_message_count", [])}
            if out:
                return out
        except Exception:  # noqa: BLE001 - fall back to the files themselves
            pass
    out = {}
    for f in recording_files(p):
        with open(f, "rb") as fh:
            try:
                from mcap.reader import make_reader  # noqa: PLC0415
                summary = make_reader(fh).get_summary()
            except Exception:  # noqa: BLE001 - truncated: no summary
                summary = None
            if summary is not None and summary.channels:
                counts = summary.statistics.channel_message_counts if summary.statistics else {}
                for cid, ch in summary.channels.items():
                    out[ch.topic] = (out.get(ch.topic) or 0) + counts.get(cid, 0)
                continue
            fh.seek(0)
            from mcap.reader import StreamReader  # noqa: PLC0415
            from mcap.records import Channel  # noqa: PLC0415
            try:
                for rec in StreamReader(fh, skip_magic=False).records:
                    if isinstance(rec, Channel):
                        out.setdefault(rec.topic, None)
            except Exception:  # noqa: BLE001 - keep what was read
                pass
    return out


def find_namespace(path, namespace=None) -> str:
    """The namespace of the CT cell in a recording: the given one (checked), else the only one whose
    raw image topic is present ('/' when none is: the solve then reports what it could not find).
    ValueError naming the candidates when there are several, or the given one is absent."""
    topics = recording_topics(path)
    suffix = "/" + CT_RAW[0]
    found = sorted(t[: -len(suffix)] or "/" for t in topics if t.endswith(suffix))
    if namespace is not None:
        ns = normalise(namespace)
        if topic(ns, CT_RAW[0]) not in topics:
            raise ValueError(f"the recording has no {topic(ns, CT_RAW[0])}; CT cells in it: {found or 'none'}")
        return ns
    if len(found) == 1:
        return found[0]
    if not found:
        return "/"     # nothing of a CT cell readable (a stub, a foreign file): the solve says what it found
    raise ValueError(f"the recording holds several CT cells {found}: choose one with --namespace")
