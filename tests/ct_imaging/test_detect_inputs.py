"""Real detector inputs (issue 12.6): the shared frame decoder accepts mono16, 16UC1, mono8
and 32FC1; flat-field and dark images and levels from ct_instrument.yaml; encodings give the
same centres as mono16 within what their bit depth allows."""

import types

import numpy as np
import pytest

from ct_calib_nodes.core import detect
from ct_calib_nodes.core.geometry import DetectorSpec
from ct_calib_nodes.core.phantom import helix49
from ct_calib_nodes.core.render import RenderSettings, render_projection
from ct_calib_nodes.core.scenario import default_static_truth
from ct_calib_nodes.io import ct_files
from ct_calib_nodes.io.convert import MessageError, array_from_image

DET = DetectorSpec(1024, 1024, 0.0004)
DRANGE = (14.0, 27.0)


def _msg(arr, enc, big=False):
    a = np.ascontiguousarray(arr)
    dt = a.dtype.newbyteorder(">" if big else "<")
    return types.SimpleNamespace(encoding=enc, height=a.shape[0], width=a.shape[1], step=a.shape[1] * a.itemsize,
                                 is_bigendian=int(big), data=a.astype(dt).tobytes())


@pytest.mark.parametrize("enc,dtype", [("mono16", np.uint16), ("16UC1", np.uint16), ("mono8", np.uint8),
                                       ("8UC1", np.uint8), ("32FC1", np.float32)])
@pytest.mark.parametrize("big", [False, True])
def test_decoder_accepts_the_encodings_drivers_publish(enc, dtype, big):
    a = (np.arange(12 * 7).reshape(12, 7) % 200).astype(dtype)
    arr, e = array_from_image(_msg(a, enc, big))
    assert e == enc and arr.dtype == np.dtype(dtype) and np.array_equal(arr, a)


def test_decoder_names_what_is_wrong():
    with pytest.raises(MessageError, match="unsupported image encoding 'rgb8'"):
        array_from_image(_msg(np.zeros((4, 4), np.uint8), "rgb8"))
    m = _msg(np.zeros((4, 4), np.uint16), "mono8")
    m.step = 3                                       # too small for 4 px
    with pytest.raises(MessageError, match="step"):
        array_from_image(m)


@pytest.fixture(scope="module")
def frame():
    w = default_static_truth(0.364)
    return render_projection(w, np.zeros(6), 0.3, helix49(), DET, RenderSettings(ellipse_centre_bias=False),
                             np.random.default_rng(4))


def _err(det, tr):
    d = np.linalg.norm(det.centre_px[:, None] - tr.centre_px[None], axis=2)
    j = d.argmin(axis=1)
    assert np.all(d[np.arange(len(j)), j] < 0.5)
    return det.centre_px - tr.centre_px[j]


def test_16uc1_is_mono16_and_mono8_works(frame):
    a = detect.detect_spheres(frame.image, encoding="mono16", flat_field_counts=50000.0, diameter_px_range=DRANGE)
    b = detect.detect_spheres(frame.image, encoding="16UC1", flat_field_counts=50000.0, diameter_px_range=DRANGE)
    assert np.array_equal(a.centre_px, b.centre_px)
    g8 = np.clip(np.rint(frame.image * (220.0 / 50000.0)), 0, 255).astype(np.uint8)
    # the file's flat_field_counts (50000) describes mono16 frames: ignored for mono8
    c = detect.detect_spheres(g8, encoding="mono8", flat_field_counts=50000.0, diameter_px_range=DRANGE)
    assert len(c) >= len(a) - 2
    e = _err(c, frame.truth)
    # 8-bit quantisation (1/220 of the open beam) roughly doubles the edge noise
    assert np.all(e.std(axis=0) < 0.03)
    with pytest.raises(detect.FrameError) as ei:
        detect.detect_spheres(frame.image, encoding="mono8")
    assert ei.value.reason == "wrong_dtype"


def test_flat_field_and_dark_images(frame):
    """A detector with a dark offset and a pixel gain pattern: with the flat and dark images the
    centres are as good as on the clean frame; the transmission is (I - dark) / (flat - dark)."""
    rng = np.random.default_rng(8)
    gain = (1.0 + 0.05 * rng.standard_normal(frame.image.shape)).astype(np.float32)
    dark = np.full(frame.image.shape, 800.0, np.float32)
    raw = np.clip(frame.image * gain + dark, 0, 65535).astype(np.uint16)
    flat = 50000.0 * gain + dark
    t = detect.to_transmission(raw, "mono16", flat, dark=dark)
    assert abs(float(np.median(t)) - float(np.median(frame.image / 50000.0))) < 0.002
    good = detect.detect_spheres(raw, flat_field_counts=flat, dark=dark, diameter_px_range=DRANGE)
    bad = detect.detect_spheres(raw, flat_field_counts=50000.0, diameter_px_range=DRANGE)
    eg = _err(good, frame.truth)
    clean = _err(detect.detect_spheres(frame.image, flat_field_counts=50000.0, diameter_px_range=DRANGE), frame.truth)
    print(f"sd with flat+dark {eg.std(axis=0).round(4)}, clean {clean.std(axis=0).round(4)}, "
          f"without: n={len(bad)} of {len(good)}")
    assert np.all(eg.std(axis=0) < 1.3 * clean.std(axis=0) + 0.001)
    with pytest.raises(detect.FrameError) as ei:
        detect.detect_spheres(raw, flat_field_counts=flat[:10], diameter_px_range=DRANGE)
    assert ei.value.reason == "bad_flat_field"


def test_instrument_file_optional_flat_and_dark_keys(tmp_path):
    flat = np.full((4, 6), 1000.0, np.float32)
    np.save(tmp_path / "flat.npy", flat)
    base = "units: SI\nsource_to_detector: 1.0\ndetector:\n  cols: 6\n  rows: 4\n  pixel_pitch: 0.0004\n"
    (tmp_path / "a.yaml").write_text(base + "  flat_field_counts: 900\n")
    inst = ct_files.load_instrument(tmp_path / "a.yaml")          # foreign file without the keys
    assert inst.flat_field() == 900.0 and inst.dark is None and inst.flat_field_image is None
    (tmp_path / "b.yaml").write_text(base + "  flat_field_image: flat.npy\n  dark_counts: 100\n")
    inst = ct_files.load_instrument(tmp_path / "b.yaml")
    assert np.array_equal(inst.flat_field(), flat) and inst.dark == 100.0
    (tmp_path / "c.yaml").write_text(base + "  flat_field_image: missing.npy\n")
    with pytest.raises(ct_files.CtFileError, match="flat_field_image"):
        ct_files.load_instrument(tmp_path / "c.yaml")
    np.save(tmp_path / "small.npy", flat[:2])
    (tmp_path / "d.yaml").write_text(base + "  dark_image: small.npy\n")
    with pytest.raises(ct_files.CtFileError, match="dark_image"):
        ct_files.load_instrument(tmp_path / "d.yaml")


def test_diameter_range_from_the_reference_object():
    ref = helix49()
    lo, hi = detect.shadow_diameter_range_px(ref.diameters_m, ref.centres_of_m, 1.04821, 0.364, 0.0004)
    # helix49 reaches 61 mm from its centroid (+1.5 mm sphere radius): nominal shadows 19.6-24.4 px
    assert 0.6 * 3e-3 * 1.04821 / (0.364 + 0.0625) / 0.0004 == pytest.approx(lo, rel=1e-3)
    assert 1.5 * 3e-3 * 1.04821 / (0.364 - 0.0625) / 0.0004 == pytest.approx(hi, rel=1e-3)
