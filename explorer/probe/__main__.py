"""``python -m explorer.probe``: the probe's command line (in a bundle: ``python3 probe.pyz``)."""

import sys

from .run import main

sys.exit(main())
