"""Constants shared by the CT core tests (a module of its own: `from conftest import ...`
picks whichever conftest.py pytest loaded first when several test directories are collected)."""

SIGMA_PX = 0.05   # pixel noise of the simulated centres: the detection target [px]
N_VIEWS = 360     # projections per full turn in the shared simulated data
# Radius of the shadow contour the simulated detector fits [m]: its half-depth iso-transmission
# contour lies inside the 1.5 mm silhouette (a 3 mm steel sphere at 100 keV transmits 42 % at its
# centre). The observations are the centres of that contour's ellipse, with their semi-minor axes.
CONTOUR_RADIUS_M = 1.1e-3
