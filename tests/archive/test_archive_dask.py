"""Archive re-solves: a Dask LocalCluster of 2 workers gives results identical to the sequential
solve of the same recordings; a bad recording is reported, not fatal; only the caller writes the
history."""
import pathlib

import numpy as np
import pytest

from ct_calib_nodes.archive import find_recordings, run, store
from ct_calib_nodes.io.history import History
from ct_calib_nodes.io.sample_recording import write_sample_recording
from ct_calib_nodes.io.truth_files import read_truth

pytestmark = pytest.mark.ros   # needs the message packages (recordings are ROS messages)


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    root = tmp_path_factory.mktemp("archive")
    for seed in (1, 2):
        write_sample_recording(root / f"rec_{seed}", positions=2, projections=6, cols=384, pixel_pitch_m=0.00107,
                               seed=seed, truth_path=root.parent / f"truth_{seed}.yaml")
    (root / "broken.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\0" * 100)
    return root


def test_dask_local_cluster_equals_sequential(archive, tmp_path):
    from distributed import Client, LocalCluster

    paths = find_recordings(archive)
    assert [p.name for p in paths] == ["broken.mcap", "rec_1", "rec_2"]
    seq = run(paths, workers=1)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        par = run(paths, scheduler=client)
        assert len({r["pid"] for r in par}) == 2 or len(paths) < 2      # both workers took work
    assert [r["recording"] for r in par] == [str(p) for p in paths]
    assert not seq[0]["ok"] and not par[0]["ok"] and seq[0]["records"] == []
    for s, p in zip(seq[1:], par[1:]):
        assert s["ok"] and p["ok"], (s["reason"], p["reason"])
        assert s["static"] == p["static"]                 # bit-identical estimates and uncertainties
        assert s["maps"] == p["maps"]
        assert [r.status for r in s["records"]] == [r.status for r in p["records"]]
    # and right: the static geometry within 5 u of the simulator's truth
    for seed, r in zip((1, 2), seq[1:]):
        truth = read_truth(archive.parent / f"truth_{seed}.yaml")
        err = np.asarray(r["static"]["x"][:13]) - truth.static_w
        assert np.all(np.abs(err) < 5 * np.asarray(r["static"]["std"][:13])), err
    db = tmp_path / "h.sqlite"
    assert store(par, db) == 6          # per recording: geometry + multi and single maps
    with History(db) as h:
        geo = h.list(kind="ct_geometry", source="archive", with_details=True)
        assert [pathlib.Path(i.path).name for g in geo for i in g.inputs if i.role == "recording"] == ["rec_1", "rec_2"]
        maps = h.list(kind="ct_error_map", with_details=True)
        assert all(any(i.role == "upstream" for i in m.inputs) for m in maps)
