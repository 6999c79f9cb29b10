"""The one stage-command builder used by the calibration node and RosCell (io/convert.py)."""

import numpy as np
import pytest

from picms_nodes.io.convert import stage_command


def test_stage_command_one_point_xyz():
    m = stage_command(np.array([0.01, -0.02, 0.125]))
    assert list(m.joint_names) == ["x", "y", "z"]
    assert len(m.points) == 1
    assert list(m.points[0].positions) == [0.01, -0.02, 0.125]


@pytest.mark.parametrize("q", [[0.0, 0.0], [0.0, np.nan, 0.0], [0.0, 0.0, np.inf]])
def test_stage_command_refuses_bad_targets(q):
    with pytest.raises(ValueError, match="three finite positions"):
        stage_command(q)
