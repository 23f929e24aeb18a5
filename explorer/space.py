"""Search spaces (YAML) and the candidates they contain.

A :class:`Candidate` is one point of the model family (the design guide, in docs/): a small frozen,
hashable value that prints as YAML, names a trial, a cache entry and an exported model. A
:class:`SearchSpace` lists the choices of every searched dimension; it can be enumerated, sized,
and sampled by an Optuna trial.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import yaml

from explorer.errors import UserError
from explorer._space_parse import (HEAD_POSITIONS, RandomTrial, canonical_head, check_heads, describe_candidate,
                                   ecu_exit_drawn, encoder_exit_drawn, head_options, parse_choices, space_size,
                                   top_level_choices, two_layers, without_cascade)
from explorer.files import read_yaml

#: MobileNet v1 depthwise-separable blocks (in, out, stride), after conv0 (3 -> 32, stride 2).
MOBILENET_V1_BLOCKS: tuple[tuple[int, int, int], ...] = (
    (32, 64, 1), (64, 128, 2), (128, 128, 1), (128, 256, 2), (256, 256, 1), (256, 512, 2),
    (512, 512, 1), (512, 512, 1), (512, 512, 1), (512, 512, 1), (512, 512, 1),
    (512, 1024, 2), (1024, 1024, 1),
)

#: the shipped search spaces, package data (the repository links them as search_spaces/ at its top)
SPACES_DIR = Path(__file__).resolve().parent / "search_spaces"


def encoder_stride(blocks: int) -> int:
    """Output stride of MobileNet v1 truncated after ``blocks`` blocks (conv0 has stride 2)."""
    stride = 2
    for _, _, s in MOBILENET_V1_BLOCKS[:blocks]:
        stride *= s
    return stride


def check_size(size: tuple[int, int], stride: int, flag: str) -> tuple[int, int]:
    """``size`` (HxW) if both sides divide by the encoder's ``stride`` (what the decoder's up-sampling
    needs), else one UserError line naming ``flag`` and the nearest sizes that work."""
    h, w = size
    if h % stride or w % stride or min(h, w) < stride:
        up = lambda x: max(stride, -(-x // stride) * stride)   # noqa: E731
        raise UserError(f"{flag} {h}x{w}: both sides must be multiples of the encoder stride {stride} "
                        f"(e.g. {up(h)}x{up(w)})")
    return size


@dataclass(frozen=True)
class Candidate:
    """One network of the family. When ``ecu`` is off the LiDAR fields are 0 (canonical form)."""

    encoder_blocks: int = 9
    width_mult: float = 1.0
    ecu: bool = True
    lidar_depth: int = 4
    lidar_width: int = 16
    ecu_band: int = 3
    ecu_width: int = 256
    decoder_widths: tuple[int, ...] = (768, 64, 32, 16)
    exits: tuple[int, ...] = (0, 1, 2, 4)
    head_depth: int = 1
    head_width: int = 32
    # Added with the widened space; left out of to_dict() at these defaults, so keys stay stable.
    encoder_exits: tuple[int, ...] = ()    # image exits after these encoder blocks (stride 4 or 8)
    lidar_exit: bool = False               # a learned LiDAR-only path, run before the image encoder
    lidar_first: bool = False              # LiDAR encoder before the image encoder (encoder exits fuse it)
    precision: str = "fp32"                # "int8": deployed statically quantized, costed and measured so
    exit_residual: bool = False            # every exit corrects path 0 (the interpolated scan) instead of replacing it
    # exit heads sized for their position: 0 = as head_depth / head_width (canonical where they agree)
    encoder_head_depth: int = 0            # the encoder exits' heads (stride 4-8)
    encoder_head_width: int = 0
    ecu_head_depth: int = 0                # exit_0's head, after the ECU (the encoder's stride)
    ecu_head_width: int = 0
    downscale: int = 1                     # works at the input size divided by this (1: at the input size)

    def __post_init__(self) -> None:
        object.__setattr__(self, "decoder_widths", tuple(int(w) for w in self.decoder_widths))
        object.__setattr__(self, "exits", tuple(sorted({int(e) for e in self.exits})))
        object.__setattr__(self, "width_mult", float(self.width_mult))
        object.__setattr__(self, "encoder_exits", tuple(sorted({int(e) for e in self.encoder_exits})))
        object.__setattr__(self, "lidar_exit", bool(self.lidar_exit))
        object.__setattr__(self, "exit_residual", bool(self.exit_residual))
        object.__setattr__(self, "downscale", int(self.downscale))
        if not self.ecu:
            for name in ("lidar_depth", "lidar_width", "ecu_band", "ecu_width"):
                object.__setattr__(self, name, 0)
        # The order only changes anything when an encoder exit can fuse the LiDAR feature.
        object.__setattr__(self, "lidar_first", bool(self.lidar_first and self.ecu and self.encoder_exits))
        if self.head_depth == 1:
            object.__setattr__(self, "head_width", 0)
        for position, present in (("encoder", bool(self.encoder_exits)), ("ecu", 0 in self.exits)):
            for name, value in zip(("depth", "width"), canonical_head(self, position, present)):
                object.__setattr__(self, f"{position}_head_{name}", value)
        self.validate()

    def head(self, position: str) -> tuple[int, int]:
        """(depth, width) of the exit heads at ``position``: "encoder", "ecu" (exit_0) or "decoder"
        (width 0 for a one-layer head)."""
        depth = getattr(self, f"{position}_head_depth", 0) or self.head_depth
        width = (getattr(self, f"{position}_head_width", 0) or self.head_width) if depth == 2 else 0
        return depth, width

    # -- validation --------------------------------------------------------------------------
    def validate(self) -> None:
        n = len(MOBILENET_V1_BLOCKS)
        if not 1 <= self.encoder_blocks <= n:
            raise UserError(f"encoder_blocks={self.encoder_blocks} is out of range: MobileNet v1 has blocks 1..{n}")
        if not 0.1 <= self.width_mult <= 2.0:
            raise UserError(f"width_mult={self.width_mult} is out of range: use a value in [0.1, 2.0]")
        stride = encoder_stride(self.encoder_blocks)
        stages = int(math.log2(stride))
        if len(self.decoder_widths) != stages:
            raise UserError(
                f"encoder_blocks={self.encoder_blocks} gives stride {stride}, which needs "
                f"{stages} decoder stages, but decoder_widths has {len(self.decoder_widths)}: "
                "keep blocks whose stride matches the decoder")
        if any(w < 1 for w in self.decoder_widths):
            raise UserError(f"decoder_widths {list(self.decoder_widths)} must all be positive")
        if not self.exits:
            raise UserError("a candidate needs at least one exit (the last decoder stage)")
        if self.exits[-1] != stages:
            raise UserError(
                f"exits {list(self.exits)} must include the last decoder stage ({stages}): "
                "the last stage always has an exit")
        if self.exits[0] < 0:
            raise UserError(f"exit positions {list(self.exits)} must be >= 0 (0 = after the ECU)")
        for k in self.encoder_exits:
            if not 1 <= k < self.encoder_blocks or encoder_stride(k) not in ENCODER_EXIT_STRIDES:
                raise UserError(
                    f"encoder exit after block {k}: no such place in a {self.encoder_blocks}-block encoder; "
                    f"encoder exits go after a block at stride 4 or 8 (blocks {list(encoder_exit_blocks(self.encoder_blocks))})")
        if self.downscale not in DOWNSCALES:
            raise UserError(f"downscale={self.downscale} is not one of {list(DOWNSCALES)}")
        if self.precision not in PRECISIONS:
            raise UserError(f"precision {self.precision!r} is not one of {list(PRECISIONS)}")
        if self.head_depth not in (1, 2):
            raise UserError(f"head_depth={self.head_depth!r}: an exit head has 1 or 2 pointwise convs")
        if self.head_depth == 2 and self.head_width < 1:
            raise UserError("head_width must be positive when head_depth is 2")
        check_heads(self)
        if self.ecu:
            if self.lidar_depth < int(math.log2(stride)):
                raise UserError(
                    f"lidar_depth={self.lidar_depth} cannot reach the image feature's stride {stride}: "
                    f"it needs at least {int(math.log2(stride))} strided 1D convs")
            if self.lidar_width < 1 or self.ecu_width < 1:
                raise UserError("lidar_width and ecu_width must be positive when the ECU is on")
            if self.ecu_band < 1 or self.ecu_band % 2 == 0:
                raise UserError(f"ecu_band={self.ecu_band} must be a positive odd number of feature rows")

    # -- derived -------------------------------------------------------------------------------
    @property
    def stride(self) -> int:
        """What the input's sides must divide by: the encoder's stride times ``downscale``."""
        return encoder_stride(self.encoder_blocks) * self.downscale

    def frame_size(self, size: tuple[int, int]) -> tuple[int, int]:
        """The frames it trains or is scored on where ``size`` is asked for (data.frames_for_downscale)."""
        return (size[0] * self.downscale, size[1] * self.downscale)

    @property
    def working_stride(self) -> int:
        """The encoder's stride relative to the size the network works at (the input / ``downscale``)."""
        return encoder_stride(self.encoder_blocks)

    @property
    def num_paths(self) -> int:
        """Number of paths, path 0 (the interpolated scan) included."""
        return len(self.exits) + len(self.encoder_exits) + int(self.lidar_exit) + 1

    @property
    def key(self) -> str:
        """Short stable name: a hash of the canonical field values."""
        text = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha1(text.encode()).hexdigest()[:10]

    def describe(self) -> str:
        """The architecture in words."""
        return describe_candidate(self)

    def to_dict(self) -> dict[str, Any]:
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        d["decoder_widths"] = list(self.decoder_widths)
        d["exits"] = list(self.exits)
        d["encoder_exits"] = list(self.encoder_exits)
        for name, default in _LATER_FIELDS.items():
            if d[name] == default:
                del d[name]
        return d

    def to_yaml(self) -> str:
        return yaml.safe_dump({"candidate": self.to_dict()}, sort_keys=False)

    @classmethod
    def from_dict(cls, data: Any, source: str = "candidate") -> "Candidate":
        if not isinstance(data, dict):
            raise UserError(f"{source}: a candidate is a mapping of fields, got {type(data).__name__}")
        data = without_cascade(data, "exit_cascade", source)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise UserError(f"{source}: unknown candidate field(s) {unknown}; known: {sorted(known)}")
        try:
            return cls(**data)
        except (TypeError, ValueError, OverflowError) as exc:   # a field of the wrong type
            raise UserError(f"{source}: {str(exc).splitlines()[0]}") from None

    @classmethod
    def from_yaml(cls, path: str | Path) -> "Candidate":
        data = load_yaml(path)
        if isinstance(data, dict) and "candidate" in data:
            data = data["candidate"]
        return cls.from_dict(data, source=str(path))


