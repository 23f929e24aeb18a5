"""bench_held_out (experiments/held_out.py) measures the study's winner and the paper design on the
validation frames the study did not choose with."""

from __future__ import annotations

import dataclasses
import re

import pytest
import torch

from experiments.held_out import EARLY_HEADS, LEVER_NETWORKS, parse_recipes
from experiments.lib.retraining import Network, held_out_data, reference_of, resolve_networks, retrained

from explorer.data import open_dataset
from explorer.space import Candidate, paper_candidate
from explorer.study.config import SearchConfig

from conftest import TINY_DATA


def test_only_the_frames_after_the_studys_are_measured():
    context = SearchConfig(study="held-out", data=TINY_DATA, input_size=(64, 64), train_size=(32, 32)).resolve()
    data = held_out_data(context, seed=3, val_from=10)
    val = open_dataset(TINY_DATA, "val", (64, 64), train_augment=False)
    assert len(data.deploy_val) == len(val) - 10
    assert torch.equal(data.deploy_val[0]["depth"], val[10]["depth"])
    assert torch.equal(data.deploy_val[len(val) - 11]["depth"], val[len(val) - 1]["depth"])
    assert tuple(data.train[0]["image"].shape[-2:]) == (32, 32)
    assert tuple(data.deploy_train[0]["image"].shape[-2:]) == (64, 64)


def test_a_start_past_the_validation_set_is_refused():
    context = SearchConfig(study="held-out", data=TINY_DATA, input_size=(64, 64), train_size=(32, 32)).resolve()
    with pytest.raises(SystemExit, match="validation set has 16 frames"):
        held_out_data(context, seed=0, val_from=16)


def test_recipes_take_the_studys_tuning_unless_given():
    fixed = SearchConfig(study="s", tune_steps=20)
    assert parse_recipes("300, 2000+130", fixed) == {"300": (300, 20), "2000_tune130": (2000, 130)}
    assert parse_recipes("2000", fixed) == {"2000": (2000, 20)}
    assert parse_recipes("300+20", fixed) == {"300_tune20": (300, 20)}
    assert parse_recipes("2000", SearchConfig(study="s")) == {"2000": (2000, 133)}   # the default share


@pytest.mark.parametrize("text", ["", "300x", "300+", "0", "300+-1"])
def test_a_recipe_that_is_not_n_or_n_plus_t_is_refused(text):
    with pytest.raises(SystemExit, match="--steps"):
        parse_recipes(text, SearchConfig(study="s"))


def test_networks_beside_the_paper_design_are_the_spaces_largest_or_a_yaml(tmp_path):
    context = SearchConfig(study="s", space="tiny").resolve()
    mine = Candidate(encoder_blocks=6, width_mult=0.5, decoder_widths=(256, 64, 32, 16), exits=(4,))
    (tmp_path / "mine.yaml").write_text(mine.to_yaml())
    networks = resolve_networks(f"paper, largest,{tmp_path / 'mine.yaml'}", None, context)
    assert list(networks) == ["paper", "largest", "mine"]
    assert networks["paper"].candidate == paper_candidate() and networks["mine"].candidate == mine
    assert {n.weights for n in networks.values()} == {"equal"}
    largest = networks["largest"].candidate
    assert context.space.contains(largest)
    assert largest.encoder_blocks == max(context.space.encoder_blocks)
    assert largest.width_mult == max(context.space.width_mult)


def test_a_field_changed_after_a_base_makes_a_network_just_outside_the_space():
    context = SearchConfig(study="s", space="anytime_depth").resolve()
    networks = resolve_networks("paper,paper:encoder_blocks=11:decoder_widths=[1024, 64, 32, 16]", None, context)
    assert list(networks) == ["paper", "paper_encoder_blocks_11_decoder_widths_1024_64_32_16"]
    deeper = networks["paper_encoder_blocks_11_decoder_widths_1024_64_32_16"].candidate
    assert deeper == dataclasses.replace(paper_candidate(), encoder_blocks=11, decoder_widths=(1024, 64, 32, 16))
    assert not context.space.contains(deeper)


