"""What the experiments share: stand-alone trainings and their cache (``labels``), rank fidelity against
them (``fidelity``, ``per_exit``, ``predictor``), and the machinery of the search-value strategies
(``comparison``)."""
