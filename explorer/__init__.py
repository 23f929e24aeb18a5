"""anytime-explorer: hardware-aware design-space exploration of anytime depth networks."""

__version__ = "0.1.0"
