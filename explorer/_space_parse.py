"""Helpers of :mod:`explorer.space` kept apart to hold that module to its size: reading one
dimension's choices from a space's YAML, and a stand-in for an Optuna trial."""

from __future__ import annotations

import math
from typing import Any, Callable

from explorer.errors import UserError
from explorer.files import read_choices, read_stage_choices


#: where an exit's head may be sized apart from ``head_depth``/``head_width`` (Candidate fields ``<position>_head_*``)
HEAD_POSITIONS = ("encoder", "ecu")


def head_words(candidate) -> str:
    """``candidate``'s exit heads in words, those sized for their position after the others."""
    words = lambda depth, width: "1 pw conv" if depth == 1 else f"2 pw convs ({width} ch)"   # noqa: E731
    out = words(candidate.head_depth, candidate.head_width)
    for position, where in (("encoder", "encoder exits"), ("ecu", "ECU exit")):
        if getattr(candidate, f"{position}_head_depth") or getattr(candidate, f"{position}_head_width"):
            out += f"; {where}: {words(*candidate.head(position))}"
    return out


def check_heads(candidate) -> None:
    """One UserError line where a head sized for its position is not a head."""
    for position in HEAD_POSITIONS:
        depth, width = candidate.head(position)
        if depth not in (1, 2) or (depth == 2 and width < 1):
            raise UserError(f"{position}_head_depth={depth!r}, {position}_head_width={width!r}: an exit head has "
                            "1 or 2 pointwise convs, the first of a positive width")


def canonical_head(candidate, position: str, present: bool) -> tuple[int, int]:
    """The stored (depth, width) override of ``candidate``'s heads at ``position``: 0 where it agrees
    with ``head_depth``/``head_width`` or the position has no exit, so one network has one key."""
    if not present:
        return 0, 0
    depth = getattr(candidate, f"{position}_head_depth") or candidate.head_depth
    width = (getattr(candidate, f"{position}_head_width") or candidate.head_width) if depth == 2 else 0
    return (0 if depth == candidate.head_depth else depth,
            0 if depth != 2 or width == candidate.head_width else width)


def head_options(space, position: str, depth: int, width: int, present: bool) -> list[tuple[int, int]]:
    """The distinct (depth, width) heads ``space`` offers at ``position`` where the other heads are
    (``depth``, ``width``); one, (0, 0), where the position has no exit."""
    if not present:
        return [(0, 0)]
    out: dict[tuple[int, int], None] = {}
    for d in getattr(space, f"{position}_head_depth"):
        d = d or depth
        for w in (getattr(space, f"{position}_head_width") if d == 2 else (0,)):
            out[(d, (w or width) if d == 2 else 0)] = None
    return list(out)


def encoder_exit_drawn(params: dict) -> bool:
    return any(v for k, v in params.items() if k.startswith("encoder_exit_"))


def ecu_exit_drawn(params: dict) -> bool:   # listed only where exit_0 is optional or required
    return bool(params.get("exit_0", True))


def two_layers(position: str) -> Callable[[dict], bool]:
    """Whether a trial draws ``position``'s head width: where the position has an exit whose head has two layers."""
    drawn = encoder_exit_drawn if position == "encoder" else ecu_exit_drawn
    return lambda params: drawn(params) and (params.get(f"{position}_head_depth") or params["head_depth"]) == 2


def space_size(space) -> int:
    """``SearchSpace.size``: LiDAR/ECU choices count only where the ECU is on, a head's width only where
    it has two layers, a position's heads only where it has an exit."""
    lidar = len(space.lidar_depth) * len(space.lidar_width) * len(space.ecu_band) * len(space.ecu_width)
    encoder_exit_sets = 2 ** len(space.optional_encoder_exits)
    exit_sets = 2 ** len(space.optional_exits)
    with_ecu_exit = exit_sets if 0 in space.required_exits else exit_sets // 2 if 0 in space.optional_exits else 0
    heads = 0
    for d in space.head_depth:
        for w in (space.head_width if d == 2 else (0,)):
            encoder = len(head_options(space, "encoder", d, w, True))
            # with the ECU on, a non-empty set of encoder exits also chooses the stage order
            ecu = sum(lidar * (1 + (encoder_exit_sets - 1) * len(set(space.lidar_first)) * encoder) if on
                      else 1 + (encoder_exit_sets - 1) * encoder for on in space.ecu)
            heads += ecu * (exit_sets - with_ecu_exit + with_ecu_exit * len(head_options(space, "ecu", d, w, True)))
    rest = len(space.encoder_blocks) * len(space.width_mult) * math.prod(len(c) for c in space.decoder_widths)
    return heads * rest * len(set(space.lidar_exit)) * len(set(space.exit_residual)) * len(set(space.precision)) \
        * len(set(space.downscale))


#: the one line for a stored candidate or a space that asks for cascaded exits
CASCADE_GONE = ("cascaded exits (exit_cascade, exits.cascade) were removed because they did not pay: retrained, "
                "they made the paper design's anytime loss worse in every seed (docs/evidence.md); search or "
                "retrain without them (residual exits, each correcting the scan, remain)")


def without_cascade(data: dict, key: str, where: str) -> dict:
    """``data`` less ``key`` where it holds only false (a candidate's ``exit_cascade`` at its default, a
    space's ``exits.cascade: [false]``), so what was stored so still loads; one UserError line otherwise."""
    if key not in data:
        return data
    raw = data[key]
    if any(v is not False for v in (raw if isinstance(raw, list) else [raw])):
        raise UserError(f"{where}: {CASCADE_GONE}")
    return {k: v for k, v in data.items() if k != key}


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


def describe_candidate(c) -> str:
    """A candidate's architecture in words."""
    parts = ["LiDAR-only exit first"] if c.lidar_exit else []
    if c.downscale > 1:
        parts.append(f"working at 1/{c.downscale} of the input size")
    parts.append(f"MobileNet v1 x{c.width_mult:g}, {c.encoder_blocks} blocks (stride {c.working_stride})")
    if c.encoder_exits:
        fused = " fused with the LiDAR feature" if c.lidar_first else ""
        parts.append("encoder exits after block " + ", ".join(map(str, c.encoder_exits)) + fused)
    if c.ecu:
        order = "before" if c.lidar_first else "after"
        parts.append(f"LiDAR encoder ({order} the image encoder) {c.lidar_depth} layers from "
                     f"{c.lidar_width} ch, ECU band {c.ecu_band} rows, {c.ecu_width} ch")
    else:
        parts.append("no LiDAR branch (image only)")
    parts.append("decoder " + "-".join(str(w) for w in c.decoder_widths))
    names = ["ECU" if e == 0 else f"stage {e}" for e in c.exits]
    head = head_words(c)
    correct = ", each correcting the interpolated scan" if c.exit_residual else ""
    parts.append(f"exits after {', '.join(names)} ({head}){correct}")
    if c.precision != "fp32":
        parts.append(c.precision)
    return "; ".join(parts)


def top_level_choices(data: dict, source: str, keys: dict[str, tuple[type, tuple]]) -> dict[str, tuple]:
    """The choices a space lists at its top level (``key: (kind, allowed values)``), each checked."""
    values = {}
    for key, (kind, allowed) in keys.items():
        if key in data:
            values[key] = tuple(read_choices(data[key], f"{source}: {key}", kind))
            bad = [v for v in values[key] if v not in allowed]
            if bad:
                raise UserError(f"{source}: {key} {bad} unknown: list some of {list(allowed)}")
    return values
