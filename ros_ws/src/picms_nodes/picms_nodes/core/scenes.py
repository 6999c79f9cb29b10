"""Planar parts seen by the Pixel Probe cameras: chrome-on-glass targets and a flange face.

A `PlanarPart` is a set of 2-D features in the part's top plane (z = 0 of the part frame)
placed in the stage frame by `R_stage_part` (columns: part axes in the stage frame) and
`p_stage_part` (part origin), as fixed in the stage frame at encoder reading 0 (the cameras
ride on the stage, the part does not). `part_truth(part)` gives the ground truth (feature
centres, sizes, corners, dots, plane pose) in the part and the stage frame, for the tests of
targeting and measurement. Rendering (`render.render_frame(..., part=...)`) ray-casts every
pixel near an edge onto the plane with the true lens (`plane_signal`), so the images are true
perspective.

Lighting:
- `bright_field` (chrome on glass, transmitted light): the features are chrome, dark
  (physics.dark_level) on the bright back-lit glass (physics.bright_level).
- `dark_field` (flange face, low-angle ring light): the face and the holes are dark
  (`face_level`); every edge of the material (outer edge, holes, aperture) carries a bright
  band (`band_level`) of width `band_m` on the material side (the edge break / chamfer that
  scatters the grazing light into the lens). The true edge (bore, aperture, outer diameter)
  is the band's boundary away from the material; the band's other boundary lies `band_m`
  into the face.

Feature types (all in part metres): circle (diameter), square (side), rectangle (size
[sx, sy]), each with an in-plane `rotation` (rad), and dot_grid (rows x cols dots of
`diameter` at `pitch`, rotated by `rotation` about its centre).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .camera import rotvec_to_matrix


@dataclass(frozen=True)
class Feature:
    id: str
    type: str                       # circle | square | rectangle | dot_grid
    center: tuple                   # (x, y) in the part frame, m
    size: tuple                     # circle/dot_grid: (diameter,), square: (side,), rectangle: (sx, sy)
    rotation: float = 0.0           # rad, in-plane
    rows: int = 0
    cols: int = 0
    pitch: float = 0.0

    def __post_init__(self):
        if self.type not in ("circle", "square", "rectangle", "dot_grid"):
            raise ValueError(f"feature {self.id!r}: unknown type {self.type!r}")
        if any(not s > 0 for s in self.size):
            raise ValueError(f"feature {self.id!r}: sizes must be > 0, got {self.size}")
        if self.type == "dot_grid" and (self.rows < 1 or self.cols < 1 or not self.pitch > self.size[0]):
            raise ValueError(f"feature {self.id!r}: dot grid needs rows, cols >= 1 and pitch > diameter")

    def _local(self, x, y):
        c, s = np.cos(self.rotation), np.sin(self.rotation)
        dx, dy = x - self.center[0], y - self.center[1]
        return c * dx + s * dy, -s * dx + c * dy

    def sdf(self, x, y):
        """Signed distance (m) of part points to the feature's boundary, negative inside."""
        if self.type == "circle":
            return np.hypot(x - self.center[0], y - self.center[1]) - self.size[0] / 2
        u, v = self._local(x, y)
        if self.type == "dot_grid":
            iu = np.clip(np.rint(u / self.pitch + (self.cols - 1) / 2), 0, self.cols - 1)
            iv = np.clip(np.rint(v / self.pitch + (self.rows - 1) / 2), 0, self.rows - 1)
            return np.hypot(u - (iu - (self.cols - 1) / 2) * self.pitch,
                            v - (iv - (self.rows - 1) / 2) * self.pitch) - self.size[0] / 2
        hx, hy = (self.size[0] / 2, self.size[0] / 2) if self.type == "square" else (self.size[0] / 2, self.size[1] / 2)
        qx, qy = np.abs(u) - hx, np.abs(v) - hy
        return np.hypot(np.maximum(qx, 0), np.maximum(qy, 0)) + np.minimum(np.maximum(qx, qy), 0)

    def radius_bound(self) -> float:
        """Radius (m) of a circle about `center` that contains the feature."""
        if self.type == "circle":
            return self.size[0] / 2
        if self.type == "dot_grid":
            return np.hypot(self.cols - 1, self.rows - 1) * self.pitch / 2 + self.size[0] / 2
        sx, sy = (self.size[0], self.size[0]) if self.type == "square" else self.size
        return float(np.hypot(sx, sy) / 2)

    def corners_part(self) -> np.ndarray:
        """(4, 2) corners of a square/rectangle in the part frame (counter-clockwise)."""
        sx, sy = (self.size[0], self.size[0]) if self.type == "square" else self.size
        c, s = np.cos(self.rotation), np.sin(self.rotation)
        loc = np.array([[-sx, -sy], [sx, -sy], [sx, sy], [-sx, sy]]) / 2
        return loc @ np.array([[c, s], [-s, c]]) + np.asarray(self.center)

    def dots_part(self) -> np.ndarray:
        """(rows * cols, 2) dot centres in the part frame, row by row."""
        c, s = np.cos(self.rotation), np.sin(self.rotation)
        iv, iu = np.mgrid[0:self.rows, 0:self.cols]
        loc = np.column_stack([(iu.ravel() - (self.cols - 1) / 2) * self.pitch,
                               (iv.ravel() - (self.rows - 1) / 2) * self.pitch])
        return loc @ np.array([[c, s], [-s, c]]) + np.asarray(self.center)