#: Fields added after the first release, with the value that leaves them out of a candidate's dict.
_LATER_FIELDS: dict[str, Any] = {"encoder_exits": [], "lidar_exit": False, "lidar_first": False,
                                  "precision": "fp32", "exit_residual": False, "encoder_head_depth": 0,
                                  "encoder_head_width": 0, "ecu_head_depth": 0, "ecu_head_width": 0, "downscale": 1}
#: Numeric precisions a candidate may be deployed at (``explorer export --quantize``).
PRECISIONS = ("fp32", "int8")
#: Sizes a candidate may work at, as divisors of its input size: the image is averaged over
#: ``downscale`` x ``downscale`` pixels and the scan keeps the first return of each ``downscale`` columns
#: before the first stage that learns; its exits resize their depth maps to the input size.
DOWNSCALES = (1, 2, 4)
#: Strides at which an image exit may leave the encoder (after block k, before the decoder).
ENCODER_EXIT_STRIDES = (4, 8)


def encoder_exit_blocks(encoder_blocks: int = len(MOBILENET_V1_BLOCKS)) -> tuple[int, ...]:
    """Block numbers after which an encoder exit may sit in an ``encoder_blocks``-block encoder."""
    return tuple(k for k in range(1, encoder_blocks) if encoder_stride(k) in ENCODER_EXIT_STRIDES)


