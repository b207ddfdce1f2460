# Train the semantic radiance field (srf.zarr) and evaluate it on held-out views (eval/).
# Checkpoints live beside the output ({scene}/srf.ckpt/), so a killed training job resumes
# when the rule runs again; the trainer removes them after success.
# threads: 2, the cores of the machines we measure on (a 4096-ray step of the demo, 96-cell grid,
# ~52 samples per ray early in training: 0.48 s on one thread, 0.37 s on two). Snakemake never
# runs other jobs on those cores, but another process outside it that shares them makes a
# two-thread step several times slower (every small op waits for the descheduled thread): then
# use `--set-threads train=1`.


rule train:
    input:
        images=rules.downscale.output[0],
        labels=rules.composite.output[0],
    output:
        directory(f"{RESULTS}/{{scene}}/srf.zarr"),
    params:
        options=scene_section("train"),
        holdout=holdout_every,
        checkpoints=lambda wildcards: f"{RESULTS}/{wildcards.scene}/srf.ckpt",
    log:
        stdout="logs/{scene}/train.log",
        metrics="logs/{scene}/train_metrics.jsonl",
    benchmark:
        "benchmarks/runs/{scene}/train.tsv"
    threads: 2
    resources:
        mem_mb=8000,
        runtime=120,
        gpu=0,
    shell:
        "srfpipe train --images {input.images:q} --labels {input.labels:q} --out {output:q} "
        "--checkpoints {params.checkpoints:q} --holdout-every {params.holdout} --threads {threads} "
        "--metrics-log {log.metrics:q} --options {params.options:q} > {log.stdout:q} 2>&1"


rule evaluate:
    input:
        images=rules.downscale.output[0],
        labels=rules.composite.output[0],
        srf=rules.train.output[0],
    output:
        report(
            directory(f"{RESULTS}/{{scene}}/eval"),
            patterns=["renders/{view}.png", "{table}.html", "{figure}.svg"],
            caption="../report/evaluation.rst",
            category="{scene}",
            subcategory=evaluation_subcategory,
        ),
    params:
        options=scene_section("evaluate"),
    log:
        "logs/{scene}/evaluate.log",
    benchmark:
        "benchmarks/runs/{scene}/evaluate.tsv"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
    shell:
        "srfpipe evaluate --images {input.images:q} --labels {input.labels:q} --srf {input.srf:q} "
        "--threads {threads} --options {params.options:q} --out {output:q} > {log:q} 2>&1"
