import argparse
import json

import pandas as pd
import pytest
import yaml

from conftest import TINY_DATA


def test_help_lists_every_command(run_cli):
    code, out, _ = run_cli("--help")
    assert code == 0
    for cmd in ("space", "profile", "anytime", "devices", "calibrate", "enumerate", "data", "train",
                "evaluate", "search", "rescore", "report", "export", "run"):
        assert cmd in out


def _options(parser, path=()):
    import argparse
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _options(sub, path + (name,))
        elif not isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            yield " ".join(path), action


def test_every_option_of_every_command_is_explained_with_its_default():
    from explorer.cli import build_parser
    options = list(_options(build_parser()))
    assert len(options) > 100
    assert not [(cmd, a.option_strings or a.dest) for cmd, a in options if not a.help]
    shown = [(cmd, a) for cmd, a in options if a.help != argparse.SUPPRESS]   # deprecated spellings are hidden
    for cmd, a in shown:   # a default worth stating is stated, in the text's own words or appended
        if a.default not in (None, False, True) and not isinstance(a.default, list) and a.nargs is None:
            assert "default" in a.help, (cmd, a.option_strings)
    helps = {(cmd, a.option_strings[-1]): a.help for cmd, a in shown if a.option_strings}
    assert helps[("evaluate", "--input-size")] == "evaluation resolution HxW (default: the training size)"  # its own
    assert helps[("enumerate", "--input-size")].endswith("(default 224x224)")
    assert helps[("rescore", "--json")] == helps[("curve", "--json")]   # one explanation per flag


def test_help_renders_for_every_command(run_cli):
    from explorer.cli import build_parser
    commands = {cmd for cmd, _ in _options(build_parser()) if cmd}
    for cmd in commands:
        code, out, _ = run_cli(*cmd.split(), "--help")
        assert code == 0 and "usage: explorer" in out, cmd
    code, out, _ = run_cli("export", "--help")
    assert "(default 3%)" in out and "(default 32)" in out


def test_space_show_and_profile_json(run_cli):
    code, out, _ = run_cli("space", "show", "anytime_depth", "--json")
    assert code == 0 and json.loads(out)["size"] >= 10_000
    code, out, _ = run_cli("profile", "paper", "--device", "tx2", "--json")
    data = json.loads(out)
    assert code == 0 and len(data["paths"]) == 5 and data["paths"][4]["latency_ms"] > data["paths"][1]["latency_ms"]


def test_profile_candidate_file_and_measure(run_cli, tmp_path):
    from explorer.space import SearchSpace
    cand = list(SearchSpace.from_yaml("tiny").enumerate())[0]
    f = tmp_path / "c.yaml"
    f.write_text(cand.to_yaml())
    code, out, _ = run_cli("profile", f, "--input-size", "32x32", "--measure", "--repeats", "3",
                           "--provider", "CPUExecutionProvider", "--json")
    data = json.loads(out)
    assert code == 0 and data["measured"]["whole_graph_ms"] > 0
    assert all(p["measured_ms"] >= 0 for p in data["paths"])


def test_anytime_calculator(run_cli):
    code, out, _ = run_cli("anytime", "--path", "0:1.0", "--path", "2:0.5", "--path", "5:0.2",
                           "--budget", "time:uniform:10ms", "--json")
    assert code == 0 and json.loads(out)["anytime_loss"] == pytest.approx(0.45)


@pytest.mark.parametrize("args, msg", [
    (("anytime", "--path", "x", "--budget", "time:uniform:1ms"), "COST:LOSS"),
    (("anytime", "--path", "1:1", "--budget", "time"), "incomplete"),
    (("profile", "paper", "--input-size", "100x100"), "stride"),
    (("profile", "anytime_depth"), "explorer enumerate"),
    (("profile", "paper", "--input-size", "big"), "HxW"),
    (("profile", "paper", "--measure", "--provider", "NoSuchExecutionProvider"), "NoSuchExecutionProvider"),
    (("devices", "show", "tx9"), "unknown device"),
    (("search", "--device", "tx9"), "unknown device"),
    (("search", "--budget", "time:uniform:-1ms"), "quantity"),
    (("search", "--time-limit", "-5m"), "--time-limit"),
    (("search", "--baselines", "paper,resnet-9000"), "unknown baseline 'resnet-9000'"),
    (("search", "--baselines", "paper,paper"), "named twice"),
    (("search", "--baselines", "s2d-resnet18", "--train-size", "48x48"), "divisible by 32"),
    (("search", "--baselines", "monodepth2-resnet18", "--train-size", "32x32"), "at least 64"),
    (("search", "--baselines", "paper", "--no-baselines"), "not both"),
    (("rescore", "--study", "nope", "--device", "rpi4", "--budget", "time:uniform:33ms"), "no study journal"),
    (("report", "--study", "nope"), "no study journal"),
    (("export", "--out", "x"), "either --study"),
    (("evaluate", "missing.pt"), "no such file"),
])
def test_user_errors_are_one_line_exit_2(run_cli, tmp_path, args, msg):
    code, _, err = run_cli(*args, *(("--reports", tmp_path) if args[0] in ("rescore", "report") else ()))
    assert code == 2
    assert msg in err and len(err.strip().splitlines()) == 1, err