def paper_candidate() -> Candidate:
    """The paper's design (Table 1) as this project interprets it; see search_spaces/paper.yaml."""
    return Candidate()


def paper_nee_candidate() -> Candidate:
    """The paper's design without early exits ("Ours-NEE" in Table 2)."""
    return dataclasses.replace(Candidate(), exits=(4,))


def fastdepth_candidate() -> Candidate:
    """FastDepth-like: full MobileNet v1 (stride 32), FastDepth's decoder widths, one exit, image only."""
    return Candidate(encoder_blocks=13, width_mult=1.0, ecu=False,
                     decoder_widths=(512, 256, 128, 64, 32), exits=(5,), head_depth=1)


# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Dimension:
    """One searched dimension, declared once: the :class:`Candidate` field it sets, where a space's YAML
    lists its choices (``section.key``), the kind of its values ("positions": one yes/no parameter per
    optional place; "stages": one choice per decoder stage), and when a trial draws it (``applies``, on
    the parameters drawn before; ``several``: only where the space offers several choices)."""

    field: str
    section: str
    key: str
    kind: Any
    applies: Callable[[dict], bool] | None = None
    several: bool = False


def _ecu_on(params: dict) -> bool:
    return bool(params["ecu"])


def _ecu_and_encoder_exits(params: dict) -> bool:   # the stage order matters only then
    return bool(params["ecu"]) and encoder_exit_drawn(params)


