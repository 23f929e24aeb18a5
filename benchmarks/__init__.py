"""The product's speed and resources, in suites: ``python -m benchmarks.<suite> --list``.

- ``runtime``: deployment on this machine (the anytime runtime, path 0, skips, int8);
- ``training``: training steps (memory layout, the optimizer, threads, the supernet's pace);
- ``search``: the search's machinery (enumeration, fits, the sampler, storage, long studies);
- ``commands``: whole commands as a user runs them (``make search``, ``make test``, finalists);
- ``gpu``: a GPU kept busy, a whole study on one, and the search's rate.

``harness`` is what every suite (and every experiment, ``experiments/``) runs on.
"""
