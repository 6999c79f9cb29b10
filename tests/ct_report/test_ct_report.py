"""Tests of the calibration report (core/report.py).

Inputs are built from the truth scenario (scenario.default_campaign): the
true error map, noisy "multi" / "single" series with stated uncertainties,
the truth static parameters with a seeded covariance, and seeded residuals.
No solver is involved; the tests check that the report shows exactly the
numbers it was given and that error_map's uncertainty propagation is right.
"""

import html
import re
import struct

import numpy as np
import pytest

from ct_calib_nodes.core import geometry as g
from ct_calib_nodes.core.error_map import ErrorMap, error_map
from ct_calib_nodes.core import report as rp
from ct_calib_nodes.core import scenario as sc

ARCSEC = sc.ARCSEC


def png_size(path):
    """(width, height) from a PNG's IHDR chunk; asserts the PNG signature."""
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n", f"{path.name} is not a PNG"
    assert head[12:16] == b"IHDR"
    return struct.unpack(">II", head[16:24])


def make_inputs(seed=3):
    rng = np.random.default_rng(seed)
    camp = sc.default_campaign()
    k = camp.motions.shape[0]
    u_multi = np.tile([2e-6, 2e-6, 20e-6, 2 * ARCSEC, 30 * ARCSEC, 1 * ARCSEC], (k, 1))
    u_multi[0] = 0.0                                     # k = 1 is the datum
    u_single = 3.0 * u_multi
    cov = lambda u: np.einsum("kj,ij->kij", u ** 2, np.eye(6))  # noqa: E731
    multi = error_map(camp.srd_reported_m, camp.motions + rng.normal(size=(k, 6)) * u_multi, cov(u_multi),
                      name="multi")
    single = error_map(camp.srd_reported_m, camp.motions + rng.normal(size=(k, 6)) * u_single, cov(u_single),
                       name="single")
    ref = ErrorMap.reference("reference", camp.srd_reported_m, **camp.error_map("travel"))
    u_w = np.r_[1e-5, 1e-5, 1e-5, 2e-5, 1e-4, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5, 1e-4, 1e-4, 1e-4]
    a = rng.normal(size=(13, 13))
    corr = a @ a.T
    corr /= np.sqrt(np.outer(np.diag(corr), np.diag(corr)))
    table = rp.ParameterTable.from_covariance(g.STATIC_PARAM_NAMES, g.STATIC_PARAM_UNITS, camp.static_w,
                                              corr * np.outer(u_w, u_w), "Static parameters (k = 1)")
    n_v, n_s, n_k = 24, 49, 4
    res = rp.ReprojectionResiduals(
        rng.normal(size=(n_v * n_s * n_k, 2)) * 0.05,
        view_index=np.tile(np.repeat(np.arange(n_v), n_s), n_k),
        sphere_index=np.tile(np.arange(n_s), n_v * n_k),
        stage_index=np.repeat(np.arange(n_k), n_v * n_s), label="multi")
    meta = {"recording": "sim_campaign.mcap", "observations": res.residuals_px.shape[0], "rejected": 7,
            "wall_time_s": 12.5}
    return camp, multi, single, ref, table, res, meta


@pytest.fixture(scope="module")
def full_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("report_ref")
    camp, multi, single, ref, table, res, meta = make_inputs()
    index = rp.write_report(out, [multi, single], reference=ref, params_table=table, residuals=res, meta=meta)
    return out, index, (camp, multi, single, ref, table, res, meta)


def test_error_map_matches_scenario():
    camp = sc.default_campaign()
    for definition in ("travel", "detector"):
        s = error_map(camp.srd_reported_m, camp.motions, definition=definition, name="truth")
        truth = camp.error_map(definition)
        for comp in rp.COMPONENTS:
            assert np.allclose(s.values(comp[0]), truth[comp[0]], rtol=0, atol=1e-15), comp[0]
        assert s.u_positioning_m is None and s.definition == definition


