import shutil
import subprocess

import optuna
import pytest

from explorer.report import write_report
from explorer.study.search import SearchConfig, SearchRun, search
from explorer.study.view import study_view
from conftest import TINY_DATA

# the whole default flow at toy size: supernet estimates, then finalists and baselines retrained
TINY = dict(space="tiny", data=TINY_DATA, train_size=(32, 32), input_size=(64, 64), train_steps=6,
            batch_size=8, val_limit=8, evaluator="supernet", supernet_steps=4, finalists=2, finalist_steps=6)


@pytest.fixture(scope="module")
def study_with_everything(tmp_path_factory):
    reports = tmp_path_factory.mktemp("rep")
    out = search(SearchConfig(study="rep", budgets=("time:uniform:30ms", "energy:uniform:0.5J"), **TINY).resolve(),
                 SearchRun(n_trials=9, timeout_s=None, reports=reports))
    study = out.study
    # a failed trial and a rejected (pruned) one, as a real study has
    t = study.ask()
    study.tell(t, state=optuna.trial.TrialState.FAIL)
    t = study.ask()
    t.set_user_attr("rejected", "too big")
    study.tell(t, state=optuna.trial.TrialState.PRUNED)
    return study, reports


@pytest.mark.slow
def test_report_holds_the_tables(study_with_everything):
    study, reports = study_with_everything
    path = write_report(study_view(study), reports / "rep")
    html = path.read_text()
    assert "Anytime loss against the baselines" in html and 'id="table2"' in html and 'id="trials"' in html
    assert "paper design" in html and "FastDepth-like" in html
    assert "L_T@33ms" in html and "L_E@0.5J" in html
    assert html.count("data:image/png;base64,") >= 4
    assert "http://" not in html and "https://" not in html  # opens offline
    assert '<meta name="viewport" content="width=device-width' in html   # a phone lays it out at its own width
    assert "FAIL" in html and "PRUNED" in html
    # how each device's costs were obtained in the words of `explorer devices`, fit errors in one unit
    assert "latency published, energy published" in html and "<td>calibrated</td>" not in html
    assert "Table 2 Rpi4 row: median error" in html and "71 measured GPU kernels: median error 15.1%, largest 65.6%" in html
    # the finalists: every retrained one beside its estimate, and the winner is a retrained one
    assert 'id="finalists-table"' in html and "(retrained)" in html
    assert "has no search estimate" in html     # the baselines outside the tiny space say why
    # how far the estimate can be trusted: no fidelity was measured for the tiny space, and it says so
    assert 'id="fidelity"' in html and "ranking of the space is unmeasured" in html
    # estimates and measurements on the front and in the history: filled or open marks, and the captions say so
    assert 'id="front-marks"' in html and "<b>open</b> marks (rings, crosses) are the search's <b>estimates</b>" in html
    assert 'id="history-figure"' in html


def test_finalists_agreement_is_named_for_what_it_is(study_with_everything):
    from explorer.study.results import estimate_fidelity, finalists_agreement
    study, _ = study_with_everything
    agreement = finalists_agreement(study)
    assert agreement is None or (-1 <= agreement["tau"] <= 1 and agreement["rows"] >= 3)
    assert "unmeasured" in estimate_fidelity(study_view(study))


def test_report_draws_the_winners_paths_on_a_time_axis(study_with_everything):
    from explorer.study.results import is_retrained, winner
    study, reports = study_with_everything
    assert is_retrained(winner(study))
    html = write_report(study_view(study), reports / "rep").read_text()
    figure = html.split('<figure id="paths-figure">', 1)[1].split("</figure>", 1)[0]
    assert '<img alt="Trial ' in figure and "data:image/png;base64," in figure
    # the times are the cost model's, the errors the retrained winner's, at the size it was measured at
    assert "ready on tx2 (estimated)" in figure and "RMSE (measured)" in figure
    assert "measured on the retrained network at 64x64" in figure and "B_max = 30 ms of time:uniform:30ms" in figure


def test_paths_worse_than_an_earlier_one_are_marked(study_with_everything, monkeypatch):
    from explorer.cost.devices import get_device
    from explorer.report import figures
    from explorer.study.results import winner
    assert figures.worse_than_earlier([0.5, 0.4, 0.45, 0.3, 0.3, 0.35]) == {2: 1, 5: 3}
    assert figures.worse_than_earlier([0.5, 0.6]) == {1: 0}
    study, _ = study_with_everything
    best = winner(study)
    # the winner as it would be had every path improved on the ones before but the last
    metrics = [{**m, "rmse": 1.0 - 0.1 * p} for p, m in enumerate(best.user_attrs["path_metrics"])]
    metrics[-1]["rmse"] = metrics[-2]["rmse"] + 0.05
    bad = optuna.trial.create_trial(values=best.values, user_attrs={**best.user_attrs, "path_metrics": metrics})
    drawn = []
    real_png = figures.png
    monkeypatch.setattr(figures, "png", lambda fig: drawn.append([t.get_text() for ax in fig.axes for t in ax.texts]
                                                                 + [ax.get_xlabel() for ax in fig.axes]) or real_png(fig))
    image, worse = figures.path_timeline(bad, get_device("tx2"), "time:uniform:30ms")
    last = len(metrics) - 1
    assert image and worse == {last: last - 1}
    assert f"worse than path {last - 1}" in drawn[0] and any("estimated on tx2" in t for t in drawn[0])


