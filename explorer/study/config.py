"""A search's settings (``SearchConfig``: what a study is and how it runs) and the baselines it compares
against."""


import dataclasses
import json
from dataclasses import dataclass
from typing import Callable

from explorer.anytime import BudgetDistribution, parse_budget
from explorer.cost import get_device
from explorer.cost.devices import DeviceProfile, check_budget_priced
from explorer.data import SCORES, parse_data_spec
from explorer.errors import UserError
from explorer.files import parse_yaml
from explorer.model.reference import REFERENCES, ReferenceModel
from explorer.space import (
    Candidate,
    SearchSpace,
    check_size,
    fastdepth_candidate,
    paper_candidate,
    paper_nee_candidate,
)
from explorer.study.records import study_record
from explorer.supernet import SupernetRecipe
from explorer.supernet.evaluators import EVALUATORS
from explorer.training.deployment import DeploymentRecipe
from explorer.training.train import PROXY, TrainConfig

#: the device a study is priced on, and the budget it minimizes for, unless told otherwise (--device, --budget)
DEFAULT_DEVICE = "tx2"
DEFAULT_BUDGET = "time:uniform:33ms"
#: the devices a study's winner is also priced on, after the study's own (the report's tables, an export)
COMPARISON_DEVICES = ("tx2", "rpi4")

BASELINES: dict[str, Callable[[], Candidate]] = {
    "paper": paper_candidate, "paper-nee": paper_nee_candidate, "fastdepth": fastdepth_candidate}
#: what a study compares against unless told otherwise (--baselines)
DEFAULT_BASELINES = tuple(BASELINES)


def baseline_model(name: str):
    """The candidate, or the reference network (:class:`~explorer.model.reference.ReferenceModel`),
    that the baseline ``name`` stands for."""
    if name in BASELINES:
        return BASELINES[name]()
    if name in REFERENCES:
        return ReferenceModel(name)
    raise UserError(f"unknown baseline '{name}': use {', '.join(BASELINES)} or a reference network "
                    f"({', '.join(REFERENCES)})")
OBJECTIVES = ("anytime_loss", "params", "macs", "first_exit_ms")
#: the finalists' tuning at the deployment size unless --tune-steps is given: this share of their steps
#: at the training size (20 of the default 300), and never fewer than TUNE_MIN_STEPS
TUNE_SHARE = 1 / 15
TUNE_MIN_STEPS = 20
#: how a study proposes candidates: TPE (NSGA-II with several objectives), or uniformly at random
SAMPLERS = ("tpe", "random")


def objective_names(config: "SearchConfig") -> list[str]:
    """What each objective is, for optuna-dashboard and Optuna's plots: anytime_loss[time:uniform:33ms]."""
    return [f"anytime_loss[{config.budgets[0]}]" if o == "anytime_loss" else o for o in config.objectives]


