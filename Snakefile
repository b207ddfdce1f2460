# srfpipe: posed RGB captures -> Semantic Radiance Field simulators.
# Build one scene:   snakemake --cores 2 results/orchard/sim
# Build every scene: snakemake --cores 2
# Its report:        snakemake --report report.html
from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/report.smk"
include: "workflow/rules/capture.smk"
include: "workflow/rules/images.smk"
include: "workflow/rules/segment.smk"
include: "workflow/rules/train.smk"
include: "workflow/rules/occupancy.smk"
include: "workflow/rules/batch.smk"
include: "workflow/rules/sim.smk"


rule all:
    input:
        get_final_output(),
        report_figures(),
    default_target: True