def test_error_map_uncertainty_propagation_monte_carlo():
    """Propagated u of the straightness and positioning vs the spread of 4000 seeded draws.

    The sample std of N = 4000 normal draws has relative standard error
    1/sqrt(2(N-1)) = 1.1 %; 6 % is > 5 standard errors.
    """
    rng = np.random.default_rng(11)
    camp = sc.default_campaign()
    k = camp.motions.shape[0]
    s_motion = np.tile([3e-6, 5e-6, 1e-5, 1e-5, 1e-5, 1e-5], (k, 1)) * (1 + np.arange(k)[:, None] / k)
    s_motion[0] = 0.0
    cov = np.einsum("kj,ij->kij", s_motion ** 2, np.eye(6))
    for definition in ("travel", "detector"):
        s = error_map(camp.srd_reported_m, camp.motions, cov, definition=definition)
        draws = [error_map(camp.srd_reported_m, camp.motions + rng.normal(size=(k, 6)) * s_motion,
                           definition=definition) for _ in range(4000)]
        for comp in ("straightness_x_m", "straightness_y_m", "positioning_m"):
            sd = np.array([d.values(comp) for d in draws]).std(axis=0)
            assert np.allclose(sd[1:], s.uncertainty(comp)[1:], rtol=0.06), (definition, comp)
        assert np.allclose(s.u_yaw_rad, s_motion[:, 4])
    # the paper's positioning is reading - dz: its u is u(dz) exactly
    assert np.allclose(s.u_positioning_m, s_motion[:, 2])


def test_report_writes_all_files(full_report):
    out, index, _ = full_report
    assert index == out / "index.html" and index.exists() and (out / "index.md").exists()
    names = {p.name for p in out.glob("*.png")}
    expected = {f"error_{c[0].rsplit('_', 1)[0]}.png" for c in rp.COMPONENTS} | {"correlation_0.png",
                                                                              "residuals_0.png"}
    assert names == expected
    for p in out.glob("*.png"):
        w, h = png_size(p)
        assert 400 <= w <= 2500 and 300 <= h <= 2000, (p.name, w, h)
        assert p.stat().st_size > 10_000, p.name             # not a blank canvas


def test_html_and_markdown_reference_every_png(full_report):
    out, index, _ = full_report
    text = index.read_text(encoding="utf-8")
    md = (out / "index.md").read_text(encoding="utf-8")
    srcs = set(re.findall(r'<img src="([^"]+)"', text))
    md_srcs = set(re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md))
    pngs = {p.name for p in out.glob("*.png")}
    assert srcs == pngs and md_srcs == pngs
    assert all("/" not in s for s in srcs)                    # relative, beside index.html


def parse_html_tables(text):
    tables = []
    for t in re.findall(r"<table[^>]*>(.*?)</table>", text, flags=re.S):
        rows = [[html.unescape(c) for c in re.findall(r"<t[dh]>(.*?)</t[dh]>", r)]
                for r in re.findall(r"<tr>(.*?)</tr>", t, flags=re.S)]
        tables.append(rows)
    return tables


def test_parameter_table_contains_every_parameter(full_report):
    _, index, (camp, _, _, _, table, _, _) = full_report
    tables = parse_html_tables(index.read_text(encoding="utf-8"))
    ptab = next(t for t in tables if t[0][0] == "parameter")
    rows = {r[0]: r for r in ptab[1:]}
    assert set(rows) == set(g.STATIC_PARAM_NAMES)
    for i, name in enumerate(g.STATIC_PARAM_NAMES):
        r = rows[name]
        assert r[1] == g.STATIC_PARAM_UNITS[i]
        # 9 significant digits are printed: relative agreement 1e-8.
        assert float(r[2]) == pytest.approx(camp.static_w[i], rel=1e-8, abs=1e-15)
        assert float(r[3]) == pytest.approx(table.std_uncertainties[i], rel=1e-8)
        if g.STATIC_PARAM_UNITS[i] == "rad":
            assert r[4].endswith("°") and r[5].endswith("arcsec")
            assert float(r[4].split()[0]) == pytest.approx(np.degrees(camp.static_w[i]), rel=1e-6, abs=1e-9)
            assert float(r[5].split()[0]) == pytest.approx(table.std_uncertainties[i] / ARCSEC, rel=1e-3)
        else:
            assert r[4].endswith("mm") and r[5].endswith("µm")
            assert float(r[5].split()[0]) == pytest.approx(table.std_uncertainties[i] * 1e6, rel=1e-3)


