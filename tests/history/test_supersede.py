"""A verdict after the solve (issue 11: the discrepancy engine finds the geometry's model inadequate) is
kept in the history as a superseding record: the original row untouched, latest_valid no longer returns
the withdrawn solve, and the record names what it supersedes."""
from ct_calib_nodes.io.history import History, Input, Quantity, SolveRecord


def _geo(cell="/c", t=1):
    return SolveRecord(cell=cell, kind="ct_geometry", status="success", message="converged",
                       result={"static": {"x": [t]}, "ros_msg": {"type": "x", "cdr_b64": ""}}, campaign_id="c@1",
                       data_start_ns=10 * t, data_end_ns=20 * t, inputs=[Input(role="recording", path="/r", sha256="ab")],
                       quantities=[Quantity(name="z_R", value=0.1 * t, u=1e-6, unit="m")])


def test_supersede_keeps_the_original_and_withdraws_it(tmp_path):
    with History(tmp_path / "h.sqlite") as h:
        older = h.record(_geo(t=1))
        geo = h.record(_geo(t=2))
        assert h.latest_valid("/c", "ct_geometry").uid == geo.uid
        assert not h.superseded(geo.uid)
        sup = h.supersede(geo, "poor_fit", "converged; model inadequate", {"verdict": "drift found"})
        # the original row is unchanged, and still readable
        again = h.get(geo.uid)
        assert again is not None and again.status == "success" and again.message == "converged"
        # the superseding record: status, link, copied quantities and stamps, no stale message bytes
        assert sup.status == "poor_fit" and sup.status_code == 5 and sup.id > geo.id
        assert sup.result["supersedes"]["uid"] == geo.uid and sup.result["verdict"] == "drift found"
        assert "ros_msg" not in sup.result
        assert (sup.data_start_ns, sup.data_end_ns, sup.campaign_id) == (20, 40, "c@1")
        stored = h.list(kind="ct_geometry", status="poor_fit", with_details=True)
        assert len(stored) == 1
        roles = {i.role: i for i in stored[0].inputs}
        assert roles["supersedes"].ref_uid == geo.uid and roles["recording"].sha256 == "ab"
        assert [(q.name, q.value) for q in h.quantities(stored[0].id)] == [("z_R", 0.2)]
        assert h.superseded(geo.uid) and not h.superseded(older.uid)
        # the newest valid geometry is now the older one, never the withdrawn one
        assert h.latest_valid("/c", "ct_geometry").uid == older.uid
        assert h.count() == 3
