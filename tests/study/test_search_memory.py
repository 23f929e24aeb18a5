import gc
import sys
import weakref

import explorer.study.search as search_module
from explorer.study.objective import Objective
from explorer.study.search import SearchConfig, SearchRun, search
from conftest import TINY_DATA

TINY = dict(space="tiny", data=TINY_DATA, train_size=(32, 32), input_size=(64, 64), train_steps=2,
            batch_size=8, val_limit=8, evaluator="proxy", finalists=0, baselines=())


def test_the_samplers_objective_is_let_go_when_sampling_ends(tmp_path, monkeypatch):
    """The sampler's Objective (with a supernet, its evaluator's caches: a gigabyte) is freed before the
    retrainings start, even in a process where it is the first to import optuna.artifacts (whose
    deferred ImportErrors keep the importing frames)."""
    for name in [m for m in sys.modules if m == "optuna.artifacts" or m.startswith("optuna.artifacts.")]:
        monkeypatch.delitem(sys.modules, name)
    made, alive_at_release = [], []

    class Tracked(Objective):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(weakref.ref(self))

    def release():
        gc.collect()
        alive_at_release.append(sum(ref() is not None for ref in made))

    monkeypatch.setattr(search_module, "Objective", Tracked)
    monkeypatch.setattr(search_module, "release_host_memory", release)
    out = search(SearchConfig(study="memory", **TINY).resolve(),
                 SearchRun(n_trials=2, timeout_s=None, reports=tmp_path))
    assert len(out.study.trials) == 2 and len(made) == 1
    assert alive_at_release == [0, 0]   # none before sampling, and the sampler's is gone after it