def test_error_map_numbers_match_inputs(full_report):
    _, index, (_, multi, single, *_rest) = full_report
    tables = parse_html_tables(index.read_text(encoding="utf-8"))
    em = [t for t in tables if t[0][0] == "SRD [mm]"]
    assert len(em) == 2
    for tab, s in zip(em, (multi, single)):
        assert len(tab) - 1 == s.srd_reported_m.size
        for i, row in enumerate(tab[1:]):
            assert float(row[0]) == pytest.approx(s.srd_reported_m[i] * 1e3, rel=1e-6)
            for (comp, _, _, f, _), cell in zip(rp.COMPONENTS, row[1:]):
                val, unc = (float(x) for x in cell.split(" ± "))
                # 4 decimals printed in µm / arcsec: absolute agreement 5e-5 display units.
                assert val == pytest.approx(s.values(comp)[i] * f, abs=5.1e-5)
                assert unc == pytest.approx(2 * s.uncertainty(comp)[i] * f, abs=5.1e-5)
    md = (full_report[0] / "index.md").read_text(encoding="utf-8")
    assert f"{multi.positioning_m[-1] * 1e6:.4f} ± {2 * multi.u_positioning_m[-1] * 1e6:.4f}" in md


def test_metadata_and_residual_stats_in_page(full_report):
    _, index, (*_, res, meta) = full_report
    tables = parse_html_tables(index.read_text(encoding="utf-8"))
    kv = {r[0]: r[1] for t in tables if t[0] == ["key", "value"] for r in t[1:]}
    assert kv == {k: str(v) for k, v in meta.items()}
    stats = {r[0]: r[1] for t in tables if t[0] == ["statistic", "value"] for r in t[1:]}
    assert int(stats["observations"]) == res.residuals_px.shape[0]
    assert float(stats["RMS |residual| [px]"]) == pytest.approx(res.rms_px(), rel=1e-3)
    # sigma = 0.05 px per component -> RMS of the 2-D length = 0.05 sqrt(2) (4704 draws: ~1 % spread).
    assert res.rms_px() == pytest.approx(0.05 * np.sqrt(2), rel=0.05)


def test_delta_plot_only_with_reference(full_report, tmp_path):
    out_ref, index_ref, (camp, multi, single, ref, *_r) = full_report
    index = rp.write_report(tmp_path, [multi, single])
    text = index.read_text(encoding="utf-8")
    text_ref = index_ref.read_text(encoding="utf-8")
    assert "with delta to reference" not in text
    assert len(re.findall(r'<img [^>]*alt="[^"]*with delta to reference', text_ref)) == len(rp.COMPONENTS)
    # The delta panel makes the figure taller (6.2 in vs 4.4 in at 110 dpi).
    for comp in rp.COMPONENTS:
        name = f"error_{comp[0].rsplit('_', 1)[0]}.png"
        h_ref, h = png_size(out_ref / name)[1], png_size(tmp_path / name)[1]
        assert h_ref > 1.25 * h, (name, h_ref, h)
    assert not list(tmp_path.glob("correlation_*.png")) and not list(tmp_path.glob("residuals_*.png"))


def test_reference_interpolation():
    ref = ErrorMap.reference("ref", [0.4, 0.5], positioning_m=[0.0, 1e-4], straightness_x_m=[0.0, 0.0],
                             straightness_y_m=[0.0, 0.0], pitch_rad=[0.0, 2e-5], yaw_rad=[0.0, 0.0],
                             roll_rad=[np.nan, np.nan])
    v = rp._reference_at(ref, "positioning_m", np.array([0.39, 0.4, 0.45, 0.5, 0.6]))
    assert np.allclose(v, [np.nan, 0.0, 5e-5, 1e-4, np.nan], equal_nan=True)
    assert np.all(np.isnan(rp._reference_at(ref, "roll_rad", np.array([0.45]))))