def test_weights_anytime_trains_a_network_with_anytime_exit_weights_and_pairs_it_with_its_paper_design():
    context = SearchConfig(study="s", space="anytime_depth").resolve()
    networks = resolve_networks("paper,paper:weights=anytime,largest:weights=anytime,largest", None, context)
    assert list(networks) == ["paper", "paper_weights_anytime", "largest_weights_anytime", "largest"]
    assert networks["paper_weights_anytime"] == Network(paper_candidate(), "anytime")
    assert networks["largest_weights_anytime"].candidate == networks["largest"].candidate
    # a network is compared with the paper design trained the same way; the paper design's variant with the plain one
    assert reference_of("largest_weights_anytime", networks) == "paper_weights_anytime"
    assert reference_of("largest", networks) == "paper"
    assert reference_of("paper_weights_anytime", networks) == "paper"
    alone = resolve_networks("paper,largest:weights=anytime", None, context)
    assert reference_of("largest_weights_anytime", alone) == "paper"


def test_the_lever_networks_size_the_early_heads_and_keep_the_rest_of_each_network():
    context = SearchConfig(study="s", space="anytime_depth").resolve()
    largest = resolve_networks("paper,largest", None, context)["largest"].candidate
    networks = resolve_networks(LEVER_NETWORKS.replace("winner", "largest"), None, context)
    heads = "_" + re.sub(r"[^0-9A-Za-z]+", "_", EARLY_HEADS)   # a change's punctuation as underscores
    assert list(networks) == ["largest", "paper", f"largest{heads}", f"paper{heads}", f"largest{heads}_distill_1"]
    paper = networks[f"paper{heads}"].candidate
    # the paper design has no encoder exit: only its first exit's head (after the ECU) is sized
    assert paper == dataclasses.replace(paper_candidate(), ecu_head_depth=2, ecu_head_width=64)
    assert paper.head("ecu") == (2, 64) and paper.head("decoder") == paper_candidate().head("decoder")
    sized = networks[f"largest{heads}"].candidate
    assert sized.head("encoder") == (2, 64) and sized.head("ecu") == (2, 64)
    assert sized.head("decoder") == largest.head("decoder")
    assert dataclasses.replace(sized, encoder_head_depth=0, encoder_head_width=0, ecu_head_depth=0,
                               ecu_head_width=0) == largest
    assert networks[f"largest{heads}_distill_1"] == Network(sized, "equal", 1.0)
    assert networks[f"largest{heads}"].distill == 0.0 and reference_of(f"largest{heads}_distill_1", networks) == "paper"


@pytest.mark.parametrize("text, message", [("winner,largest", "include paper"),
                                           ("winner,paper:encoder_blocks=7", "include paper"),
                                           ("paper,biggest", "'biggest'"),
                                           ("paper,missing.yaml", "'missing.yaml'"),
                                           ("paper,paper:encoder_blocks", "not FIELD=VALUE"),
                                           ("paper,paper:weights=budget", "use one of equal, anytime"),
                                           ("paper,paper:encoder_blocks=13", "needs 5 decoder stages"),
                                           ("paper,paper:colour=red", "unknown candidate field"),
                                           ("paper,paper:decoder_widths=[1,", "not a YAML value")])
def test_networks_that_cannot_be_resolved_are_refused(text, message):
    with pytest.raises(SystemExit, match=message):
        resolve_networks(text, None, SearchConfig(study="s", space="tiny").resolve())


def _recipes_trained(monkeypatch, errors=None) -> list:
    """The training recipes retrained() hands over, collected instead of training (every path ``errors``,
    by default 1.0 m)."""
    import experiments.lib.retraining as retraining
    seen = []

    def fake_training(net, data, recipe, accelerator):
        seen.append(recipe.train)
        return type("Result", (), {"metrics": {"rmse": errors or [1.0] * net.candidate.num_paths}})()

    monkeypatch.setattr(retraining, "train_for_deployment", fake_training)
    return seen