@dataclass(frozen=True)
class PlanarPart:
    name: str
    lighting: str                   # bright_field | dark_field
    R_stage_part: np.ndarray
    p_stage_part: np.ndarray
    features: tuple                 # bright_field: chrome features; dark_field: holes (material removed)
    outer: Feature | None = None    # dark_field: the material's outer boundary
    band_m: float = 60e-6           # dark_field: bright edge band width on the material side
    face_level: float = 8.0         # dark_field: face and holes, DN before vignetting
    band_level: float = 180.0       # dark_field: edge bands, DN before vignetting
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.lighting not in ("bright_field", "dark_field"):
            raise ValueError(f"part {self.name!r}: lighting must be bright_field or dark_field, got {self.lighting!r}")
        R = np.asarray(self.R_stage_part, float)
        if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-9):
            raise ValueError(f"part {self.name!r}: R_stage_part is not a rotation matrix")
        object.__setattr__(self, "R_stage_part", R)
        object.__setattr__(self, "p_stage_part", np.asarray(self.p_stage_part, float).reshape(3))

    def sdf(self, x, y):
        """Signed distance (m) to the region that gives signal: chrome (bright field) or material (dark field)."""
        if self.lighting == "bright_field":
            d = self.features[0].sdf(x, y)
            for f in self.features[1:]:
                d = np.minimum(d, f.sdf(x, y))
            return d
        d = self.outer.sdf(x, y) if self.outer is not None else np.full(np.shape(x), -1.0)
        for f in self.features:
            d = np.maximum(d, -f.sdf(x, y))
        return d

    def to_stage(self, xy) -> np.ndarray:
        """Part-plane points (N, 2) -> stage frame (N, 3)."""
        xy = np.atleast_2d(np.asarray(xy, float))
        return xy @ self.R_stage_part[:, :2].T + self.p_stage_part

    def bound_points_part(self) -> np.ndarray:
        """Points (N, 2) in the part plane whose hull contains everything drawn."""
        feats = list(self.features) + ([self.outer] if self.outer is not None else [])
        a = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        ring = np.column_stack([np.cos(a), np.sin(a)]) / np.cos(np.pi / 16)
        return np.vstack([np.asarray(f.center) + (f.radius_bound() + self.band_m) * ring for f in feats])


def part_pose(position_stage=(0.0, 0.0, 0.0), tilt_rotvec_xy=(0.0, 0.0), in_plane_rad=0.0):
    """(R_stage_part, p_stage_part): a tilt (rotation vector [tx, ty, 0], rad) after an in-plane rotation."""
    c, s = np.cos(in_plane_rad), np.sin(in_plane_rad)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    R = rotvec_to_matrix([tilt_rotvec_xy[0], tilt_rotvec_xy[1], 0.0]) @ Rz
    return R, np.asarray(position_stage, float).reshape(3)