#: The family's dimensions, in the order a trial draws them (the order fixes what a seeded sampler draws).
DIMENSIONS: tuple[Dimension, ...] = (
    Dimension("ecu", "ecu", "enabled", bool),
    Dimension("lidar_depth", "lidar_encoder", "depth", int, _ecu_on),
    Dimension("lidar_width", "lidar_encoder", "width", int, _ecu_on),
    Dimension("ecu_band", "ecu", "band", int, _ecu_on),
    Dimension("ecu_width", "ecu", "width", int, _ecu_on),
    Dimension("head_depth", "exits", "head_depth", int),
    Dimension("head_width", "exits", "head_width", int, lambda params: params["head_depth"] == 2),
    Dimension("exits", "exits", "optional", "positions"),
    Dimension("encoder_exits", "image_encoder", "exits", "positions"),
    Dimension("lidar_first", "lidar_encoder", "first", bool, _ecu_and_encoder_exits),
    Dimension("lidar_exit", "exits", "lidar_only", bool),
    Dimension("encoder_head_depth", "exits", "encoder_head_depth", int, encoder_exit_drawn),
    Dimension("encoder_head_width", "exits", "encoder_head_width", int, two_layers("encoder")),
    Dimension("ecu_head_depth", "exits", "ecu_head_depth", int, ecu_exit_drawn),
    Dimension("ecu_head_width", "exits", "ecu_head_width", int, two_layers("ecu")),
    Dimension("precision", "", "precision", str, several=True),
    Dimension("downscale", "", "downscale", int, several=True),
    Dimension("exit_residual", "exits", "residual", bool, several=True),
    Dimension("encoder_blocks", "image_encoder", "blocks", int),
    Dimension("width_mult", "image_encoder", "width_mult", float),
    Dimension("decoder_widths", "decoder", "widths", "stages"),
)
#: a space's field for a dimension of optional places, and the prefix of its parameters
_POSITIONS = {"exits": ("optional_exits", "exit"), "encoder_exits": ("optional_encoder_exits", "encoder_exit")}
#: YAML section -> {key: field}; ``exits.required`` lists places that are always there (not a dimension)
_SPACE_SCHEMA: dict[str, dict[str, str]] = {"exits": {"required": "required_exits"}}
for _dim in filter(lambda d: d.section, DIMENSIONS):
    _SPACE_SCHEMA.setdefault(_dim.section, {})[_dim.key] = _dim.field
