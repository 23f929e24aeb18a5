"""Training and validation splits that never share a frame.

Every source splits its frames here: sequences and recordings in time (the last tenth validates, a
gap keeps the neighbours of a validation frame out of training), unordered pairs by their listing.
A source too small for both splits is a :class:`UserError`.
"""

from __future__ import annotations

from explorer.errors import UserError

#: the share of a source's frames that validates when it names no split of its own
VAL_SHARE = 0.1
SPLITS = ("train", "val")


def split_range(count: int, split: str, where: str, share: float = VAL_SHARE, gap: int = 0,
                start: int = 0, what: str = "frame(s)") -> range:
    """Items ``start .. start + count - 1`` in order: ``val`` is the last ``share`` of them (at least
    one), ``train`` what precedes it less ``gap`` items, so that no training item lies within ``gap``
    of a validation one."""
    if split not in SPLITS:
        raise ValueError(f"split must be 'train' or 'val', got {split!r}")
    if not 0 < share < 1:
        raise UserError(f"{where}: the validation share must lie between 0 and 1, got {share:g}")
    n_val = max(int(round(count * share)), 1)
    n_train = count - n_val - gap
    if n_train < 1:
        need = n_val + gap + 1
        raise UserError(f"{where}: {count} {what} are too few for a training and a validation split "
                        f"(at least {need} needed); add frames or give a validation set of its own")
    items = range(start, start + count)
    return items[count - n_val:] if split == "val" else items[:n_train]


def parse_share(value: str, where: str) -> float:
    try:
        share = float(value)
    except ValueError:
        raise UserError(f"{where}: val={value!r} is neither a share (0.1) nor a CSV file of its own") from None
    if not 0 < share < 1:
        raise UserError(f"{where}: the validation share must lie between 0 and 1, got {share:g}")
    return share
