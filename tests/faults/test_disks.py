"""Every place a command writes is checked before its work: a file where a folder goes, a folder nobody
can write (even root: /proc), is one line, exit 2, with nothing written."""

from pathlib import Path

import optuna
import pytest

from explorer.errors import UserError


def _plain_study(tmp_path) -> Path:
    journal = tmp_path / "s.log"
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    optuna.create_study(study_name="s", storage=optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(journal))))
    return journal


@pytest.mark.parametrize("out, says", [("existing.html", "is a file, not a folder for the report"),
                                       ("/proc/r", "cannot write the report there")])
def test_report_out_where_a_report_cannot_go_is_one_line(tmp_path, run_cli, out, says):
    journal = _plain_study(tmp_path)
    (tmp_path / "existing.html").write_text("mine")
    before = sorted(p.name for p in tmp_path.iterdir()), journal.read_bytes()
    code, _, err = run_cli("report", "--study", "s", "--storage", f"journal:{journal}",
                           "--out", out if out.startswith("/") else tmp_path / out)
    assert code == 2 and says in err and len(err.strip().splitlines()) == 1, err
    assert (sorted(p.name for p in tmp_path.iterdir()), journal.read_bytes()) == before
    assert (tmp_path / "existing.html").read_text() == "mine"


@pytest.mark.parametrize("out", ["/proc/x.png", "/proc/nope/x.npy"])
def test_a_depth_map_that_cannot_be_written_is_refused_before_the_model_runs(out):
    from explorer.deploy.runtime import check_depth_out
    with pytest.raises(UserError, match="give --out a path you can write") as caught:
        check_depth_out(Path(out))
    assert "\n" not in str(caught.value)


def test_a_search_in_a_folder_that_cannot_be_written_is_one_line(run_cli):
    code, _, err = run_cli("search", "--space", "tiny", "--trials", "1", "--storage", "journal:/proc/j.log")
    assert code == 2 and "give --reports or --storage a folder you can write" in err, err
    assert len(err.strip().splitlines()) == 1


def _no_work(*args, **kwargs):
    raise AssertionError("the command went on to its work")


@pytest.mark.parametrize("command", [["train", "paper", "--steps", "1", "--out", "/proc/x/ck.pt"],
                                     ["supernet", "train", "--space", "tiny", "--steps", "1",
                                      "--out", "/proc/x/sn.pt"]])
def test_training_onto_a_folder_that_cannot_be_written_is_one_line_before_any_training(run_cli, monkeypatch,
                                                                                       command):
    import explorer.data
    import explorer.supernet
    import explorer.training.train
    monkeypatch.setattr(explorer.data, "open_dataset", _no_work)
    monkeypatch.setattr(explorer.training.train, "train", _no_work)
    monkeypatch.setattr(explorer.supernet, "train_supernet", _no_work)
    code, _, err = run_cli(*command)
    assert code == 2 and "/proc/x: cannot write the" in err and "give --out" in err, err
    assert len(err.strip().splitlines()) == 1
