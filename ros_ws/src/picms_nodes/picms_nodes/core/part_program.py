"""part_program.yaml (INTERFACES.md, PiCMS): load, validate, and plan the points to measure.

The format is fixed by INTERFACES.md. Two optional keys are added (documented in
doc/picms_measure.md):

- per circle / square / rectangle `material: inside | outside` (default: `inside` in bright
  field: the chrome IS the feature; `outside` in dark field: the features are holes in the
  face). The dark-field edge band lies on the material side; the true edge is the band's
  boundary away from the material, so the locator must know which side that is.
- per circle / square / rectangle `rotation` (rad, default 0), as for dot grids.
- `edge_band_m` (top level or per feature, dark field only): the width of the bright edge band
  (the edge break / chamfer, a drawing value). When given, the edge fits fix it; when absent it
  is estimated from free fits of the band (doc/picms_measure.md: with the blur close to the
  band's width that estimate scatters by +-10 um, i.e. +-5 um on each edge).

Planned points (`plan`): `points_per_side` points on every edge of a square / rectangle
(spread over the middle 70 % of the side, away from the corners), `points` points on a
circle rim (equal angles from the part +x axis), every dot of a dot grid (row by row), and the
plane fitted from every measured point (no points of its own).
"""
from __future__ import annotations

import math
import pathlib
from dataclasses import dataclass, field

import numpy as np
import yaml

FEATURE_TYPES = ("square", "rectangle", "circle", "dot_grid", "plane")
LIGHTINGS = ("bright_field", "dark_field")


class PartProgramError(ValueError):
    """A part program that cannot be run; the message names the bad key or feature."""


@dataclass(frozen=True)
class FeatureSpec:
    id: str
    type: str                               # square | rectangle | circle | dot_grid | plane
    center: tuple = (0.0, 0.0)              # part frame, m
    rotation: float = 0.0                   # rad, in-plane
    size: tuple = ()                        # square (side,), rectangle (sx, sy), circle (diameter,)
    points_per_side: int = 0
    points: int = 0
    rows: int = 0
    cols: int = 0
    pitch: float = 0.0
    dot_diameter: float = 0.0
    material: str = "inside"                # which side of the edge is material (chrome / face)
    band_m: float | None = None             # dark field: edge band width (m) when given

    @property
    def half_sizes(self) -> tuple:
        if self.type == "square":
            return (self.size[0] / 2, self.size[0] / 2)
        if self.type == "rectangle":
            return (self.size[0] / 2, self.size[1] / 2)
        raise AttributeError("half_sizes: only squares and rectangles")

    def radius_bound(self) -> float:
        if self.type == "circle":
            return self.size[0] / 2
        if self.type in ("square", "rectangle"):
            return float(np.hypot(*self.half_sizes))
        if self.type == "dot_grid":
            return float(np.hypot(self.cols - 1, self.rows - 1) * self.pitch / 2 + self.dot_diameter / 2)
        return 0.0

    def dots_part(self) -> np.ndarray:
        """(rows * cols, 2) nominal dot centres, row by row (index = row * cols + col)."""
        c, s = math.cos(self.rotation), math.sin(self.rotation)
        iv, iu = np.mgrid[0:self.rows, 0:self.cols]
        loc = np.column_stack([(iu.ravel() - (self.cols - 1) / 2) * self.pitch,
                               (iv.ravel() - (self.rows - 1) / 2) * self.pitch])
        return loc @ np.array([[c, s], [-s, c]]) + np.asarray(self.center)


@dataclass(frozen=True)
class PartProgram:
    part: str
    lighting: str
    origin_at_stage: np.ndarray             # (3,) encoder reading with X* on the part origin
    tolerance: float                        # m
    rotation_about_normal: float | None     # rad, None: unknown (found from the images)
    features: tuple                         # FeatureSpec, in program order
    source: str = ""
    raw: dict = field(default_factory=dict, repr=False)   # the parsed YAML (kept with measurements)

    def feature(self, fid: str) -> FeatureSpec:
        for f in self.features:
            if f.id == fid:
                return f
        raise KeyError(fid)


@dataclass(frozen=True)
class PlannedPoint:
    """One point to measure. `xy_part` nominal (part frame, m); for edge points `normal_part`
    is the in-plane unit normal pointing INTO the material, `tangent_part` along the edge."""
    feature_id: str
    kind: str                               # edge | dot
    index: int
    xy_part: np.ndarray
    normal_part: np.ndarray = field(default_factory=lambda: np.zeros(2))
    tangent_part: np.ndarray = field(default_factory=lambda: np.zeros(2))
    side: int = -1                          # square/rectangle: side 0..3 (+x, +y, -x, -y); dots: -1
    grid_rc: tuple = (-1, -1)               # dot grid: (row, col)
    curvature_radius: float = 0.0           # circle rim: radius (m); straight edges: 0


