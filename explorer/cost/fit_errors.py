"""A device profile's fit errors in one unit: each fit's median and largest error relative to the figure
it was fitted to, as ``explorer devices`` and the report show them."""

from __future__ import annotations

import statistics

from explorer.cost.devices import DeviceProfile


def fit_errors(profile: DeviceProfile) -> list[dict]:
    """Each fit in ``profile``'s provenance as {what, count, median, max}, errors as fractions of the
    fitted figures (0.15 = 15%). A fit stored as absolute errors (rpi4's, of the anytime losses of the
    paper's Table 2) is read from its checks, the figures it was fitted to; a fit with neither has
    None."""
    checks = [c for c in profile.provenance.get("checks") or []
              if c.get("target") and c.get("predicted") is not None]
    out = []
    for fit in profile.provenance.get("fit") or []:
        if "median_abs_error" in fit:   # explorer.cost.fit.fit_summary: |predicted / measured - 1|
            out.append({"what": fit["what"], "count": fit.get("count"), "median": fit["median_abs_error"],
                        "max": fit.get("max_abs_error")})
        elif checks and fit.get("count") == len(checks):
            rel = [abs(c["predicted"] / c["target"] - 1) for c in checks]
            out.append({"what": fit["what"], "count": len(rel), "median": statistics.median(rel), "max": max(rel)})
        else:
            out.append({"what": fit["what"], "count": fit.get("count"), "median": None, "max": None})
    return out


def fit_words(fit: dict) -> str:
    """One fit in words: what, median and largest error in percent, over how many figures."""
    if fit["median"] is None:
        return f"{fit['what']}: no error recorded"
    largest = f", largest {percent(fit['max'])}" if fit["max"] is not None else ""
    count = f" over {fit['count']} figure{'s' if fit['count'] != 1 else ''}" if fit["count"] else ""
    return f"{fit['what']}: median error {percent(fit['median'])}{largest}{count}"


def percent(x: float) -> str:
    return f"{x:.1%}" if x >= 0.001 else "under 0.1%"