def test_depth_maps_are_drawn_at_the_deployment_size(study_with_everything, monkeypatch):
    """A retrained winner was measured, and ships, at the deployment size: its maps are drawn there, each
    path titled with its time on the device and its RMSE, over a colour bar in metres."""
    from explorer.cost.devices import get_device
    from explorer.report import figures
    from explorer.study.results import trial_losses, trial_path_costs, winner
    study, _ = study_with_everything
    best = winner(study)
    deployed = tuple(best.user_attrs["measured"]["input_size"])
    assert deployed != tuple(study.user_attrs["config"]["train_size"])
    sizes, drawn = [], []
    real_open, real_png = figures.open_dataset, figures.png
    monkeypatch.setattr(figures, "open_dataset",
                        lambda spec, split, size, **kw: sizes.append(tuple(size)) or real_open(spec, split, size, **kw))
    monkeypatch.setattr(figures, "png", lambda fig: drawn.append(
        ([ax.get_title() for ax in fig.axes], [ax.get_ylabel() for ax in fig.axes], fig.get_suptitle()))
        or real_png(fig))
    device = get_device("tx2")
    image, why = figures.depth_maps(study_view(study), best, None, device)
    assert image and not why and sizes == [deployed]
    titles, labels, legend = drawn[0]
    for p, (ms, rmse) in enumerate(zip(trial_path_costs(best, device, "time"), trial_losses(best))):
        assert f"path {p}\n{ms:.3g} ms\n{rmse:.3g} m" in titles
    assert "depth (m)" in labels and legend == "ms: estimated on tx2\nm: RMSE, measured"


def test_report_escapes_user_strings(tmp_path):
    study = optuna.create_study(study_name="<script>alert(1)</script>")
    study.set_user_attr("config", {"device": "tx2", "data": "<b>x</b>", "budgets": ["time:uniform:33ms"]})
    html = write_report(study_view(study), tmp_path).read_text()
    assert "<script>alert(1)</script>" not in html and "&lt;script&gt;" in html
    assert "<b>x</b>" not in html


def test_report_costs_the_reference_networks_on_every_device(tmp_path):
    study = optuna.create_study(study_name="refs")
    study.set_user_attr("config", {"device": "tx2", "budgets": ["time:uniform:33ms"]})
    html = write_report(study_view(study), tmp_path, devices=["tx2", "rpi4"]).read_text()
    assert 'id="references"' in html
    for name in ("fastdepth", "s2d-resnet50", "s2d-resnet18", "monodepth2-resnet18", "tx2 ms", "rpi4 ms"):
        assert name in html


def test_single_trial_study_reports(tmp_path):
    out = search(SearchConfig(study="one", baselines=False, **{**TINY, "finalists": 0}).resolve(),
                 SearchRun(n_trials=1, timeout_s=None, reports=tmp_path))
    assert write_report(study_view(out.study), tmp_path / "one").is_file()


def test_report_in_headless_chromium(study_with_everything, tmp_path):
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if not chromium:
        pytest.skip("Debian's chromium is not installed (make test installs it when it can)")
    study, reports = study_with_everything
    path = write_report(study_view(study), reports / "rep")
    shot = tmp_path / "report.png"
    args = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            f"--user-data-dir={tmp_path / 'profile'}", "--enable-logging=stderr", "--v=0",
            "--window-size=1280,3000", f"--screenshot={shot}", path.resolve().as_uri()]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert shot.is_file() and shot.stat().st_size > 50_000, proc.stderr[-2000:]
    console = [line for line in proc.stderr.splitlines() if "CONSOLE" in line or "Uncaught" in line]
    assert not console, console


