# The batch target: every scene file in scenes_dir, or the scenes of a sheet (config `sheet`), to
# the final artifact; and, when a run ends, one line per scene of that run (srfpipe.batch).
#   snakemake --workflow-profile workflow/profiles/slurm batch
# With --keep-going (both profiles) a failing scene stops only its own jobs.
BATCH_SCENES = batch_scenes()


rule batch:
    input:
        get_final_output(BATCH_SCENES),


onsuccess:
    run_summary(log)


onerror:
    run_summary(log)
