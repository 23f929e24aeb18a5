"""``explorer calibrate``'s progress: every phase of the work (re-timing passes included) counted on a
line of its own from 0 to its total, so that no line shows a stopped clock and an ETA of 0:00:00 while
its work goes on. Checked on rich's own task state, not on timings."""

from __future__ import annotations

import io
from rich.console import Console
from rich.progress import Progress

from explorer import probe
from explorer.calibration import calibrate as cal
from explorer.console import Phases


def _shown(calls: list[tuple[str, int, int | None]]) -> list[tuple[str, float, float | None]]:
    """Feeds ``calls`` to ``Phases`` on a real rich progress display; after each call, the line it
    updated is finished (its clock stopped, ETA 0:00:00) exactly when its count reached its total.
    Returns the lines at the end: (description, completed, total)."""
    bar = Progress(console=Console(file=io.StringIO()), auto_refresh=False)
    phases = Phases(bar)
    for what, done, total in calls:
        phases(what, done, total)
        task = next(t for t in bar.tasks if t.id == phases.task)
        assert task.description == what and task.completed == done
        left = total is None or done < total
        assert task.finished is not left, (what, done, total)
        assert not left or task.time_remaining != 0.0, (what, done, total)   # an ETA, or none yet: not 0:00:00
        assert sum(not t.finished for t in bar.tasks) <= 1   # the earlier phases are done
    return [(t.description, t.completed, t.total) for t in bar.tasks]


def _count(what: str, total: int) -> list[tuple[str, int, int]]:
    return [(what, i, total) for i in range(total + 1)]


CALIBRATION = ([(cal.EXPORTING, 0, None)] + _count(cal.EXPORTING, 4)[1:] + _count(probe.TIMING_GRAPHS, 6)
               + _count(probe.TIMING_AGAIN, 3) + _count(probe.MEASURING_ENERGY, 2) + _count(cal.FITTING, 1)
               + _count(probe.TIMING_AGAIN, 2) + _count(cal.FITTING, 1) + _count(cal.FITTING, 1))


def test_each_phase_and_each_pass_of_timing_again_runs_its_own_clock():
    lines = _shown(CALIBRATION)
    # a pass that starts again takes its earlier line's place: one line per phase, the latest pass
    assert lines == [(cal.EXPORTING, 4, 4), (probe.TIMING_GRAPHS, 6, 6), (probe.MEASURING_ENERGY, 2, 2),
                     (probe.TIMING_AGAIN, 2, 2), (cal.FITTING, 1, 1)]


def test_calibrate_counts_every_phase_from_zero_to_its_total(tmp_path, monkeypatch):
    """The probe's passes and energy as it reports them, a round of graphs far above the fit timed
    again (reported as timing again, not as the probe's first pass), and the fits between."""
    graphs = [f"L{i:03d}" for i in range(5)]

    def bundle(folder, progress=None, **kwargs):
        for i in range(3):
            progress(i + 1, 3)

    def fake_run_probe(folder, out, *args, progress=None, remeasure_passes=None, **kwargs):
        results = FakeProbe.results
        pending = [g for g in graphs if g not in results["layers"]]
        passes = [pending] + ([pending[:2]] if remeasure_passes else [])
        for labels in passes:
            progress(0, len(labels), probe.TIMING_GRAPHS if labels is pending else probe.TIMING_AGAIN)
            for i, label in enumerate(labels):
                results["layers"][label] = 1.0
                progress(i + 1, len(labels), probe.TIMING_GRAPHS if labels is pending else probe.TIMING_AGAIN)
        if args[3]:   # energy
            for i in range(3):
                progress(i, 2, probe.MEASURING_ENERGY)
        return results

    class FakeProbe:   # the probe module as calibrate sees it
        results = {"layers": {}, "stages": {}, "speed": {}}
        run_probe = staticmethod(fake_run_probe)

        def __getattr__(self, name):
            return getattr(probe, name)

    outliers = iter([["L001", "L003"], []])
    monkeypatch.setattr(cal, "_probe", FakeProbe())
    monkeypatch.setattr(cal, "write_bundle_dir", bundle)
    monkeypatch.setattr(cal, "fit_results", lambda results, **kwargs: "profile")
    monkeypatch.setattr(cal, "slow_outliers", lambda profile, results: next(outliers))
    calls = []
    assert cal.calibrate(progress=lambda *call: calls.append(call), results_out=tmp_path / "r.json",
                         remeasure_passes=1) == "profile"
    assert calls == ([(cal.EXPORTING, 0, None)] + _count(cal.EXPORTING, 3)[1:] + _count(probe.TIMING_GRAPHS, 5)
                     + _count(probe.TIMING_AGAIN, 2) + _count(probe.MEASURING_ENERGY, 2) + _count(cal.FITTING, 1)
                     + _count(probe.TIMING_AGAIN, 2) + _count(cal.FITTING, 1) + _count(cal.FITTING, 1))
    _shown(calls)
