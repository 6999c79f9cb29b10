"""Shared fixtures of the renderer tests (all named render_*)."""

import numpy as np
import pytest

from ct_calib_nodes.core.geometry import DetectorSpec
from ct_calib_nodes.core.phantom import ReferenceObject

SRD_M = 0.364        # paper's first stage position
SDD_M = 1.04821      # paper's source-to-detector distance


@pytest.fixture
def render_ideal_w():
    """Factory: perfectly aligned instrument, {OF} origin on the axis at source height."""
    def make(srd_m=SRD_M, sdd_m=SDD_M):
        return np.array([srd_m, 0.0, 0.0, sdd_m, 0.0, 0.0, 0.0, 0.0, 0.0, srd_m, 0.0, 0.0, 0.0])
    return make


@pytest.fixture
def render_one_sphere():
    """Factory: a ReferenceObject with spheres at the given {OF} centres, no tube."""
    def make(centres_of_m, diameter_m=0.003, tube=None):
        c = np.atleast_2d(np.asarray(centres_of_m, dtype=float))
        return ReferenceObject(name="test", ids=np.arange(1, len(c) + 1), centres_of_m=c,
                               diameters_m=np.full(len(c), diameter_m), tube=tube)
    return make


@pytest.fixture
def render_small_detector():
    """Odd-sized detector: its geometric centre is the centre of pixel (50, 50)."""
    return DetectorSpec(cols=101, rows=101, pixel_pitch_m=0.0004)


@pytest.fixture
def render_detector():
    return DetectorSpec(cols=1024, rows=1024, pixel_pitch_m=0.0004)