_KINDS = {**{d.field: d.kind for d in DIMENSIONS}, "required_exits": "positions"}
#: the per-position head dimensions, each with its value in a candidate (resolved: 0 stands for head_depth/width)
_HEAD_FIELDS: dict[str, Callable[[Candidate], int]] = {
    f"{p}_head_{n}": (lambda c, p=p, i=i: c.head(p)[i]) for p in HEAD_POSITIONS for i, n in enumerate(("depth", "width"))}


@dataclass(frozen=True)
class _Param:
    """One Optuna parameter of a space: its name, choices, dimension, and its value in a candidate."""

    name: str
    choices: tuple
    dimension: Dimension
    value_of: Callable[[Candidate], Any]


_TOP_KEYS = set(_SPACE_SCHEMA) | {"name", "description", "precision", "downscale"}


def load_yaml(path: str | Path) -> Any:
    """A space or candidate YAML file, read safely (``explorer.files.read_yaml``)."""
    return read_yaml(path, "YAML file")


def resolve_space_path(spec: str | Path) -> Path:
    """A path, or the name of a shipped space (``tiny`` -> search_spaces/tiny.yaml)."""
    p = Path(spec)
    if p.is_file():
        return p
    shipped = SPACES_DIR / f"{spec}.yaml"
    if shipped.is_file():
        return shipped
    names = sorted(f.stem for f in SPACES_DIR.glob("*.yaml"))
    raise UserError(f"search space {spec!s} not found: give a YAML file or one of {names}")


