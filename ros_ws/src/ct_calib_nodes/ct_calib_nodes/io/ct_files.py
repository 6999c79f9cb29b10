"""The YAML files that come with a CT recording (INTERFACES.md): ct_instrument.yaml and
reference_object.yaml. Readers check every field and name what is wrong."""

from __future__ import annotations

import pathlib
from dataclasses import dataclass

import numpy as np
import yaml

from ct_calib_nodes.core.geometry import DetectorSpec
from ct_calib_nodes.core.phantom import ReferenceObject
from ct_calib_nodes.io.atomic import write_text_atomic

CONFIG_DIR = pathlib.Path(__file__).resolve().parent.parent.parent / "config"


class CtFileError(ValueError):
    """A CT YAML file is missing, unreadable or does not follow INTERFACES.md."""


@dataclass(frozen=True)
class CtInstrument:
    """Nominal values of the instrument (ct_instrument.yaml).

    Attributes
    ----------
    sdd_reported_m : float
        Source-to-detector distance as the instrument software states it [m].
    detector : DetectorSpec
        Pixel grid (cols, rows, pixel pitch [m]).
    flat_field_counts : float
        Mean open-beam counts of mono16 frames.
    index_repeatability_rad : float or None
        Optional ``rotary_index_repeatability`` [rad]: standard uncertainty of the
        rotary table's zero index on returning to it, included in u(yaw).
    temperature_K : float or None
        Optional ``temperature`` [K]: the reference object's temperature during
        the scan, for its thermal expansion (with the object's expansion
        coefficient and calibration temperature).
    flat_field_image : ndarray (rows, cols) or None
        Optional ``detector.flat_field_image``: file name (relative to the YAML file;
        ``.npy``, or an image OpenCV reads unchanged, e.g. 16-bit PNG/TIFF) of the
        open-beam counts per pixel (gain map). Used instead of ``flat_field_counts``.
    dark : float, ndarray (rows, cols) or None
        Optional ``detector.dark_counts`` (offset level, counts) or
        ``detector.dark_image`` (file, as above): subtracted from frames and flat field.
    """

    sdd_reported_m: float
    detector: DetectorSpec
    flat_field_counts: float
    index_repeatability_rad: float | None = None
    temperature_K: float | None = None
    flat_field_image: np.ndarray | None = None
    dark: float | np.ndarray | None = None

    def flat_field(self):
        """What the detector divides by: the flat-field image if given, else the scalar (None if 0)."""
        if self.flat_field_image is not None:
            return self.flat_field_image
        return float(self.flat_field_counts) if self.flat_field_counts else None

    def to_yaml_dict(self) -> dict:
        d = {"units": "SI", "source_to_detector": float(self.sdd_reported_m),
             "detector": {"cols": int(self.detector.cols), "rows": int(self.detector.rows),
                          "pixel_pitch": float(self.detector.pixel_pitch_m),
                          "flat_field_counts": float(self.flat_field_counts)}}
        if self.index_repeatability_rad is not None:
            d["rotary_index_repeatability"] = float(self.index_repeatability_rad)
        if self.temperature_K is not None:
            d["temperature"] = float(self.temperature_K)
        return d


def _load(path) -> dict:
    path = pathlib.Path(path)
    if not path.is_file():
        raise CtFileError(f"{path}: file not found")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise CtFileError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise CtFileError(f"{path}: expected a mapping at top level, got {type(data).__name__}")
    units = data.get("units", "SI")
    if str(units).upper() != "SI":
        raise CtFileError(f"{path}: units must be SI (metres), got {units!r}")
    return data