@pytest.mark.parametrize("width", [1280, 390])
def test_report_fits_the_screen_and_every_image_loads(study_with_everything, tmp_path, width):
    """At a laptop's width and a phone's, nothing is wider than the viewport (wide tables scroll inside
    their card) and every figure decodes."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if not chromium:
        pytest.skip("Debian's chromium is not installed (make test installs it when it can)")
    import html as html_lib
    study, reports = study_with_everything
    report = write_report(study_view(study), reports / "rep").read_text()
    # the report in a frame of the screen's width (headless windows are 500 px or wider); a srcdoc frame
    # shares its parent's origin, so the parent measures it once it has loaded
    page = tmp_path / "probe.html"
    page.write_text(
        f'<html><body><iframe id="f" style="border:0" width="{width}" height="1500" '
        f'srcdoc="{html_lib.escape(report, quote=True)}"></iframe><script>'
        "document.getElementById('f').addEventListener('load', () => { const d = document.getElementById('f')"
        ".contentDocument; const imgs = [...d.images]; document.body.setAttribute('data-probe', "
        "[d.documentElement.scrollWidth, d.documentElement.clientWidth, imgs.length, "
        "imgs.filter(i => !i.complete || i.naturalWidth === 0).length].join(',')); });</script></body></html>")
    args = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-sync",
            "--disable-background-networking", "--disable-component-update", f"--user-data-dir={tmp_path / 'p'}",
            "--window-size=1400,1600", "--hide-scrollbars", "--virtual-time-budget=10000", "--dump-dom",
            page.resolve().as_uri()]
    dom = subprocess.run(args, capture_output=True, text=True, timeout=120).stdout
    probe_values = dom.split('data-probe="', 1)[1].split('"', 1)[0]
    scroll_width, viewport, images, broken = map(int, probe_values.split(","))
    assert viewport == width and scroll_width <= viewport, probe_values
    assert images >= 3 and broken == 0, probe_values


#: what the phone test reads from the page: its layout widths, the narrow-screen stylesheet's padding,
#: Table 2's box and cue, and every scrolling box's right edge
_LAYOUT = """JSON.stringify((() => {
  const d = document.documentElement, box = document.getElementById('table2-box'),
        cue = document.getElementById('table2-cue'), seen = cue.getBoundingClientRect();
  return {inner: innerWidth, page: d.scrollWidth, body: document.body.scrollWidth, client: d.clientWidth,
          pad: getComputedStyle(document.querySelector('main')).paddingLeft,
          box: [box.scrollWidth, box.clientWidth, getComputedStyle(box).overflowX],
          cue: [!cue.hidden && seen.height > 0 && seen.width > 0, seen.left, seen.right,
                seen.bottom <= box.getBoundingClientRect().top],
          rights: [...document.querySelectorAll('.scroll')].map(b => b.getBoundingClientRect().right)};
})())"""


@pytest.mark.parametrize("width, mobile", [(390, True), (1280, False)])
def test_report_on_a_phone_under_mobile_emulation(study_with_everything, tmp_path, width, mobile):
    """Chromium emulating a phone 390 px wide (where a page without the viewport meta tag is laid out at
    980 px) and a laptop: the narrow-screen stylesheet applies on the phone only, the page is no wider
    than the screen, wide tables scroll inside their own box, and Table 2's cue line (above its box)
    shows exactly when that box scrolls sideways: always on the phone."""
    import json

    from _chromium import chromium, evaluate_emulated
    if not chromium():
        pytest.skip("Debian's chromium is not installed (make test installs it when it can)")
    study, reports = study_with_everything
    page = write_report(study_view(study), reports / "rep")
    seen = json.loads(evaluate_emulated(page, _LAYOUT, tmp_path / "profile", width, 844, mobile))
    # the layout is the screen's width (less a laptop's vertical scroll bar; a phone's overlays the page)
    assert seen["inner"] == width and (seen["client"] == width if mobile else width - 20 <= seen["client"]), seen
    fits = seen["client"]
    assert seen["page"] <= fits and seen["body"] <= fits, seen                    # no sideways scroll of the page
    assert seen["pad"] == ("8px" if width < 700 else "32px"), seen                # the narrow-screen stylesheet
    assert all(right <= fits for right in seen["rights"]), seen                   # every wide table's box fits
    scrolls_sideways = seen["box"][0] > seen["box"][1] + 1
    assert seen["box"][2] == "auto" and seen["cue"][0] == scrolls_sideways, seen
    if mobile:
        shown, left, right, above = seen["cue"]
        assert scrolls_sideways and shown and 0 <= left and right <= fits and above, seen


@pytest.fixture(scope="module")
def study_with_envelope(study_with_everything, tmp_path_factory):
    """A copy of the study after ``explorer envelope`` retrained two dedicated networks."""
    from explorer.study.envelope import envelope_trials, train_envelope
    study, _ = study_with_everything
    reports = tmp_path_factory.mktemp("env")
    storage = optuna.storages.InMemoryStorage()
    optuna.copy_study(from_study_name=study.study_name, from_storage=study._storage, to_storage=storage)
    copy = optuna.load_study(study_name=study.study_name, storage=storage)
    train_envelope(study_view(copy), 2, reports)
    assert len(envelope_trials(copy)) == 2
    return copy, reports


@pytest.mark.slow
def test_after_explorer_envelope_its_networks_are_named_as_such(study_with_envelope):
    import re

    from explorer.study.envelope import dedicated_path, envelope_trials
    from explorer.study.finalists import finalist_trials
    from explorer.study.records import trial_record
    study, reports = study_with_envelope
    html = write_report(study_view(study), reports / "rep").read_text()
    # the table of all trials tags each one with the path it was trained for
    for t in envelope_trials(study):
        row = re.search(rf"<tr>\s*<td>{t.number}</td>.*?</tr>", html, re.S).group(0)
        assert f"envelope network for path {dedicated_path(trial_record(t))} (measured)" in row
    # the front and the history draw them as a series of their own, not among the finalists
    finalists = [t for t in finalist_trials(study) if not trial_record(t).baseline]
    for figure in ("Anytime loss against parameters", "Anytime loss against MACs", "Anytime loss by trial"):
        alt = re.search(rf'alt="({figure}[^"]*)"', html).group(1)
        assert "2 envelope networks (measured, one path each)" in alt, alt
        assert f"{len(finalists)} finalists (measured)" in alt, alt
    assert 'id="envelope-apart"' in html and "The 2 envelope networks of" in html


def test_envelope_networks_neither_join_the_front_nor_squash_it():
    import pandas as pd

    from explorer.report import figures
    rows = [dict(number=i, state="COMPLETE", value=v, baseline="", figures="estimate", params=p, macs=p)
            for i, (v, p) in enumerate([(0.45, 1e6), (0.42, 2e6), (0.40, 3e6), (0.44, 2.5e6)])]
    rows.append(dict(number=4, state="COMPLETE", value=0.41, baseline="", figures="measured", params=2e6, macs=2e6))
    plain = pd.DataFrame(rows)
    envelope = pd.DataFrame(rows + [
        dict(number=5, state="COMPLETE", value=v, baseline="", figures=f"{figures.ENVELOPE_TAG} for path {k} (measured)",
             params=p, macs=p) for k, (v, p) in enumerate([(0.95, 5e5), (0.61, 9e5), (0.39, 3.5e6)], start=1)])
    _, without = figures.pareto(plain, "params", "parameters")
    _, with_them = figures.pareto(envelope, "params", "parameters")
    assert "the front of the estimates (3 points)" in without and "the front of the estimates (3 points)" in with_them
    assert "1 finalists (measured)" in with_them
    # the two far above the candidates are drawn at the axis' top, the third where it is
    assert "3 envelope networks (measured, one path each), 2 of them above the axis" in with_them
    _, history = figures.history(envelope)
    assert "4 trials (estimates)" in history and "3 envelope networks" in history


def test_estimates_are_open_marks_and_measurements_filled(monkeypatch):
    """On the front and in the history, what was measured (finalists, measured baselines, envelope networks)
    is drawn filled and the search's estimates (candidates, estimated baselines) open, and the alt text
    says so: not told apart by the legend alone."""
    import pandas as pd
    from matplotlib.colors import to_rgba_array

    from explorer.report import figures
    drawn = []
    monkeypatch.setattr(figures, "png", lambda fig: drawn.append(fig) or "")
    rows = [dict(number=i, state="COMPLETE", value=v, baseline="", figures="estimate", params=p, macs=p)
            for i, (v, p) in enumerate([(0.45, 1e6), (0.42, 2e6), (0.40, 3e6)])]
    rows += [dict(number=3, state="COMPLETE", value=0.41, baseline="", figures="measured", params=2e6, macs=2e6),
             dict(number=4, state="COMPLETE", value=0.43, baseline="paper", figures="measured", params=2e6, macs=2e6),
             dict(number=5, state="COMPLETE", value=0.44, baseline="fastdepth", figures="estimate", params=1e6,
                  macs=1e6),
             dict(number=6, state="COMPLETE", value=0.42, baseline="", params=1.5e6, macs=1.5e6,
                  figures=f"{figures.ENVELOPE_TAG} for path 1 (measured)")]
    frame = pd.DataFrame(rows)
    alts = [figures.pareto(frame, "params", "parameters")[1], figures.history(frame)[1]]
    for fig, alt in zip(drawn, alts):
        assert figures.MARKS in alt and "open marks" in alt
        marks = {c.get_label(): c for c in fig.axes[0].collections if not c.get_label().startswith("_")}
        assert {"trials (estimates)", "finalists (measured)", "paper design (measured)"} <= set(marks), marks
        for label, mark in marks.items():
            faces = to_rgba_array(mark.get_facecolor()) if len(mark.get_facecolor()) else []
            filled = len(faces) > 0 and all(face[3] > 0 for face in faces)
            assert filled == ("measured" in label), label