def chrome_targets(position_stage=(0.0, 0.0, 0.0), tilt_rotvec_xy=(0.0, 0.0), in_plane_rad=0.0) -> PlanarPart:
    """Chrome-on-glass plate: 5 and 7 mm squares and circles, and a 5 x 5 grid of 250 um dots at 500 um pitch."""
    R, p = part_pose(position_stage, tilt_rotvec_xy, in_plane_rad)
    feats = (Feature("sq5", "square", (-0.009, 0.008), (0.005,)),
             Feature("sq7", "square", (0.009, 0.008), (0.007,)),
             Feature("c5", "circle", (-0.009, -0.008), (0.005,)),
             Feature("c7", "circle", (0.009, -0.008), (0.007,)),
             Feature("grid", "dot_grid", (0.0, 0.0), (0.00025,), rows=5, cols=5, pitch=0.0005))
    return PlanarPart("chrome_targets", "bright_field", R, p, feats)


def flange_face(position_stage=(0.0, 0.0, 0.0), tilt_rotvec_xy=(0.0, 0.0), in_plane_rad=0.0) -> PlanarPart:
    """Flange face, 30 mm outer diameter: 10 x 5 mm rectangular aperture, four 3.4 mm screw
    holes on a 22 mm circle, two 2 mm pin holes; dark-field light (bright edge bands)."""
    R, p = part_pose(position_stage, tilt_rotvec_xy, in_plane_rad)
    holes = [Feature("aperture", "rectangle", (0.0, 0.0), (0.010, 0.005))]
    for k in range(4):
        a = np.pi / 4 + k * np.pi / 2
        holes.append(Feature(f"screw_{k + 1}", "circle", (0.011 * np.cos(a), 0.011 * np.sin(a)), (0.0034,)))
    holes.append(Feature("pin_1", "circle", (0.0, 0.0095), (0.002,)))
    holes.append(Feature("pin_2", "circle", (0.0, -0.0095), (0.002,)))
    return PlanarPart("flange", "dark_field", R, p, tuple(holes), outer=Feature("outer", "circle", (0.0, 0.0), (0.030,)))


def part_truth(part: PlanarPart) -> dict:
    """Ground truth of a part: plane pose and every feature's centre, size, corners or dots
    (part frame and stage frame, m). Holes in dark field are listed with `hole: true`."""
    feats = []
    allf = [(f, part.lighting == "dark_field") for f in part.features]
    if part.outer is not None:
        allf.append((part.outer, False))
    for f, hole in allf:
        d = {"id": f.id, "type": f.type, "hole": hole, "center_part": np.asarray(f.center, float),
             "center_stage": part.to_stage(f.center)[0], "rotation": float(f.rotation)}
        if f.type in ("circle", "dot_grid"):
            d["diameter"] = float(f.size[0])
        elif f.type == "square":
            d["side"] = float(f.size[0])
        else:
            d["size"] = np.asarray(f.size, float)
        if f.type in ("square", "rectangle"):
            d["corners_part"] = f.corners_part()
            d["corners_stage"] = part.to_stage(d["corners_part"])
        if f.type == "dot_grid":
            d.update(rows=f.rows, cols=f.cols, pitch=float(f.pitch), dots_part=f.dots_part(),
                     dots_stage=part.to_stage(f.dots_part()))
        feats.append(d)
    return {"name": part.name, "lighting": part.lighting, "R_stage_part": part.R_stage_part.copy(),
            "p_stage_part": part.p_stage_part.copy(), "normal_stage": part.R_stage_part[:, 2].copy(),
            "band_m": part.band_m if part.lighting == "dark_field" else 0.0, "features": feats}


SCENES = ("smr", "empty", "wire", "chrome_targets", "flange")


def make_part(scene: str, position_stage=(0.0, 0.0, 0.0), tilt_rotvec_xy=(0.0, 0.0), in_plane_rad=0.0):
    """The part of a named scene (None for smr, empty, wire)."""
    if scene not in SCENES:
        raise ValueError(f"unknown scene {scene!r}; one of {SCENES}")
    if scene == "chrome_targets":
        return chrome_targets(position_stage, tilt_rotvec_xy, in_plane_rad)
    if scene == "flange":
        return flange_face(position_stage, tilt_rotvec_xy, in_plane_rad)
    return None