def test_read_reference_csv_and_yaml(tmp_path):
    camp = sc.default_campaign()
    truth = camp.error_map("travel")
    srd = camp.srd_reported_m
    lines = ["# laser interferometer + electronic level, units SI",
             "srd_m,positioning_m,straightness_x_m,pitch_rad,yaw_rad,roll_rad"]
    order = np.arange(srd.size)[::-1]                          # unsorted on purpose
    for i in order:
        roll = "" if i == 3 else repr(float(truth["roll_rad"][i]))
        lines.append(",".join([repr(float(x)) for x in (srd[i], truth["positioning_m"][i], truth["straightness_x_m"][i],
                               truth["pitch_rad"][i], truth["yaw_rad"][i])] + [roll]))
    p = tmp_path / "ref.csv"
    p.write_text("\n".join(lines) + "\n")
    r = rp.read_reference_error_map(p)
    assert r.name == "reference" and r.u_pitch_rad is None
    assert np.array_equal(r.srd_reported_m, srd) and r.definition == "travel"
    assert np.array_equal(r.positioning_m, truth["positioning_m"])
    assert np.all(np.isnan(r.straightness_y_m))                # column absent
    assert np.isnan(r.roll_rad[3]) and np.array_equal(np.delete(r.roll_rad, 3), np.delete(truth["roll_rad"], 3))

    y = tmp_path / "ref.yaml"
    y.write_text("name: interferometer\nunits: SI\n"
                 f"srd_m: {srd.tolist()}\npitch_rad: {truth['pitch_rad'].tolist()}\n")
    r = rp.read_reference_error_map(y)
    assert r.name == "interferometer" and np.array_equal(r.pitch_rad, truth["pitch_rad"])
    assert np.all(np.isnan(r.positioning_m))

    bad = tmp_path / "bad.yaml"
    bad.write_text("units: mm\nsrd_m: [364.0]\n")
    with pytest.raises(ValueError, match="SI"):
        rp.read_reference_error_map(bad)
    bad_csv = tmp_path / "bad.csv"
    bad_csv.write_text("srd_mm,positioning_m\n364,0\n")
    with pytest.raises(ValueError, match="unknown columns"):
        rp.read_reference_error_map(bad_csv)


def test_input_checks():
    with pytest.raises(ValueError, match="positioning_m"):
        ErrorMap("x", "travel", [0.1, 0.2], [0.0], [0, 0], [0, 0], [0, 0], [0, 0], [0, 0])
    with pytest.raises(ValueError, match="u_pitch_rad"):
        ErrorMap("x", "travel", [0.1], [0.0], [0.0], [0.0], [0.0], [0.0], [0.0], u_pitch_rad=[-1.0])
    with pytest.raises(ValueError, match="srd_reported_m"):
        ErrorMap("x", "travel", [np.nan], [0.0], [0.0], [0.0], [0.0], [0.0], [0.0])
    with pytest.raises(ValueError, match="definition"):
        ErrorMap("x", "iso", [0.1], [0.0], [0.0], [0.0], [0.0], [0.0], [0.0])
    with pytest.raises(ValueError, match="correlation"):
        rp.ParameterTable(("a", "b"), ("m", "m"), [1.0, 2.0], [0.1, 0.1], correlation=[[1.0, 2.0], [2.0, 1.0]])
    with pytest.raises(ValueError, match="view_index"):
        rp.ReprojectionResiduals(np.zeros((3, 2)), view_index=np.zeros(2, int), sphere_index=np.zeros(3, int))
    with pytest.raises(ValueError, match="non-empty"):
        rp.write_report("/nonexistent-never-created", [])
