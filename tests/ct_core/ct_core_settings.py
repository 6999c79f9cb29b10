"""Constants shared by the CT core tests (a module of its own: `from conftest import ...`
picks whichever conftest.py pytest loaded first when several test directories are collected)."""

SIGMA_PX = 0.05   # pixel noise of the simulated centres: the detection target [px]
N_VIEWS = 360     # projections per full turn in the shared simulated data
