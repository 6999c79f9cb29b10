"""ct_demo's end-of-campaign decision: the ErrorMap `final` flag rules when the maps carry it; the
quiet-time rule only serves maps without the field."""

from types import SimpleNamespace

from ct_calib_nodes.nodes.ct_demo import campaign_over


def _map(n, final=None):
    m = SimpleNamespace(srd_reported_m=[0.1] * n)
    if final is not None:
        m.final = final
    return m


QUIET = {"all_obs_at": 0.0, "multi_after": True, "single_after": True}


def test_final_flag_required_even_after_quiet_time():
    assert not campaign_over({"multi": _map(6, False), "single": _map(6, False)}, QUIET, 6, now=100.0)
    assert not campaign_over({"multi": _map(6, True), "single": _map(6, False)}, QUIET, 6, now=100.0)
    assert campaign_over({"multi": _map(6, True), "single": _map(6, True)}, QUIET, 6, now=100.0)


def test_final_map_with_too_few_positions_is_not_over():
    assert not campaign_over({"multi": _map(5, True), "single": _map(6, True)}, QUIET, 6, now=100.0)
    assert not campaign_over({"multi": _map(6, True)}, QUIET, 6, now=100.0)


def test_without_final_field_quiet_time_decides():
    maps = {"multi": _map(6), "single": _map(6)}
    assert not campaign_over(maps, QUIET, 6, now=5.0)
    assert campaign_over(maps, QUIET, 6, now=7.0)
    assert not campaign_over(maps, dict(QUIET, single_after=False), 6, now=7.0)


def test_demo_gives_the_recorder_longer_than_its_drain():
    """A recorder SIGKILLed while it drains leaves a file without its summary (seen under load:
    its own 1 Hz diagnostics kept the drain going past the demo's 20 s stop timeout)."""
    from ct_calib_nodes.nodes import ct_demo, mcap_recorder

    assert ct_demo.RECORDER_STOP_S > mcap_recorder.DRAIN_MAX_S + 5.0
