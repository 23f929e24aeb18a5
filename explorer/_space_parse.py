"""Helpers of :mod:`explorer.space` kept apart to hold that module to its size: reading one
dimension's choices from a space's YAML, and a stand-in for an Optuna trial."""

from __future__ import annotations

from typing import Any

from explorer.files import read_choices, read_stage_choices


class RandomTrial:
    """Stands in for an Optuna trial: each categorical is drawn uniformly."""

    def __init__(self, rng) -> None:
        self.rng = rng

    def suggest_categorical(self, name: str, choices: list) -> Any:
        return self.rng.choice(list(choices))


def parse_choices(values: dict, field: str, kind: Any, space_field: str, body: dict, key: str, where: str,
                  default: Any) -> None:
    """Reads ``body[key]``, the choices of ``field`` (of ``kind``; ``space_field``: where a space keeps
    them), into ``values`` (from ``default``, the default candidate's value, when the key is absent)."""
    if key not in body:
        if kind == "stages":
            values[field] = tuple((w,) for w in default)
        elif field == "exits":
            values[space_field] = tuple(default[:-1])
        elif kind != "positions":    # no required exits, no encoder exits: the dataclass's defaults
            values[field] = (default,)
        return
    raw = body[key]
    if kind == "stages":
        values[field] = read_stage_choices(raw, where)
    elif kind == "positions":
        values[space_field] = tuple(read_choices(raw, where, int, allow_empty=True))
    else:
        values[field] = tuple(read_choices(raw, where, kind))
