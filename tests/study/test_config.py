"""The search's settings: what reaches the supernet's recipe, and what a study is identified by."""

import pytest

from explorer.cli import build_parser
from explorer.space import SearchSpace
from explorer.study.config import SearchConfig
from explorer.supernet import default_path


def test_amp_reaches_the_supernet_recipe_and_its_cache_file():
    plain, amp = SearchConfig(study="s"), SearchConfig(study="s", amp=True, train_size=(224, 224), batch_size=64)
    assert amp.supernet_recipe().amp and not plain.supernet_recipe().amp
    space = SearchSpace.from_yaml(plain.space)
    assert default_path(space, "synthetic", amp.supernet_recipe()) != default_path(space, "synthetic",
                                                                                 plain.supernet_recipe())
    assert "amp" in SearchConfig.IDENTITY     # a study estimated without it is not resumed with it


def test_a_study_made_before_amp_existed_reads_as_without_it():
    old = {k: v for k, v in SearchConfig(study="s").to_dict().items() if k != "amp"}
    assert SearchConfig.from_dict({**SearchConfig.defaults_of_older_studies(), **old}).amp is False


def test_search_takes_amp_on_the_command_line():
    assert build_parser().parse_args(["search", "--amp"]).amp is True
    assert build_parser().parse_args(["search"]).amp is False


def test_head_kinds_reach_the_supernet_recipe_and_a_study_made_before_them_reads_as_random():
    assert SearchConfig(study="s").supernet_recipe().head_kinds == "rotate"
    assert SearchConfig(study="s", head_kinds="cover").supernet_recipe().head_kinds == "cover"
    assert "head_kinds" in SearchConfig.IDENTITY   # a study estimated by one supernet is not resumed with another
    old = {k: v for k, v in SearchConfig(study="s").to_dict().items() if k != "head_kinds"}
    assert SearchConfig.from_dict({**SearchConfig.defaults_of_older_studies(), **old}).head_kinds == "random"
    assert build_parser().parse_args(["search", "--head-kinds", "cover"]).head_kinds == "cover"


def test_the_finalists_tuning_keeps_its_share_of_a_longer_recipe_unless_given():
    assert SearchConfig(study="s").finalist_recipe().tune_steps == 20              # the default 300 steps
    assert SearchConfig(study="s", finalist_steps=100).finalist_recipe().tune_steps == 20
    assert SearchConfig(study="s", finalist_steps=2000).finalist_recipe().tune_steps == 133
    assert SearchConfig(study="s", finalist_steps=2000, tune_steps=20).finalist_recipe().tune_steps == 20
    assert not SearchConfig(study="s", finalist_steps=2000, tune_steps=0).finalist_recipe().tunes


def test_a_study_stored_with_its_tuning_steps_keeps_them():
    stored = SearchConfig(study="s", tune_steps=20).to_dict()
    assert SearchConfig.from_dict({**stored, "finalist_steps": 2000}).finalist_recipe().tune_steps == 20
    assert SearchConfig.from_dict(SearchConfig(study="s").to_dict()).tune_steps is None


def test_search_leaves_the_tuning_steps_to_the_recipe_unless_given():
    assert build_parser().parse_args(["search"]).tune_steps is None
    assert build_parser().parse_args(["search", "--tune-steps", "5"]).tune_steps == 5


@pytest.mark.parametrize("stored, says", [
    ({"input_size": "big"}, r"damaged \(input_size: "),
    ({"input_size": [224, 224, 3]}, r"damaged \(input_size: "),
    ({"input_size": [0, 224]}, r"damaged \(input_size: \(0, 224\)"),
    ({"lr": float("nan")}, r"damaged \(lr: "),
    ({"seed": "x"}, r"damaged \(seed: "),
])
def test_a_study_whose_stored_settings_have_the_wrong_type_is_one_line(stored, says):
    import optuna

    from explorer.errors import UserError
    from explorer.study.config import SearchConfig, study_config
    from explorer.study.records import record_study
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(study_name="s")
    record_study(study, config={**SearchConfig(study="s").to_dict(), **stored})
    with pytest.raises(UserError, match=says) as caught:
        study_config(study)
    assert "\n" not in str(caught.value)


def test_a_study_stored_before_baselines_were_named_still_reads():
    import optuna

    from explorer.study.config import DEFAULT_BASELINES, SearchConfig, study_config
    from explorer.study.records import record_study
    study = optuna.create_study(study_name="s")
    record_study(study, config={**SearchConfig(study="s").to_dict(), "baselines": True, "input_size": [96, 128]})
    config = study_config(study)
    assert config.baselines == DEFAULT_BASELINES and config.input_size == (96, 128)


@pytest.fixture(scope="module")
def tiny_study(tmp_path_factory):
    """A one-trial study of the tiny space in a journal (copied by each test before damaging it)."""
    from explorer.study.search import SearchConfig, SearchRun, search
    from conftest import TINY_DATA
    folder = tmp_path_factory.mktemp("tiny-study")
    cfg = SearchConfig(study="s", space="tiny", data=TINY_DATA, train_size=(32, 32), input_size=(64, 64),
                       train_steps=2, batch_size=8, val_limit=8, evaluator="proxy", finalists=0)
    search(cfg.resolve(), SearchRun(storage_url=f"journal:{folder / 's.log'}", n_trials=1, timeout_s=None,
                                    reports=folder))
    return folder / "s.log"


DAMAGED_SPACES = {"not YAML": "name: [unclosed\n", "nested too deep": "[" * 5000,
                  "not a space": "- a list\n", "an unknown section": "name: x\nwings: {span: [3]}\n"}


@pytest.mark.parametrize("damage", DAMAGED_SPACES)
@pytest.mark.parametrize("command", ["report", "rescore", "envelope", "search"])
def test_a_study_whose_stored_space_is_damaged_is_one_line_naming_it(tmp_path, tiny_study, run_cli, damage, command):
    import shutil

    import optuna

    from conftest import TINY_DATA
    journal = tmp_path / "s.log"
    shutil.copy(tiny_study, journal)
    storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(journal)))
    optuna.load_study(study_name="s", storage=storage).set_user_attr("space_yaml", DAMAGED_SPACES[damage])
    files = lambda: sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*"))  # noqa: E731
    before = files(), journal.read_bytes()
    args = {"report": ["report", "--out", tmp_path / "r"],
            "rescore": ["rescore", "--device", "tx2", "--budget", "time:uniform:33ms"],
            "envelope": ["envelope", "--networks", "1"],
            "search": ["search", "--space", "tiny", "--data", TINY_DATA, "--train-size", "32x32", "--input-size",
                       "64x64", "--proxy-steps", "2", "--batch-size", "8", "--no-report", "--evaluator", "proxy",
                       "--finalists", "0", "--trials", "2"]}[command]
    code, _, err = run_cli(*args, "--study", "s", "--storage", f"journal:{journal}", "--reports", tmp_path)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "study 's''s stored space is damaged" in err and "restore the study's storage" in err, err
    assert (files(), journal.read_bytes()) == before