@dataclass(frozen=True)
class SearchConfig:
    study: str
    space: str = "anytime_depth"
    device: str = DEFAULT_DEVICE
    budgets: tuple[str, ...] = (DEFAULT_BUDGET,)
    data: str = "synthetic"
    objectives: tuple[str, ...] = ("anytime_loss",)
    metric: str = "rmse"
    input_size: tuple[int, int] = (224, 224)     # deployment size: costs are computed here
    train_size: tuple[int, int] = (64, 64)       # proxy training resolution
    train_steps: int = 150
    batch_size: int = 16
    lr: float = PROXY.lr
    val_limit: int | None = 96
    seed: int = 0
    max_params: float | None = None
    max_first_exit_ms: float | None = None
    baselines: tuple[str, ...] = DEFAULT_BASELINES   # () = none (--no-baselines)
    pruning: bool = True
    keep_weights: bool = True
    accelerator: str = "auto"
    evaluator: str = "auto"                      # supernet for dense labels, proxy for self-supervision
    supernet: str | None = None                  # a supernet file (default: the cached one)
    supernet_steps: int = 600
    finalists: int = 3                           # retrained stand-alone at the end (0 = none)
    finalist_steps: int = 300
    tune_steps: int | None = None                # the finalists' steps at --input-size (None: tuning_steps)
    max_retries: int = 2          # an interrupted trial (killed, Ctrl-C, lost worker) is tried again
    supervision: str = "supervised"              # supervised | self | mixed (see explorer.training.selfsup)
    poses: str = "net"                           # self-supervision's camera motion: net | given
    hints: bool = False                          # depth hints (explorer.training.depth_hints; poses given)
    amp: bool = False                            # the supernet's forward passes under bf16 autocast (GPUs)
    head_kinds: str = "rotate"                   # which supernet subnet trains which exit-head kind
    sampler: str = "tpe"                         # tpe (NSGA-II with several objectives) | random (uniform)
    self_distill: float = 0.0                    # every network's early exits also learn its last exit's map
    keep_every_exit: bool = False                # ship every exit, even one no better than an earlier path

    def __post_init__(self) -> None:
        if self.evaluator == "auto":  # the supernet is trained with dense labels; self-supervision trains alone
            object.__setattr__(self, "evaluator", "supernet" if self.supervision == "supervised" else "proxy")
        # studies made before --baselines stored on (True) or off (False)
        baselines = self.baselines
        if isinstance(baselines, bool):
            baselines = DEFAULT_BASELINES if baselines else ()
        object.__setattr__(self, "baselines", tuple(baselines))

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        for k in ("budgets", "objectives", "input_size", "train_size", "baselines"):
            d[k] = list(d[k])
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "SearchConfig":
        d = dict(d)
        for k in ("budgets", "objectives", "input_size", "train_size"):
            if k in d:
                d[k] = tuple(d[k])
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})

    def train_config(self) -> TrainConfig:
        return dataclasses.replace(PROXY, steps=self.train_steps, batch_size=self.batch_size,
                                   input_size=self.train_size, lr=self.lr, lr_end=self.lr / 10,
                                   seed=self.seed, supervision=self.supervision, poses=self.poses,
                                   hints=self.hints, self_distill=self.self_distill,
                                   eval_every=max(2 * self.train_steps // 3, 1) if self.pruning else 0)

    def finalist_config(self, seed: int | None = None) -> TrainConfig:
        """The longer stand-alone recipe of the finalists (and of the baselines beside them)."""
        return dataclasses.replace(self.train_config(), steps=self.finalist_steps, eval_every=0,
                                   seed=self.seed if seed is None else seed)

    @property
    def tuning_steps(self) -> int:
        """The finalists' steps at the deployment size: ``tune_steps`` where given, else the default share
        of ``finalist_steps`` (TUNE_SHARE, never below TUNE_MIN_STEPS). A longer recipe with the same few
        tuning steps left both networks of bench_held_out worse than the short one did; with the same
        share of tuning they were better."""
        if self.tune_steps is not None:
            return self.tune_steps
        return max(TUNE_MIN_STEPS, round(self.finalist_steps * TUNE_SHARE))

    def finalist_recipe(self) -> DeploymentRecipe:
        """The finalists' whole recipe: ``finalist_config`` at the training size, then ``tuning_steps``
        at the deployment size, where every path is measured (explorer.training.deployment)."""
        return DeploymentRecipe(self.finalist_config(), tuple(self.input_size), self.tuning_steps)

    def supernet_recipe(self):
        return SupernetRecipe(steps=self.supernet_steps, batch_size=self.batch_size, input_size=self.train_size,
                              lr=self.lr, lr_end=self.lr / 10, seed=self.seed, amp=self.amp,
                              head_kinds=self.head_kinds, self_distill=self.self_distill)

    def resolve(self) -> "StudyContext":
        """Checks the settings (one line per mistake) and resolves the names they give (space, device,
        budgets) into what the layers below receive: done once, at the edge."""
        space, profile = SearchSpace.from_yaml(self.space), get_device(self.device)
        if not self.budgets:
            raise UserError("give at least one --budget")
        budgets = tuple(parse_budget(b) for b in self.budgets)
        for b in budgets:
            check_budget_priced(profile, b)
        self._check(space, profile)
        return StudyContext(self, space, profile, budgets)

    def validate(self) -> None:
        self.resolve()

    def _check(self, space: SearchSpace, profile: DeviceProfile) -> None:
        bad = [o for o in self.objectives if o not in OBJECTIVES]
        if bad or not self.objectives or self.objectives[0] != "anytime_loss":
            raise UserError(f"--objectives must start with anytime_loss and use only {list(OBJECTIVES)}")
        if self.metric not in SCORES:
            raise UserError(f"--metric {self.metric}: use one of {', '.join(SCORES)}")
        for name, size in (("--input-size", self.input_size), ("--train-size", self.train_size)):
            if len(size) != 2:
                raise UserError(f"{name} {size}: give HxW, e.g. 224x224")
            check_size(tuple(size), space.max_stride if name == "--input-size" else space.max_working_stride, name)
        if self.train_steps < 1:
            raise UserError("--proxy-steps must be at least 1")
        if self.sampler not in SAMPLERS:
            raise UserError(f"--sampler {self.sampler}: use one of {list(SAMPLERS)}")
        if self.evaluator not in EVALUATORS:
            raise UserError(f"--evaluator {self.evaluator}: use one of {list(EVALUATORS)}")
        if self.supernet and self.evaluator != "supernet":
            raise UserError("--supernet FILE is read by the supernet evaluator only: drop --evaluator proxy "
                            "(or give --evaluator supernet)")
        if self.supernet_steps < 1 or self.finalist_steps < 1:
            raise UserError("--supernet-steps and --finalist-steps must be at least 1")
        if self.tune_steps is not None and self.tune_steps < 0:
            raise UserError("--tune-steps must be 0 (none) or more")
        if self.finalists < 0:
            raise UserError("--finalists must be 0 (none) or more")
        if self.max_retries < 0:
            raise UserError("--max-retries must be 0 or more")
        if len(set(self.baselines)) != len(self.baselines):
            raise UserError(f"--baselines {','.join(self.baselines)}: a baseline is named twice")
        for name in self.baselines:
            model = baseline_model(name)
            if not isinstance(model, Candidate):
                h, w = self.train_size
                if h % model.stride or w % model.stride or min(h, w) < model.min_side:
                    raise UserError(f"--baselines {name} needs --train-size sides divisible by {model.stride} and "
                                    f"at least {model.min_side}, got {h}x{w} (e.g. 64x64)")
        self.train_config().validate()
        if "int8" in space.precision and "int8" not in profile.precisions:
            raise UserError(f"the space {space.name} lists precision int8, but the {self.device} profile prices no "
                            "int8 graphs: give --device a profile that does (`explorer calibrate --out mybox.yaml` "
                            "times int8 layers) or keep the space's precision at fp32")
        if self.supervision != "supervised" and not parse_data_spec(self.data).is_sequence:
            raise UserError(f"--supervision {self.supervision} needs sequence data (--data synthetic-seq, "
                            "kitti-seq:DRIVE or frames:FOLDER)")
        if self.supervision != "supervised" and self.evaluator == "supernet":
            raise UserError(f"--supervision {self.supervision}: the supernet is trained with dense labels; "
                            "add --evaluator proxy to search with self-supervised training")

    # settings that change what a trial's value means: a resumed study must keep them
    IDENTITY = ("space", "device", "budgets", "data", "objectives", "metric", "input_size", "train_size",
                "train_steps", "batch_size", "lr", "evaluator", "supernet_steps", "supervision", "poses", "hints", "amp",
                "head_kinds", "self_distill", "keep_every_exit")

    @classmethod
    def defaults_of_older_studies(cls) -> dict:
        """Settings a study made before they existed was run with."""
        return {"evaluator": "proxy", "finalists": 0, "supervision": "supervised", "poses": "net", "hints": False,
                "amp": False, "head_kinds": "random", "self_distill": 0.0, "keep_every_exit": True}


@dataclass(frozen=True)
class StudyContext:
    """A study's settings with their names resolved: its search space, device profile and budgets. Made
    once, at the edge (:meth:`SearchConfig.resolve` for a new run, :func:`study_context` for a stored
    study), and handed down instead of names."""

    config: SearchConfig
    space: SearchSpace
    device: DeviceProfile
    budgets: tuple[BudgetDistribution, ...]

    @property
    def budget(self) -> BudgetDistribution:
        """The budget the study minimizes the anytime loss for (the first)."""
        return self.budgets[0]

    def with_config(self, config: SearchConfig) -> "StudyContext":
        """The same context for settings that differ in how the run goes (steps, finalists), not in
        what is resolved."""
        return dataclasses.replace(self, config=config)


def study_context(study) -> StudyContext:
    """A stored study's context: its settings, the space and device profile it was created with (as it
    stored them: an edited space file or a recalibrated profile does not change a finished study), and
    its budgets."""
    config, stored = study_config(study), study_record(study)
    space = (_stored_space(study.study_name, stored.space_yaml, config.space) if stored.space_yaml
             else SearchSpace.from_yaml(config.space))
    device = (DeviceProfile.from_dict(stored.device_profile, "study") if stored.device_profile
              else get_device(config.device))
    return StudyContext(config, space, device, tuple(parse_budget(b) for b in config.budgets))


def stored_config(storage, name: str) -> dict | None:
    """The settings the study ``name`` stored in ``storage`` (None where there is no such study yet), read
    after its whole context (settings, space, device profile): a resumed study's damaged one is one line
    before any work (the data generated, the machine measured)."""
    import optuna
    try:
        study = optuna.load_study(study_name=name, storage=storage)
    except KeyError:
        return None
    study_context(study)
    return study_record(study).config


def _stored_space(study: str, text: str, source: str) -> SearchSpace:
    """The space a study stored (its YAML text), or one line naming the study when it is damaged (not
    YAML, nested past the reader's bound, not a valid space)."""
    try:
        return SearchSpace.from_dict(parse_yaml(text, source), source=source)
    except UserError as exc:
        raise UserError(f"study '{study}''s stored space is damaged ({exc}): restore the study's storage, "
                        "or search again under a new --study") from None


def study_config(study) -> SearchConfig:
    """The configuration an Optuna ``study`` was created with, as a checked :class:`SearchConfig`: the one
    place a study's stored settings are read back. A study made by an older version lacks later
    settings, which read as what it ran with; a study made outside ``explorer search`` (no stored
    settings) reads as the defaults."""
    stored = study_record(study).config
    if not stored:
        return SearchConfig(study=study.study_name)
    return _checked_config({"study": study.study_name, **SearchConfig.defaults_of_older_studies(), **stored})


def _checked_config(stored: dict) -> SearchConfig:
    """``stored`` settings as a SearchConfig, each of its type (``input_size: "big"`` is no size) and
    every number finite; a damaged one is one line."""
    import math

    import pydantic
    d = {k: v for k, v in stored.items() if k in {f.name for f in dataclasses.fields(SearchConfig)}}
    if isinstance(d.get("baselines"), bool):   # studies made before --baselines stored on or off
        d["baselines"] = list(DEFAULT_BASELINES) if d["baselines"] else []
    try:
        config = pydantic.TypeAdapter(SearchConfig).validate_python(d)
    except pydantic.ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err.get("loc", ()))
        raise UserError(f"study '{d['study']}''s stored settings are damaged ({where}: {err.get('msg')}): "
                        "restore the study's storage") from None
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        sizes = f.name in ("input_size", "train_size") and min(value) < 1
        if sizes or (isinstance(value, float) and not math.isfinite(value)):
            raise UserError(f"study '{d['study']}''s stored settings are damaged ({f.name}: {value}): "
                            "restore the study's storage")
    return config


def json_safe(x):
    return json.loads(json.dumps(x, default=float))