def _num(v, where, *, positive=False, integer=False):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        raise PartProgramError(f"{where}: expected a finite number, got {v!r}")
    if integer and (float(v) != int(v)):
        raise PartProgramError(f"{where}: expected an integer, got {v!r}")
    if positive and not v > 0:
        raise PartProgramError(f"{where}: must be > 0, got {v!r}")
    return int(v) if integer else float(v)


def _vec(v, n, where):
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise PartProgramError(f"{where}: expected a list of {n} numbers, got {v!r}")
    return tuple(_num(x, f"{where}[{i}]") for i, x in enumerate(v))


def _feature(d, k, lighting, band_default=None) -> FeatureSpec:
    where = f"features[{k}]"
    if not isinstance(d, dict):
        raise PartProgramError(f"{where}: expected a mapping, got {d!r}")
    fid = d.get("id")
    if not isinstance(fid, str) or not fid:
        raise PartProgramError(f"{where}: missing or empty 'id'")
    where = f"feature {fid!r}"
    typ = d.get("type")
    if typ not in FEATURE_TYPES:
        raise PartProgramError(f"{where}: 'type' must be one of {FEATURE_TYPES}, got {typ!r}")
    allowed = {"id", "type"}
    if typ == "plane":
        extra = set(d) - allowed
        if extra:
            raise PartProgramError(f"{where}: unknown keys {sorted(extra)} for a plane")
        return FeatureSpec(fid, "plane")
    if "center" not in d:
        raise PartProgramError(f"{where}: missing 'center'")
    center = _vec(d["center"], 2, f"{where}.center")
    rotation = _num(d.get("rotation", 0.0), f"{where}.rotation")
    allowed |= {"center", "rotation"}
    kw = dict(id=fid, type=typ, center=center, rotation=rotation)
    if typ in ("square", "rectangle", "circle"):
        default = "inside" if lighting == "bright_field" else "outside"
        material = d.get("material", default)
        if material not in ("inside", "outside"):
            raise PartProgramError(f"{where}.material: 'inside' or 'outside', got {material!r}")
        kw["material"] = material
        allowed.add("material")
        if lighting == "dark_field":
            b = d.get("edge_band_m", band_default)
            kw["band_m"] = None if b is None else _num(b, f"{where}.edge_band_m", positive=True)
            allowed.add("edge_band_m")
    if typ == "square":
        if "side" not in d:
            raise PartProgramError(f"{where}: missing 'side'")
        kw["size"] = (_num(d["side"], f"{where}.side", positive=True),)
        kw["points_per_side"] = _num(d.get("points_per_side", 4), f"{where}.points_per_side", positive=True, integer=True)
        allowed |= {"side", "points_per_side"}
    elif typ == "rectangle":
        if "size" not in d:
            raise PartProgramError(f"{where}: missing 'size'")
        sz = _vec(d["size"], 2, f"{where}.size")
        if not (sz[0] > 0 and sz[1] > 0):
            raise PartProgramError(f"{where}.size: both must be > 0, got {list(sz)}")
        kw["size"] = sz
        kw["points_per_side"] = _num(d.get("points_per_side", 4), f"{where}.points_per_side", positive=True, integer=True)
        allowed |= {"size", "points_per_side"}
    elif typ == "circle":
        if "diameter" not in d:
            raise PartProgramError(f"{where}: missing 'diameter'")
        kw["size"] = (_num(d["diameter"], f"{where}.diameter", positive=True),)
        kw["points"] = _num(d.get("points", 8), f"{where}.points", positive=True, integer=True)
        if kw["points"] < 3:
            raise PartProgramError(f"{where}.points: a circle needs at least 3 points, got {kw['points']}")
        allowed |= {"diameter", "points"}
    elif typ == "dot_grid":
        for key in ("rows", "cols", "pitch", "dot_diameter"):
            if key not in d:
                raise PartProgramError(f"{where}: missing '{key}'")
        kw["rows"] = _num(d["rows"], f"{where}.rows", positive=True, integer=True)
        kw["cols"] = _num(d["cols"], f"{where}.cols", positive=True, integer=True)
        kw["pitch"] = _num(d["pitch"], f"{where}.pitch", positive=True)
        kw["dot_diameter"] = _num(d["dot_diameter"], f"{where}.dot_diameter", positive=True)
        if not kw["pitch"] > kw["dot_diameter"]:
            raise PartProgramError(f"{where}: pitch {kw['pitch']} must exceed dot_diameter {kw['dot_diameter']}")
        allowed |= {"rows", "cols", "pitch", "dot_diameter"}
    extra = set(d) - allowed
    if extra:
        raise PartProgramError(f"{where}: unknown keys {sorted(extra)}")
    return FeatureSpec(**kw)


