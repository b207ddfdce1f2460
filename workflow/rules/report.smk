# What `snakemake --report report.html` shows (captions in workflow/report/): per scene, the
# evaluation's renders, metrics table and training curve (`evaluate` marks eval/); for the
# workflow, the speed-accuracy Pareto plot of benchmarks/tradeoff.py when it has been made.
from pathlib import Path

TRADEOFF_PLOT = Path(workflow.basedir) / "benchmarks" / "results" / "tradeoff.png"


def evaluation_subcategory(wildcards):
    """The report's subcategory of a file of eval/ (its patterns name view, table or figure)."""
    if hasattr(wildcards, "view"):
        return "held-out renders"
    return "metrics" if hasattr(wildcards, "table") else "training curve"


def report_figures():
    """Inputs of the default target that only the report reads: the Pareto plot, if present
    (it is a benchmark's output, not a rule's: a workflow without it still runs)."""
    if not TRADEOFF_PLOT.is_file():
        return []
    # the caption path is relative to the Snakefile, whose target `all` lists the plot
    return [report(str(TRADEOFF_PLOT), caption="workflow/report/tradeoff.rst", category="Speed and accuracy",
                   subcategory="Pareto plot")]
