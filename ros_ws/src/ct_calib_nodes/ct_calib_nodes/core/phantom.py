"""Reference objects for CT geometry calibration (spheres on a carbon-fibre tube).

The default object, :func:`helix49`, follows the seed paper's design (Ferrucci
et al. 2020, section 3 and Fig. 2): 49 steel spheres glued to the outer
circumference of a carbon-fibre cylinder in a multi-helix arrangement, so that
few sphere shadows overlap over a full rotation.

Object frame {OF} (paper, section 3): origin on the cylinder axis at
mid-height, +Y along the cylinder axis, +Z from the axis toward sphere 1,
+X = Y x Z.

Nothing here imports ROS; YAML files are read and written by the io layer,
which can use :meth:`ReferenceObject.to_yaml_dict` for the INTERFACES.md
structure.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Attenuation estimates (mono-energetic equivalent of a 150-225 kV tungsten
# spectrum filtered by ~1 mm Cu, effective energy about 100 keV):
#   iron, mu/rho(100 keV) = 0.3717 cm^2/g (NIST XCOM / Hubbell & Seltzer,
#   NISTIR 5632, X-ray mass attenuation coefficients, Table 3, Z = 26);
#   steel density 7.87 g/cm^3  ->  mu = 2.925 /cm = 292.5 /m.
#   graphite / carbon, mu/rho(100 keV) = 0.1514 cm^2/g (same table, Z = 6);
#   CFRP density ~1.55 g/cm^3 (epoxy matrix ~1.2, fibres ~1.8; the epoxy's
#   H and O change mu/rho by < 5 % at 100 keV)  ->  mu = 0.235 /cm = 23.5 /m.
MU_STEEL_100KEV_PER_M = 292.5
MU_CFRP_100KEV_PER_M = 23.5


def _ro_array(a) -> np.ndarray:
    a = np.array(a, dtype=float, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class CarbonTube:
    """Hollow carbon-fibre cylinder that carries the spheres.

    The tube's axis is the {OF} Y axis; it spans Y in [-height/2, +height/2]
    (open ends, no caps).

    Attributes
    ----------
    outer_radius_m, inner_radius_m : float
        Radii of the wall [m], ``0 <= inner < outer``.
    height_m : float
        Length along {OF} Y [m].
    mu_per_m : float
        Linear attenuation coefficient of the wall [1/m] (see module constants).
    material : str
        Free text.
    """

    outer_radius_m: float = 0.036
    inner_radius_m: float = 0.035
    height_m: float = 0.110
    mu_per_m: float = MU_CFRP_100KEV_PER_M
    material: str = "CFRP"

    def __post_init__(self):
        vals = (self.outer_radius_m, self.inner_radius_m, self.height_m, self.mu_per_m)
        if not all(np.isfinite(v) for v in vals):
            raise ValueError("CarbonTube dimensions must be finite")
        if not (0.0 <= self.inner_radius_m < self.outer_radius_m):
            raise ValueError(
                f"need 0 <= inner_radius_m < outer_radius_m, got {self.inner_radius_m}, {self.outer_radius_m}")
        if self.height_m <= 0 or self.mu_per_m < 0:
            raise ValueError("height_m must be > 0 and mu_per_m >= 0")


@dataclass(frozen=True)
class ReferenceObject:
    """A calibrated reference object: sphere centres and diameters in {OF}.

    Attributes
    ----------
    name : str
    ids : ndarray of shape (N,), int
        Sphere identifiers, unique.
    centres_of_m : ndarray of shape (N, 3)
        Sphere centres in {OF} [m] (the CMM-calibrated values).
    diameters_m : ndarray of shape (N,)
        Sphere diameters [m], positive.
    material : str
        Sphere material (``sphere_material`` in the YAML file).
    center_uncertainty_m : ndarray of shape (N,) or None
        Standard uncertainty of each calibrated centre [m].
    temperature_K : float or None
        Temperature at calibration [K].
    thermal_expansion_per_K : float or None
        Linear expansion coefficient of the object's frame [1/K] (optional
        ``thermal_expansion`` in the YAML file): the centres scale by
        ``1 + alpha (T - temperature_K)`` about their centroid.
    tube : CarbonTube or None
        The carrier cylinder, rendered as a faint absorber if not None. It is
        not part of the YAML contract (a real object's file does not carry it).
    """

    name: str
    ids: np.ndarray
    centres_of_m: np.ndarray
    diameters_m: np.ndarray
    material: str = "steel"
    center_uncertainty_m: np.ndarray | None = None
    temperature_K: float | None = None
    tube: CarbonTube | None = field(default=None)
    thermal_expansion_per_K: float | None = None

    def __post_init__(self):
        ids = np.asarray(self.ids)
        if ids.ndim != 1 or ids.size == 0:
            raise ValueError(f"ids must have shape (N,) with N >= 1, got {ids.shape}")
        if not np.issubdtype(ids.dtype, np.integer):
            if not np.all(np.isfinite(ids.astype(float))) or np.any(ids.astype(float) != np.round(ids.astype(float))):
                raise ValueError("ids must be integers")
        ids = ids.astype(np.int64)
        n = ids.size
        if np.unique(ids).size != n:
            raise ValueError("ids must be unique")
        c = np.asarray(self.centres_of_m, dtype=float)
        if c.shape != (n, 3):
            raise ValueError(f"centres_of_m must have shape ({n}, 3), got {c.shape}")
        if not np.all(np.isfinite(c)):
            raise ValueError("centres_of_m contains NaN or inf")
        d = np.asarray(self.diameters_m, dtype=float)
        if d.ndim == 0:
            d = np.full(n, float(d))
        if d.shape != (n,):
            raise ValueError(f"diameters_m must have shape ({n},), got {d.shape}")
        if not np.all(np.isfinite(d)) or np.any(d <= 0):
            raise ValueError("diameters_m must be finite and positive")
        u = self.center_uncertainty_m
        if u is not None:
            u = np.asarray(u, dtype=float)
            if u.ndim == 0:
                u = np.full(n, float(u))
            if u.shape != (n,) or not np.all(np.isfinite(u)) or np.any(u < 0):
                raise ValueError(f"center_uncertainty_m must be (N,) = ({n},) finite, >= 0")
            u = _ro_array(u)
        t = self.temperature_K
        if t is not None and not (np.isfinite(t) and t > 0):
            raise ValueError(f"temperature_K must be positive, got {t}")
        a = self.thermal_expansion_per_K
        if a is not None and not (np.isfinite(a) and abs(a) < 1e-3):
            raise ValueError(f"thermal_expansion_per_K must be finite and |alpha| < 1e-3 /K, got {a}")
        if self.tube is not None and not isinstance(self.tube, CarbonTube):
            raise ValueError("tube must be a CarbonTube or None")
        ids.setflags(write=False)
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "centres_of_m", _ro_array(c))
        object.__setattr__(self, "diameters_m", _ro_array(d))
        object.__setattr__(self, "center_uncertainty_m", u)
        object.__setattr__(self, "temperature_K", None if t is None else float(t))

    @property
    def n_spheres(self) -> int:
        return int(self.ids.size)

    def at_temperature(self, temperature_K):
        """The object at another temperature: (ReferenceObject, note saying what was done).

        The centres scale by ``1 + alpha (T - T_cal)`` about their centroid (a uniform expansion;
        the point it is taken about only moves the pose, which the solvers estimate). Without a
        temperature, a calibration temperature or an expansion coefficient nothing is changed
        and the note says which is missing.
        """
        from dataclasses import replace  # noqa: PLC0415

        if temperature_K is None:
            return self, "thermal expansion not applied: the instrument file gives no object temperature"
        missing = [k for k, v in (("temperature", self.temperature_K),
                                  ("thermal_expansion", self.thermal_expansion_per_K)) if v is None]
        if missing:
            return self, (f"thermal expansion NOT applied although the object is at {float(temperature_K):.2f} K: "
                          f"the reference object file lacks {' and '.join(missing)}")
        dt = float(temperature_K) - self.temperature_K
        scale = 1.0 + self.thermal_expansion_per_K * dt
        c = self.centres_of_m
        centroid = c.mean(axis=0)
        out = replace(self, centres_of_m=centroid + scale * (c - centroid), temperature_K=float(temperature_K))
        return out, (f"thermal expansion applied: {dt:+.2f} K from the calibration temperature "
                     f"{self.temperature_K:.2f} K, alpha {self.thermal_expansion_per_K:.3g} /K, "
                     f"centres scaled by {scale - 1.0:+.3g}")

    @property
    def radii_m(self) -> np.ndarray:
        """Sphere radii [m], shape (N,)."""
        return self.diameters_m / 2.0

    def to_yaml_dict(self) -> dict:
        """The INTERFACES.md ``reference_object.yaml`` structure (plain Python types)."""
        spheres = []
        for i in range(self.n_spheres):
            s = {
                "id": int(self.ids[i]),
                "center": [float(v) for v in self.centres_of_m[i]],
                "diameter": float(self.diameters_m[i]),
            }
            if self.center_uncertainty_m is not None:
                s["center_uncertainty"] = float(self.center_uncertainty_m[i])
            spheres.append(s)
        out = {
            "name": str(self.name),
            "units": "SI",
            "frame": "object",
            "sphere_material": str(self.material),
        }
        if self.temperature_K is not None:
            out["temperature"] = float(self.temperature_K)
        if self.thermal_expansion_per_K is not None:
            out["thermal_expansion"] = float(self.thermal_expansion_per_K)
        out["spheres"] = spheres
        return out


# Multi-helix layout of helix49 (see helix49 docstring and doc/ct_render.md).
HELIX49_RADIUS_M = 0.0375          # sphere-centre radius: tube outer radius + sphere radius
HELIX49_DIAMETER_M = 0.003
HELIX49_Y_SPAN_M = (-0.048, 0.048)
# Azimuth step between height-neighbours. Chosen by scanning the step in
# 0.005 rad increments over [0, pi] for the lowest fraction of overlapping
# shadows over a rotation at the default scenario geometry, among layouts
# whose largest azimuth gap is below 2.5 x 360/49 deg (so the spheres cover
# the circumference). Near-opposite neighbours give a double helix.
HELIX49_TURN_RAD = 3.07


def multi_helix_centres(n: int, radius_m: float, y_min_m: float, y_max_m: float,
                        step_rad: float) -> np.ndarray:
    """Sphere centres of a (multi-)helix on a cylinder about {OF} Y.

    Sphere ``i`` (0-based) sits at height ``y_min + i * (y_max - y_min) / (n - 1)``
    and azimuth ``i * step_rad`` measured from +Z toward +X, so sphere 0 lies
    on +Z. With ``step_rad`` near ``2 pi m / h`` the spheres form ``h``
    interleaved helices.

    Returns
    -------
    ndarray of shape (n, 3) [m]
    """
    i = np.arange(n)
    y = y_min_m + (y_max_m - y_min_m) * i / max(n - 1, 1)
    az = i * step_rad
    return np.stack([radius_m * np.sin(az), y, radius_m * np.cos(az)], axis=1)


def helix49(center_uncertainty_m: float | None = 1.0e-6) -> ReferenceObject:
    """The default 49-sphere multi-helix reference object.

    49 steel spheres of 3 mm diameter glued to a CFRP tube (outer radius
    36 mm, wall 1 mm, length 110 mm); the centres lie at radius 37.5 mm
    (tube radius + sphere radius: the spheres touch the tube), heights from
    -48 mm to +48 mm in 2 mm steps. Consecutive spheres in height are
    ``HELIX49_TURN_RAD`` = 3.07 rad (175.9 deg) apart in azimuth: the spheres
    nearest in height sit nearly opposite each other, and the odd and even
    spheres form two interleaved helices (4 mm rise, -8.2 deg azimuth per
    sphere, each turning by 197 deg over the height; largest azimuth gap
    8.2 deg). This keeps shadow overlaps rare (about 3 % of sphere views
    over 360 views at the default scenario geometry, see doc/ct_render.md).
    Sphere 1 is on +Z of {OF} at the bottom (y = -48 mm).

    Parameters
    ----------
    center_uncertainty_m : float or None
        Stated CMM standard uncertainty of each centre [m] (MPE 2 um / 2).

    Returns
    -------
    ReferenceObject
    """
    c = multi_helix_centres(49, HELIX49_RADIUS_M, *HELIX49_Y_SPAN_M, HELIX49_TURN_RAD)
    return ReferenceObject(
        name="helix49",
        ids=np.arange(1, 50),
        centres_of_m=c,
        diameters_m=np.full(49, HELIX49_DIAMETER_M),
        material="steel",
        center_uncertainty_m=center_uncertainty_m,
        temperature_K=293.15,
        tube=CarbonTube(),
    )
