"""onnxruntime sessions for the package: the probe's (one measurement path for calibration, the
runtime and export checks), with a provider this onnxruntime lacks turned into a user error."""

from __future__ import annotations

from explorer import probe
from explorer.errors import UserError


def check_provider(provider: str) -> None:
    """A provider this onnxruntime lacks is one UserError line naming those it has."""
    try:
        probe.check_provider(provider)
    except probe.ProbeError as exc:
        raise UserError(str(exc)) from None


def session(model: bytes, threads: int | None = None, provider: str = probe.DEFAULT_PROVIDER, **options):
    """The probe's session (one measurement path; ``options``: its ``optimize`` and ``save_optimized``);
    a provider this onnxruntime lacks is a UserError."""
    check_provider(provider)
    return probe.session(model, threads, provider, **options)