def test_malformed_profile_file(run_cli, tmp_path):
    f = tmp_path / "box.yaml"
    f.write_text(yaml.safe_dump({"name": "box", "overlap": "maybe", "bandwidth_gbs": 1, "kinds": {}}))
    code, _, err = run_cli("profile", "paper", "--device", f)
    assert code == 2 and "box.yaml" in err


def test_enumerate_writes_csv(run_cli, tmp_path):
    code, out, _ = run_cli("enumerate", "--space", "tiny", "--device", "rpi4", "--input-size", "64x64",
                           "--csv", tmp_path / "t.csv")
    frame = pd.read_csv(tmp_path / "t.csv")
    assert code == 0 and len(frame) == 16 and frame["p_path0"].between(0, 1).all()
    assert (frame["last_exit_ms"] >= frame["first_exit_ms"]).all()


@pytest.mark.slow
def test_calibrate_quick_writes_a_profile(run_cli, tmp_path, monkeypatch):
    # the command, not the re-timing (tests/test_probe.py covers that): waiting for a calm machine and
    # timing again would make this test's duration depend on how busy the machine is
    monkeypatch.setattr("explorer.cli.devices.QUICK_PROBE", {"remeasure_passes": 0, "calm_wait_s": 0.0})
    monkeypatch.setattr("explorer.calibration.calibrate.RETIME_ROUNDS", 0)
    out = tmp_path / "box.yaml"
    code, _, err = run_cli("calibrate", "--out", out, "--quick", "--repeats", "3")
    assert code == 0, err
    data = yaml.safe_load(out.read_text())
    assert data["provenance"]["fit"][0]["count"] > 40 and "onnxruntime" in data["provenance"]["conditions"]
    code, o, _ = run_cli("profile", "paper", "--device", out, "--json")
    assert code == 0 and json.loads(o)["paths"][1]["latency_ms"] > 0
    code, _, err = run_cli("calibrate", "--out", out)
    assert code == 2 and "--force" in err


def test_data_inspect_train_evaluate(run_cli, tmp_path):
    code, out, _ = run_cli("data", "inspect", "--data", TINY_DATA, "--input-size", "32x32", "--frames", "4", "--json")
    d = json.loads(out)
    assert code == 0 and d["frames"] == 16 and d["inspected"] == 4 and d["path0"]["rmse"] > 0
    ckpt = tmp_path / "c.pt"
    code, _, err = run_cli("train", "tiny", "--data", TINY_DATA, "--steps", "3", "--batch-size", "8",
                           "--train-size", "32x32", "--out", ckpt)
    assert code == 2 and "holds 16 candidates" in err
    from explorer.space import SearchSpace
    cfile = tmp_path / "cand.yaml"
    cfile.write_text(list(SearchSpace.from_yaml("tiny").enumerate())[0].to_yaml())
    code, _, err = run_cli("train", cfile, "--data", TINY_DATA, "--steps", "3", "--batch-size", "8",
                           "--train-size", "32x32", "--out", ckpt)
    assert code == 0, err
    code, out, _ = run_cli("evaluate", ckpt, "--data", TINY_DATA, "--json")
    assert code == 0 and len(json.loads(out)["paths"]) >= 2
    # another network's training never replaces this checkpoint
    before = ckpt.read_bytes()
    other = tmp_path / "other.yaml"
    other.write_text(list(SearchSpace.from_yaml("tiny").enumerate())[1].to_yaml())
    code, _, err = run_cli("train", other, "--data", TINY_DATA, "--steps", "1", "--batch-size", "8",
                           "--train-size", "32x32", "--out", ckpt)
    assert code == 2 and "holds the checkpoint of another network" in err and ckpt.read_bytes() == before
    # exits weighted by their share of the anytime loss: recorded in the checkpoint's recipe
    import torch
    from explorer.anytime import exit_loss_weights
    from explorer.cost import candidate_cost, get_device
    cand = SearchSpace.from_yaml("tiny").enumerate().__next__()
    weighted = tmp_path / "w.pt"
    code, _, err = run_cli("train", cfile, "--data", TINY_DATA, "--steps", "2", "--batch-size", "8",
                           "--train-size", "32x32", "--exit-weights", "anytime", "--device", "rpi4",
                           "--budget", "time:uniform:50ms", "--out", weighted)
    assert code == 0, err
    stored = torch.load(weighted, weights_only=True)["train_config"]["exit_weights"]
    expected = exit_loss_weights(candidate_cost(cand).path_costs(get_device("rpi4"), "time"), "time:uniform:50ms")
    assert stored == pytest.approx(list(expected)) and len(stored) == cand.num_paths - 1
    code, _, err = run_cli("train", cfile, "--data", TINY_DATA, "--steps", "2", "--exit-weights", "1,2,3,4,5,6,7",
                           "--out", tmp_path / "x.pt")
    assert code == 2 and "one per exit" in err and not (tmp_path / "x.pt").exists()


