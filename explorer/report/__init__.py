"""The HTML report of a study: one self-contained file (figures embedded as PNG, no network access)
with the summary, the best candidate (Table 1 style), anytime losses against the baselines (Table 2
style), step curves (Figure 5), the Pareto front, the optimisation history, parameter importances,
depth maps of every path (Figure 4), and a sortable table of all trials.

Modules: ``html`` (the page: its context and the file written from it), ``figures`` (the figures,
as embedded PNG).
"""

from explorer.report.figures import measured_curve
from explorer.report.figures import measured_curve as _measured_curve  # noqa: F401  (the name tests draw it by)
from explorer.report.html import TABLE2_BUDGETS, build_context, write_report

__all__ = ["TABLE2_BUDGETS", "build_context", "measured_curve", "write_report"]