def test_a_network_with_anytime_weights_is_trained_with_its_exits_anytime_shares(monkeypatch):
    from explorer.anytime import exit_loss_weights
    from explorer.cost import candidate_cost

    context = SearchConfig(study="s", data=TINY_DATA, input_size=(64, 64), train_size=(32, 32)).resolve()
    seen = _recipes_trained(monkeypatch)
    recipe = dataclasses.replace(context.config, finalist_steps=10).finalist_recipe()
    for weights in ("equal", "anytime"):
        retrained(Network(paper_candidate(), weights), recipe, 7, None, context)
    costs = candidate_cost(paper_candidate(), (64, 64)).path_costs(context.device, "time")
    assert seen[0].exit_weights is None and seen[0].seed == 7
    assert seen[1].exit_weights == exit_loss_weights(costs, context.budgets[0])
    assert seen[1].exit_weights[-1] > 1 / len(seen[1].exit_weights)   # the last path serves most of the budget


def test_distill_trains_a_network_with_self_distillation_and_pairs_it_with_its_paper_design(monkeypatch):
    context = SearchConfig(study="s", data=TINY_DATA, input_size=(64, 64), train_size=(32, 32)).resolve()
    networks = resolve_networks("paper,paper:distill=0.5,largest:distill=0.5", None, context)
    assert networks["paper_distill_0_5"] == Network(paper_candidate(), "equal", 0.5)
    assert reference_of("largest_distill_0_5", networks) == "paper_distill_0_5"
    with pytest.raises(SystemExit, match="not a number"):
        resolve_networks("paper,paper:distill=much", None, context)
    seen = _recipes_trained(monkeypatch)
    recipe = dataclasses.replace(context.config, finalist_steps=10).finalist_recipe()
    retrained(networks["paper_distill_0_5"], recipe, 7, None, context)
    assert seen[0].self_distill == 0.5


def test_the_early_error_and_ratio_take_the_paths_ready_before_9ms_on_the_tx2():
    from experiments.lib.retraining import early_error, early_to_last
    from explorer.cost import candidate_cost, get_device
    config = SearchConfig(study="s")
    paper = paper_candidate()
    ms = candidate_cost(paper, (224, 224)).path_costs(get_device("tx2"), "time")
    errors = [1.0] + [0.5 + 0.1 * k for k in range(len(ms) - 2)] + [0.25]
    early = [e for c, e in zip(ms[1:], errors[1:]) if c < 9.0]
    assert early   # the paper design's first path is ready at 6.4 ms on the TX2
    assert early_error(paper, errors, config) == pytest.approx(sum(early) / len(early))
    assert early_to_last(paper, errors, config) == pytest.approx(sum(early) / len(early) / 0.25)


@pytest.mark.parametrize("keep_every_exit", [False, True])
def test_a_retrained_network_is_scored_as_it_ships(monkeypatch, keep_every_exit):
    from explorer.cost import candidate_cost
    from explorer.model.shipped import ship
    context = SearchConfig(study="s", data=TINY_DATA, input_size=(64, 64), train_size=(32, 32),
                           keep_every_exit=keep_every_exit).resolve()
    errors = [1.0, 1.1, 0.5, 0.4, 0.3]   # the paper design's path 1 no better than the scan
    _recipes_trained(monkeypatch, errors)
    recipe = dataclasses.replace(context.config, finalist_steps=10).finalist_recipe()
    got = retrained(Network(paper_candidate()), recipe, 7, None, context)
    shipped = ship(paper_candidate(), errors, keep_every_exit)
    assert got.candidate == shipped.candidate and len(got.dropped) == (0 if keep_every_exit else 1)
    assert got.errors == ([1.0, 0.5, 0.4, 0.3] if not keep_every_exit else errors)
    assert got.costs == pytest.approx(candidate_cost(shipped.candidate, (64, 64)).path_costs(context.device, "time"))