@dataclass(frozen=True)
class SearchSpace:
    """Choices per dimension. ``decoder_widths`` holds one list of choices per decoder stage;
    ``optional_exits`` the exit positions that may or may not be present (the last stage's exit is
    always there)."""

    name: str
    encoder_blocks: tuple[int, ...]
    width_mult: tuple[float, ...]
    ecu: tuple[bool, ...]
    lidar_depth: tuple[int, ...]
    lidar_width: tuple[int, ...]
    ecu_band: tuple[int, ...]
    ecu_width: tuple[int, ...]
    decoder_widths: tuple[tuple[int, ...], ...]
    optional_exits: tuple[int, ...]
    head_depth: tuple[int, ...]
    head_width: tuple[int, ...]
    required_exits: tuple[int, ...] = ()
    optional_encoder_exits: tuple[int, ...] = ()
    lidar_first: tuple[bool, ...] = (False,)
    lidar_exit: tuple[bool, ...] = (False,)
    precision: tuple[str, ...] = ("fp32",)
    exit_residual: tuple[bool, ...] = (False,)
    encoder_head_depth: tuple[int, ...] = (0,)
    encoder_head_width: tuple[int, ...] = (0,)
    ecu_head_depth: tuple[int, ...] = (0,)
    ecu_head_width: tuple[int, ...] = (0,)
    downscale: tuple[int, ...] = (1,)
    description: str = ""
    source: str = ""

    @property
    def max_stride(self) -> int:
        """What every size the space's networks run at divides by: the largest encoder stride, times the
        largest ``downscale``."""
        return self.max_working_stride * max(self.downscale)

    @property
    def max_working_stride(self) -> int:
        """The largest encoder stride: every training size divides by it (networks work at that size)."""
        return max(encoder_stride(b) for b in self.encoder_blocks)

    @classmethod
    def from_yaml(cls, path: str | Path) -> "SearchSpace":
        path = resolve_space_path(path)
        data = load_yaml(path)
        return cls.from_dict(data, source=str(path))

    @classmethod
    def from_dict(cls, data: Any, source: str = "space") -> "SearchSpace":
        if not isinstance(data, dict):
            raise UserError(f"{source}: a search space is a mapping with sections {sorted(_SPACE_SCHEMA)}")
        unknown = sorted(set(data) - _TOP_KEYS)
        if unknown:
            raise UserError(f"{source}: unknown section(s) {unknown}; known: {sorted(_TOP_KEYS)}")
        defaults = Candidate()
        values: dict[str, Any] = {}
        for section, fields in _SPACE_SCHEMA.items():
            body = data.get(section, {}) or {}
            if not isinstance(body, dict):
                raise UserError(f"{source}: section '{section}' must be a mapping of {sorted(fields)}")
            if section == "exits":
                body = without_cascade(body, "cascade", f"{source}: exits.cascade")
            bad = sorted(set(body) - set(fields))
            if bad:
                raise UserError(f"{source}: unknown key(s) {bad} in '{section}'; known: {sorted(fields)}")
            for key, field in fields.items():
                parse_choices(values, field, _KINDS[field], _POSITIONS.get(field, (field,))[0], body, key,
                              f"{source}: {section}.{key}", getattr(defaults, field, None))
        values.update(top_level_choices(data, source, {"precision": (str, PRECISIONS), "downscale": (int, DOWNSCALES)}))
        space = cls(name=str(data.get("name", Path(source).stem)),
                    description=str(data.get("description", "")), source=source, **values)
        space._validate(source)
        return space

    def _validate(self, source: str) -> None:
        stages = len(self.decoder_widths)
        for blocks in self.encoder_blocks:
            if not 1 <= blocks <= len(MOBILENET_V1_BLOCKS):
                raise UserError(f"{source}: image_encoder.blocks {blocks} is out of range 1..{len(MOBILENET_V1_BLOCKS)}")
            stride = encoder_stride(blocks)
            if int(math.log2(stride)) != stages:
                raise UserError(
                    f"{source}: image_encoder.blocks {blocks} gives stride {stride} "
                    f"({int(math.log2(stride))} decoder stages) but decoder.widths lists {stages} stages: "
                    "a truncation must keep the stride the decoder needs")
        both = sorted(set(self.optional_exits) & set(self.required_exits))
        if both:
            raise UserError(f"{source}: exit position(s) {both} are both optional and required")
        for e in self.optional_exits + self.required_exits:
            if not 0 <= e < stages:
                raise UserError(
                    f"{source}: exits.optional has position {e}, but the decoder has stages 1..{stages} "
                    f"(0 = after the ECU; the last stage {stages} always has an exit)")
        if True in self.ecu:
            need = int(math.log2(encoder_stride(self.encoder_blocks[0])))
            low = [d for d in self.lidar_depth if d < need]
            if low:
                raise UserError(f"{source}: lidar_encoder.depth {low} cannot reach stride {2 ** need}: use >= {need}")
            even = [b for b in self.ecu_band if b < 1 or b % 2 == 0]
            if even:
                raise UserError(f"{source}: ecu.band {even} must be positive odd numbers of rows")
        for k in self.optional_encoder_exits:
            for blocks in self.encoder_blocks:
                if k not in encoder_exit_blocks(blocks):
                    raise UserError(
                        f"{source}: image_encoder.exits has block {k}, but a {blocks}-block encoder has no exit "
                        f"place there: encoder exits go after a block at stride 4 or 8, i.e. one of "
                        f"{list(encoder_exit_blocks(min(self.encoder_blocks)))}")
        for field in ("head_depth", *(f"{p}_head_depth" for p in HEAD_POSITIONS)):
            bad = [d for d in getattr(self, field) if d not in ((1, 2) if field == "head_depth" else (0, 1, 2))]
            if bad:
                raise UserError(f"{source}: exits.{field} {bad}: a head has 1 or 2 pointwise convs")
        # Every combination must be a valid candidate: build the smallest and largest.
        next(iter(self.enumerate()))

    # -- dimensions ----------------------------------------------------------------------------
    def _params(self) -> list[_Param]:
        """The space's Optuna parameters, in the order :meth:`sample` draws them (from :data:`DIMENSIONS`)."""
        out = []
        for dim in DIMENSIONS:
            if dim.kind == "positions":
                field, prefix = _POSITIONS[dim.field]
                out += [_Param(f"{prefix}_{k}", (False, True), dim, lambda c, k=k, f=dim.field: k in getattr(c, f))
                        for k in getattr(self, field)]
            elif dim.kind == "stages":
                out += [_Param(f"decoder_width_{k}", choices, dim, lambda c, k=k: c.decoder_widths[k - 1])
                        for k, choices in enumerate(self.decoder_widths, start=1)]
            elif dim.field in _HEAD_FIELDS and self._lists(dim):   # the candidate's head there, resolved
                out.append(_Param(dim.field, getattr(self, dim.field), dim, _HEAD_FIELDS[dim.field]))
            elif self._lists(dim):
                out.append(_Param(dim.field, getattr(self, dim.field), dim, lambda c, f=dim.field: getattr(c, f)))
        return out

    def _lists(self, dim: Dimension) -> bool:
        if dim.field in _HEAD_FIELDS:   # where the space sizes heads there, and the position can have an exit
            has = self.optional_encoder_exits if dim.field.startswith("encoder") else \
                0 in self.optional_exits + self.required_exits
            return bool(has) and getattr(self, dim.field) != (0,)
        if dim.several:
            return len(getattr(self, dim.field)) > 1
        if dim.applies is _ecu_and_encoder_exits:   # drawn only where both can be chosen
            return bool(self.optional_encoder_exits) and True in self.ecu
        return True

    def dimensions(self) -> dict[str, tuple]:
        """Every parameter a trial may draw, with its choices."""
        return {p.name: p.choices for p in self._params()}

    @property
    def size(self) -> int:
        """Number of distinct candidates (LiDAR/ECU choices only count when the ECU is on;
        head width only when heads have two layers)."""
        return space_size(self)

    def _exit_sets(self) -> Iterator[tuple[int, ...]]:
        last = len(self.decoder_widths)
        for mask in itertools.product((False, True), repeat=len(self.optional_exits)):
            chosen = [e for e, on in zip(self.optional_exits, mask) if on]
            yield tuple(sorted(chosen + list(self.required_exits))) + (last,)

    def enumerate(self) -> Iterator[Candidate]:
        """Every candidate once, in a deterministic order."""
        ecu_options: list[tuple] = []
        for on in self.ecu:
            if on:
                ecu_options += [(True, *c) for c in itertools.product(
                    self.lidar_depth, self.lidar_width, self.ecu_band, self.ecu_width)]
            else:
                ecu_options.append((False, 0, 0, 0, 0))
        heads = [(d, w) for d in self.head_depth for w in (self.head_width if d == 2 else (0,))]
        exit_sets = list(self._exit_sets())
        early: list[tuple] = []  # (ecu option, encoder exits, lidar first)
        for ecu in ecu_options:
            for mask in itertools.product((False, True), repeat=len(self.optional_encoder_exits)):
                enc = tuple(k for k, on in zip(self.optional_encoder_exits, mask) if on)
                orders = sorted(set(self.lidar_first)) if ecu[0] and enc else [False]
                early += [(ecu, enc, first) for first in orders]
        for blocks, wm, (ecu, enc, first), widths, exits, head, lidar_exit, residual, precision, downscale in \
                itertools.product(self.encoder_blocks, self.width_mult, early, itertools.product(*self.decoder_widths),
                                  exit_sets, heads, sorted(set(self.lidar_exit)), sorted(set(self.exit_residual)),
                                  dict.fromkeys(self.precision), dict.fromkeys(self.downscale)):
            for enc_head, ecu_head in itertools.product(head_options(self, "encoder", *head, bool(enc)),
                                                        head_options(self, "ecu", *head, 0 in exits)):
                yield Candidate(encoder_blocks=blocks, width_mult=wm, ecu=ecu[0], lidar_depth=ecu[1],
                                lidar_width=ecu[2], ecu_band=ecu[3], ecu_width=ecu[4],
                                decoder_widths=widths, exits=exits, head_depth=head[0], head_width=head[1],
                                encoder_exits=enc, lidar_exit=lidar_exit, lidar_first=first, precision=precision,
                                exit_residual=residual, downscale=downscale, encoder_head_depth=enc_head[0],
                                encoder_head_width=enc_head[1], ecu_head_depth=ecu_head[0], ecu_head_width=ecu_head[1])

    def sample(self, trial: Any) -> Candidate:
        """Draw a candidate with an Optuna trial (conditional dimensions only when they apply)."""
        params: dict[str, Any] = {}
        for p in self._params():
            if p.dimension.applies is None or p.dimension.applies(params):
                params[p.name] = trial.suggest_categorical(p.name, list(p.choices))
        return self.candidate_of(params)

    def candidate_of(self, params: dict[str, Any]) -> Candidate:
        """The candidate that the parameters :meth:`sample` drew stand for (a dimension not drawn takes
        its first choice, which the candidate's canonical form makes irrelevant)."""
        scalars = {d.field: params.get(d.field, getattr(self, d.field)[0]) for d in DIMENSIONS
                   if not isinstance(d.kind, str)}
        last = len(self.decoder_widths)
        exits = sorted([e for e in self.optional_exits if params[f"exit_{e}"]] + list(self.required_exits))
        return Candidate(**scalars, exits=tuple(exits) + (last,),
                         encoder_exits=tuple(k for k in self.optional_encoder_exits if params[f"encoder_exit_{k}"]),
                         decoder_widths=tuple(params[f"decoder_width_{k}"] for k in range(1, last + 1)))

    def random_candidates(self, count: int, seed: int = 0) -> list[Candidate]:
        """``count`` distinct candidates drawn at random (each dimension uniformly, as :meth:`sample`
        does), without enumerating the space; fewer if the space is smaller."""
        import random
        rng = random.Random(seed)
        trial = RandomTrial(rng)
        out: dict[Candidate, None] = {}
        for _ in range(20 * count + 100):
            out.setdefault(self.sample(trial))
            if len(out) == min(count, self.size):
                break
        return list(out)

    def params_of(self, candidate: Candidate) -> dict[str, Any]:
        """The Optuna parameters that :meth:`sample` would draw for ``candidate`` (for enqueueing)."""
        params: dict[str, Any] = {}
        for p in self._params():
            if p.dimension.applies is None or p.dimension.applies(params):
                params[p.name] = p.value_of(candidate)
        return params

    def contains(self, candidate: Candidate) -> bool:
        d = self.dimensions()
        p = self.params_of(candidate)
        inner = set(candidate.exits[:-1])
        return candidate.precision in self.precision and candidate.downscale in self.downscale and \
            candidate.exit_residual in self.exit_residual and \
            len(candidate.decoder_widths) == len(self.decoder_widths) and \
            set(candidate.encoder_exits) <= set(self.optional_encoder_exits) and all(
            v in d[k] for k, v in p.items()) and set(self.required_exits) <= inner and \
            inner <= set(self.optional_exits) | set(self.required_exits) and \
            not any(getattr(candidate, f) for f in _HEAD_FIELDS if f not in d)   # heads sized where not offered