@pytest.mark.slow
def test_search_rescore_report_export_cli(run_cli, tmp_path):
    common = ["--reports", tmp_path]
    code, out, err = run_cli("search", "--study", "cli", "--space", "tiny", "--data", TINY_DATA,
                             "--train-size", "32x32", "--input-size", "64x64", "--proxy-steps", "4",
                             "--batch-size", "8", "--trials", "5", "--timeout", "0", "--supernet-steps", "4",
                             "--finalists", "1", "--finalist-steps", "4", "--tune-steps", "2", *common)
    assert code == 0, err
    assert "ratio to the retrained paper-design baseline" in out and (tmp_path / "cli" / "report.html").is_file()
    assert "(one training run of each, seed 0)" in " ".join(out.split())   # one seed's figure says so
    assert "measured on the retrained network at 64x64, the deployment size, on the first 16 validation" in " ".join(out.split())
    assert "finalists: search estimate vs retrained" in out
    code, out, _ = run_cli("rescore", "--study", "cli", "--device", "rpi4", "--budget", "energy:uniform:0.5J",
                           "--json", *common)
    assert code == 0 and len(json.loads(out)) >= 3
    # in words: what was measured and what the search estimated are two tables, and which to trust is said
    code, out, _ = run_cli("rescore", "--study", "cli", "--device", "rpi4", "--budget", "time:uniform:100ms", *common)
    assert code == 0 and out.index("measured (") < out.index("estimates of the search (")
    assert "Pick from the measured table" in out and "--study cli --trial" in out
    code, _, err = run_cli("export", "--study", "cli", "--out", tmp_path / "m", "--input-size", "64x64", *common)
    assert code == 0, err
    manifest = json.loads((tmp_path / "m" / "manifest.json").read_text())
    assert manifest["source"]["study"] == "cli" and manifest["path_metrics"]
    assert manifest["measured"]["input_size"] == [64, 64] and "trained at" not in out
    # exported again over a measured curve: the curve, of the graphs replaced, goes and the export says so
    (tmp_path / "m" / "anytime_curve.json").write_text("{}")
    code, out, err = run_cli("export", "--study", "cli", "--out", tmp_path / "m", "--input-size", "64x64", *common)
    assert code == 0 and not (tmp_path / "m" / "anytime_curve.json").exists(), err
    assert f"removed {tmp_path / 'm' / 'anytime_curve.json'}" in " ".join(out.split())
    code, out, err = run_cli("export", "--study", "cli", "--out", tmp_path / "m32", "--input-size", "32x32", *common)
    assert code == 0, err
    assert "exported at 32x32, but its weights were trained at 64x64" in " ".join(out.split())
    at32 = json.loads((tmp_path / "m32" / "manifest.json").read_text())
    # what was measured at 32x32, never the study's figures for 64x64
    assert at32["measured"]["input_size"] == [32, 32] and at32["tuned_size"] == [64, 64]
    assert "study_path_metrics" not in at32["source"] and "study_path_metrics" in manifest["source"]
    assert at32["path_metrics"] != manifest["path_metrics"]
    code, _, err = run_cli("export", "--study", "cli", "--trial", "999", "--out", tmp_path / "m2", *common)
    assert code == 2 and "not a completed trial" in err


def test_notebook_copies_the_shipped_notebook_out_and_keeps_an_edited_copy(run_cli, tmp_path, monkeypatch):
    import explorer
    from pathlib import Path
    from explorer.cli.notebook import NOTEBOOKS_DIR
    from explorer.console import console
    # package data: what an installed wheel carries (pyproject's package-data), not the repository's
    assert NOTEBOOKS_DIR.parent == Path(explorer.__file__).resolve().parent
    shipped = (NOTEBOOKS_DIR / "analysis.ipynb").read_bytes()
    out = tmp_path / "analysis"
    monkeypatch.setattr(console, "width", 40)     # a narrow terminal: the command to copy stays whole
    code, stdout, err = run_cli("notebook", "--out", out)
    assert code == 0, err
    assert (out / "analysis.ipynb").read_bytes() == shipped and json.loads(shipped)["cells"]
    hint = stdout.splitlines()[1]
    assert "pip install jupyterlab" in hint and f"jupyter lab {out / 'analysis.ipynb'}" in hint
    code, stdout, _ = run_cli("notebook", "--out", out)   # the same again: nothing to refuse
    assert code == 0 and "unchanged" in stdout
    (out / "analysis.ipynb").write_text('{"cells": []}')   # the user's own edits
    code, _, err = run_cli("notebook", "--out", out)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--force" in err
    assert (out / "analysis.ipynb").read_text() == '{"cells": []}'
    code, _, err = run_cli("notebook", "--out", out, "--force")
    assert code == 0 and (out / "analysis.ipynb").read_bytes() == shipped
    (tmp_path / "a-file").write_text("x")
    code, _, err = run_cli("notebook", "--out", tmp_path / "a-file")
    assert code == 2 and "is a file" in err
