# The batch target: every scene file in scenes_dir, or the scenes of a sheet (config `sheet`), to
# the final artifact; and, when a run ends, one line per scene of that run (srfpipe.batch).
#   snakemake --workflow-profile workflow/profiles/slurm batch
# With --keep-going (both profiles) a failing scene stops only its own jobs.
from srfpipe.batch import print_summary, read_sheet


def _batch_scenes():
    if not config.get("sheet"):
        return sorted(SCENES)
    try:
        return read_sheet(config["sheet"], known=list(SCENES))
    except ValueError as exc:
        raise WorkflowError(str(exc)) from None


BATCH_SCENES = _batch_scenes()


rule batch:
    input:
        get_final_output(BATCH_SCENES),


def _summary(log):
    """One line per scene when the run built whole scenes (the batch or the default target); a run
    for single files (results/orchard/eval) is summarised by Snakemake's own job list."""
    try:
        targets = {job.rule.name for job in workflow.dag.targetjobs}
        scenes = sorted({job.wildcards.get("scene") for job in workflow.dag.jobs} - {None})
    except AttributeError:
        targets, scenes = {"batch"}, BATCH_SCENES
    if not targets & {"batch", "all"}:
        return
    chain = list(ARTIFACTS.values())
    chain = chain[: chain.index(ARTIFACTS[config["final_artifact"]]) + 1]
    print_summary(scenes, RESULTS, "logs", chain)


onsuccess:
    _summary(log)


onerror:
    _summary(log)
