"""A weight-sharing supernet over a search space: trained once per (space, data, recipe), then every
candidate of the space is a slice of it (the design guide, docs/design.md: "Evaluators"). :mod:`.evaluators`
estimates a candidate's accuracy during a search: its slice of the supernet, or a short training of its own."""

from explorer.supernet._slicing import super_name
from explorer.supernet.fidelity import describe_fidelity, measured_fidelity, store_fidelity
from explorer.supernet.network import (Supernet, largest_candidate, random_training_subnet, smallest_candidate,
                                       space_key)
from explorer.supernet.train import (HEAD_KINDS, SupernetRecipe, cache_key, default_path, train_supernet)
from explorer.supernet.train import load as load_supernet
from explorer.supernet.train import read as read_supernet

__all__ = ["HEAD_KINDS", "Supernet", "SupernetRecipe", "cache_key", "default_path", "describe_fidelity",
           "largest_candidate", "load_supernet", "measured_fidelity", "random_training_subnet", "read_supernet",
           "smallest_candidate", "space_key", "store_fidelity", "super_name", "train_supernet"]
