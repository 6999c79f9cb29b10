"""One campaign at a time (interleaved / non-monotonic refused), one status vocabulary, and an unknown
covariance published empty (never NaNs)."""
import types

import numpy as np
import pytest

from ct_calib_nodes.core import static_solver
from ct_calib_nodes.io import history, results
from ct_calib_nodes.io.campaign_guard import CampaignGuard
from ct_calib_nodes.io.ct_history import incomplete_positions


def test_guard_accepts_one_campaign_in_any_stamp_order_within_a_position():
    g = CampaignGuard("/cell_a")
    alphas = np.arange(4) * np.pi / 2
    for k, srd in enumerate((0.364, 0.436, 0.508)):
        for j in (2, 0, 3, 1):                       # DDS repairs reorder frames of a position
            assert g.check(1000 * k + j, srd, alphas[j]) is None
            g.accept(1000 * k + j, srd, alphas[j])
    assert g.refused == 0 and g.campaign_id == "/cell_a@0"


def test_guard_refuses_interleaved_and_non_monotonic():
    g = CampaignGuard()

    def take(t, srd, a):
        why = g.check(t, srd, a)
        if why is None:
            g.accept(t, srd, a)
        return why

    assert take(1, 0.364, 0.0) is None
    assert take(2, 0.364, 0.5) is None
    assert "second frame at rotary angle" in take(3, 0.364, 0.0)      # another cell at the same position
    assert take(4, 0.436, 0.0) is None
    assert "returns to position 1" in take(5, 0.364, 1.0)            # back to a position already left
    assert take(6, 0.508, 0.0) is None
    assert "reverses the direction" in take(7, 0.470, 0.0)
    assert g.refused == 3


def test_guard_check_alone_records_nothing():
    """A message the node refuses for another reason (bad values) must not block its valid repetition."""
    g = CampaignGuard()
    assert g.check(1, 0.364, 0.0) is None          # checked, then refused by the intake: not accepted
    assert g.check(2, 0.364, 0.0) is None
    g.accept(2, 0.364, 0.0)
    assert g.check(3, 0.364, 0.0) is not None


def test_incomplete_positions_named():
    assert incomplete_positions([36, 36, 36]) is None
    w = incomplete_positions([30, 36, 24])
    assert "position(s) 1 (30 of 36), 3 (24 of 36)" in w


def test_one_status_vocabulary():
    from metro_msgs.msg import SolveStatus
    codes = {"success": SolveStatus.SUCCESS, "not_converged": SolveStatus.NOT_CONVERGED,
             "degenerate": SolveStatus.DEGENERATE, "insufficient_data": SolveStatus.INSUFFICIENT_DATA,
             "failed": SolveStatus.FAILED, "poor_fit": SolveStatus.POOR_FIT}
    assert results.OUTCOME_CODES == codes == history.STATUS_WORDS == static_solver.OUTCOME_CODES
    # result files: "status" is the outcome word, never the optimiser's code next to "success"
    assert static_solver.status_fields(True, "success", 4) == {"status": "success", "status_code": 0, "lm_status": 4}
    assert static_solver.status_fields(False, "poor_fit", 1) == {"status": "poor_fit", "status_code": 5, "lm_status": 1}
    assert static_solver.status_fields(False, "success", 1)["status"] == "failed"


@pytest.mark.parametrize("cov", [np.full((2, 2), np.nan), None, np.zeros((0, 0))])
def test_unknown_covariance_is_empty(cov):
    res = types.SimpleNamespace(names=["a", "b"], units=["m", "m"], x=np.zeros(2), covariance=cov,
                                covariance_total=None, success=False, outcome="failed", message="m", n_iter=0,
                                nfev=0, n_obs=0, rms_px=np.nan, cost=np.nan, condition=np.nan)
    from builtin_interfaces.msg import Time
    m = results.estimate_msg(res, "t", Time())
    assert list(m.covariance) == [] and m.status.code == 4