def load(source) -> PartProgram:
    """A PartProgram from a path, YAML text, or an already parsed dict.

    Raises PartProgramError naming the bad key or feature.
    """
    name = ""
    if isinstance(source, dict):
        d = source
    else:
        p = pathlib.Path(source) if not (isinstance(source, str) and "\n" in source) else None
        if p is not None:
            if not p.is_file():
                raise PartProgramError(f"part program {str(p)!r}: no such file")
            text, name = p.read_text(), str(p)
        else:
            text = source
        try:
            d = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise PartProgramError(f"part program {name or '(text)'}: not valid YAML: {e}") from None
    if not isinstance(d, dict):
        raise PartProgramError(f"part program {name}: expected a mapping at the top level")
    if d.get("units", "SI") != "SI":
        raise PartProgramError(f"units: only SI is supported, got {d.get('units')!r}")
    part = d.get("part")
    if not isinstance(part, str) or not part:
        raise PartProgramError("part: missing or empty name")
    lighting = d.get("lighting", "bright_field")
    if lighting not in LIGHTINGS:
        raise PartProgramError(f"lighting: one of {LIGHTINGS}, got {lighting!r}")
    pl = d.get("placement")
    if not isinstance(pl, dict):
        raise PartProgramError("placement: missing (origin_at_stage, tolerance, rotation_about_normal)")
    if "origin_at_stage" not in pl:
        raise PartProgramError("placement.origin_at_stage: missing")
    origin = np.array(_vec(pl["origin_at_stage"], 3, "placement.origin_at_stage"))
    tol = _num(pl.get("tolerance", 0.0005), "placement.tolerance", positive=True)
    rot = pl.get("rotation_about_normal")
    rot = None if rot is None else _num(rot, "placement.rotation_about_normal")
    feats = d.get("features")
    if not isinstance(feats, list) or not feats:
        raise PartProgramError("features: missing or empty list")
    band = d.get("edge_band_m")
    if band is not None:
        band = _num(band, "edge_band_m", positive=True)
    out, seen = [], set()
    for k, fd in enumerate(feats):
        f = _feature(fd, k, lighting, band)
        if f.id in seen:
            raise PartProgramError(f"feature {f.id!r}: duplicate id")
        seen.add(f.id)
        out.append(f)
    if all(f.type == "plane" for f in out):
        raise PartProgramError("features: only planes; a plane is fitted from the points of other features")
    return PartProgram(part, lighting, origin, tol, rot, tuple(out), name, d)


def plan(prog: PartProgram) -> list[PlannedPoint]:
    """Every point to measure, in program order (see module doc)."""
    pts = []
    for f in prog.features:
        c = np.asarray(f.center, float)
        cr, sr = math.cos(f.rotation), math.sin(f.rotation)
        ex, ey = np.array([cr, sr]), np.array([-sr, cr])
        sign = 1.0 if f.material == "inside" else -1.0        # into the material
        if f.type in ("square", "rectangle"):
            hx, hy = f.half_sizes
            n = f.points_per_side
            ts = np.zeros(1) if n == 1 else np.linspace(-0.35, 0.35, n)
            k = 0
            for side, (out_n, along, h_out, h_along) in enumerate(
                    ((ex, ey, hx, hy), (ey, -ex, hy, hx), (-ex, -ey, hx, hy), (-ey, ex, hy, hx))):
                for t in ts:
                    xy = c + out_n * h_out + along * (2 * h_along * t)
                    pts.append(PlannedPoint(f.id, "edge", k, xy, -sign * out_n, along, side=side))
                    k += 1
        elif f.type == "circle":
            r = f.size[0] / 2
            for k in range(f.points):
                a = f.rotation + 2 * math.pi * k / f.points
                u = np.array([math.cos(a), math.sin(a)])
                pts.append(PlannedPoint(f.id, "edge", k, c + r * u, -sign * u, np.array([-u[1], u[0]]),
                                        curvature_radius=r))
        elif f.type == "dot_grid":
            for k, xy in enumerate(f.dots_part()):
                pts.append(PlannedPoint(f.id, "dot", k, xy, grid_rc=(k // f.cols, k % f.cols)))
    return pts