def _positive(path, data, key, where=""):
    try:
        v = float(data[key])
    except KeyError:
        raise CtFileError(f"{path}: missing key {where}{key}") from None
    except (TypeError, ValueError):
        raise CtFileError(f"{path}: {where}{key} must be a number, got {data[key]!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise CtFileError(f"{path}: {where}{key} must be positive and finite, got {v}")
    return v


def _non_negative(path, data, key, where=""):
    try:
        v = float(data[key])
    except (TypeError, ValueError):
        raise CtFileError(f"{path}: {where}{key} must be a number, got {data[key]!r}") from None
    if not np.isfinite(v) or v < 0:
        raise CtFileError(f"{path}: {where}{key} must be non-negative and finite, got {v}")
    return v


def load_instrument(path) -> CtInstrument:
    """Read ct_instrument.yaml."""
    data = _load(path)
    sdd = _positive(path, data, "source_to_detector")
    det = data.get("detector")
    if not isinstance(det, dict):
        raise CtFileError(f"{path}: missing mapping 'detector'")
    cols, rows = _positive(path, det, "cols", "detector."), _positive(path, det, "rows", "detector.")
    if cols != int(cols) or rows != int(rows):
        raise CtFileError(f"{path}: detector.cols/rows must be integers, got {cols}, {rows}")
    pitch = _positive(path, det, "pixel_pitch", "detector.")
    if pitch > 0.01:
        raise CtFileError(f"{path}: detector.pixel_pitch {pitch} m is implausible (metres expected, e.g. 0.0004)")
    flat = _positive(path, det, "flat_field_counts", "detector.") if "flat_field_counts" in det else 0.0
    if sdd > 20 or sdd < 0.01:
        raise CtFileError(f"{path}: source_to_detector {sdd} m is implausible (metres expected)")
    rep = None
    if data.get("rotary_index_repeatability") is not None:
        rep = _non_negative(path, data, "rotary_index_repeatability")
        if rep > 0.01:
            raise CtFileError(f"{path}: rotary_index_repeatability {rep} rad is implausible (radians expected)")
    temp = _positive(path, data, "temperature") if data.get("temperature") is not None else None
    shape = (int(rows), int(cols))
    flat_img = _image_file(path, det, "flat_field_image", shape) if det.get("flat_field_image") else None
    if flat_img is not None and not np.all(flat_img > 0):
        raise CtFileError(f"{path}: detector.flat_field_image must be > 0 everywhere")
    dark = None
    if det.get("dark_image"):
        dark = _image_file(path, det, "dark_image", shape)
    elif det.get("dark_counts") is not None:
        dark = _non_negative(path, det, "dark_counts", "detector.")
    return CtInstrument(sdd, DetectorSpec(int(cols), int(rows), pitch), flat, rep, temp, flat_img, dark)


def _image_file(path, det, key, shape) -> np.ndarray:
    """An optional per-pixel calibration image named in the instrument file (relative to it)."""
    f = pathlib.Path(str(det[key]))
    if not f.is_absolute():
        f = pathlib.Path(path).resolve().parent / f
    if not f.is_file():
        raise CtFileError(f"{path}: detector.{key} file {f} not found")
    try:
        if f.suffix == ".npy":
            a = np.load(f, allow_pickle=False)
        else:
            import cv2  # noqa: PLC0415
            a = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            if a is None:
                raise ValueError("unreadable image")
    except Exception as exc:  # noqa: BLE001 - any reader error is a bad file
        raise CtFileError(f"{path}: detector.{key} {f}: cannot read ({exc})") from None
    a = np.asarray(a, dtype=np.float32)
    if a.shape != shape or not np.all(np.isfinite(a)) or np.any(a < 0):
        raise CtFileError(f"{path}: detector.{key} must be a finite, non-negative {shape[0]}x{shape[1]} "
                          f"(rows x cols) image, got shape {a.shape}")
    return a


def load_reference_object(path) -> ReferenceObject:
    """Read reference_object.yaml.

    Optional keys used: ``center_uncertainty`` (m, per sphere; propagated into the geometry's
    uncertainty), ``temperature`` (K, at calibration) and ``thermal_expansion`` (1/K, the
    frame's linear expansion coefficient; this project's own optional key)."""
    data = _load(path)
    spheres = data.get("spheres")
    if not isinstance(spheres, list) or not spheres:
        raise CtFileError(f"{path}: 'spheres' must be a non-empty list")
    ids, centres, diameters, unc = [], [], [], []
    for k, s in enumerate(spheres):
        if not isinstance(s, dict) or not {"id", "center", "diameter"} <= set(s):
            raise CtFileError(f"{path}: spheres[{k}] needs id, center and diameter, got {s!r}")
        c = np.asarray(s["center"], dtype=float) if isinstance(s["center"], (list, tuple)) else None
        if c is None or c.shape != (3,) or not np.all(np.isfinite(c)):
            raise CtFileError(f"{path}: spheres[{k}].center must be 3 finite numbers [m], got {s['center']!r}")
        if np.max(np.abs(c)) > 2.0:
            raise CtFileError(f"{path}: spheres[{k}].center {c.tolist()} is implausible (metres expected)")
        ids.append(int(s["id"]))
        centres.append(c)
        diameters.append(_positive(path, s, "diameter", f"spheres[{k}]."))
        unc.append(float(s["center_uncertainty"]) if "center_uncertainty" in s else np.nan)
    if len(set(ids)) != len(ids):
        raise CtFileError(f"{path}: sphere ids are not unique")
    unc = np.asarray(unc)
    temp = data.get("temperature")
    cte = data.get("thermal_expansion")
    if cte is not None:
        try:
            cte = float(cte)
        except (TypeError, ValueError):
            raise CtFileError(f"{path}: thermal_expansion must be a number [1/K], got {cte!r}") from None
    try:
        return ReferenceObject(
            name=str(data.get("name", pathlib.Path(path).stem)), ids=np.asarray(ids),
            centres_of_m=np.asarray(centres), diameters_m=np.asarray(diameters),
            material=str(data.get("sphere_material", "steel")),
            center_uncertainty_m=None if np.all(np.isnan(unc)) else np.nan_to_num(unc, nan=float(np.nanmax(unc))),
            temperature_K=float(temp) if temp is not None else None, thermal_expansion_per_K=cte)
    except ValueError as exc:
        raise CtFileError(f"{path}: {exc}") from None


def reference_at_scan(ref: ReferenceObject, instrument: CtInstrument):
    """The reference object as it was during the scan: (ReferenceObject, note).

    Applies thermal expansion when ct_instrument.yaml gives the object's ``temperature`` and the
    reference object file its calibration ``temperature`` and ``thermal_expansion``; the note says
    what was done or what is missing (it goes into the results and the logs)."""
    return ref.at_temperature(instrument.temperature_K)


def write_yaml(path, data: dict) -> pathlib.Path:
    """Write a dict as YAML atomically (temp file + rename: never a half-written file)."""
    return write_text_atomic(path, yaml.safe_dump(data, sort_keys=False, default_flow_style=None))


def default_instrument_path() -> pathlib.Path:
    return _config_file("ct_instrument.yaml")


def default_reference_object_path() -> pathlib.Path:
    return _config_file("reference_object.yaml")


def _config_file(name: str) -> pathlib.Path:
    """Config file from the source tree, or from the installed share directory."""
    candidates = [CONFIG_DIR / name]
    try:
        from ament_index_python.packages import get_package_share_directory  # noqa: PLC0415

        candidates.append(pathlib.Path(get_package_share_directory("ct_calib_nodes")) / "config" / name)
    except Exception:  # noqa: BLE001 - not in a ROS environment
        pass
    for c in candidates:
        if c.is_file():
            return c
    raise CtFileError(f"default {name} not found in {[str(c) for c in candidates]}")
