"""Human reports: markdown pieces, figures, and the diagnosis report.

Uses matplotlib.
"""

from hybrid_pk.evaluation.plots import error_histograms as error_histograms
from hybrid_pk.report.diagnosis_report import plot_cause_evidence as plot_cause_evidence
from hybrid_pk.report.diagnosis_report import write_diagnosis_report as write_diagnosis_report
from hybrid_pk.report.evidence import Evidence as Evidence
from hybrid_pk.report.evidence import cause_evidence as cause_evidence
from hybrid_pk.report.markdown import markdown_table as markdown_table
from hybrid_pk.report.markdown import stats_table as stats_table

__all__ = [
    "Evidence",
    "cause_evidence",
    "error_histograms",
    "markdown_table",
    "plot_cause_evidence",
    "stats_table",
    "write_diagnosis_report",
]
