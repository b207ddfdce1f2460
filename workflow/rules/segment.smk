# Per-prompt masks (one job per prompt) and their composite into labels.zarr.
# Each segment job's params hold only what matters for its prompt (srfpipe.segment.run.prompt_options),
# so adding or changing one prompt reruns that prompt's job and the composite, nothing else.
from srfpipe.segment.rules import scene_masks, scene_prompts, segment_model, segment_params


wildcard_constraints:
    prompt="[A-Za-z0-9_-]+",


rule segment:
    input:
        images=rules.downscale.output[0],
        model=segment_model(SCENES),
    output:
        directory(f"{RESULTS}/{{scene}}/masks/{{prompt}}.zarr"),
    params:
        options=segment_params(SCENES),
    log:
        "logs/{scene}/segment_{prompt}.log",
    benchmark:
        "benchmarks/runs/{scene}/segment_{prompt}.tsv"
    threads: 2
    resources:
        mem_mb=4000,
        runtime=60,
    shell:
        "srfpipe segment --images {input.images:q} --prompt {wildcards.prompt:q} --threads {threads} "
        "--options {params.options:q} --out {output:q} > {log:q} 2>&1"


# images.zarr gives the frames the labels describe (and their size when there are no prompts:
# a capture without masks gets labels with zero classes).
rule composite:
    input:
        images=rules.downscale.output[0],
        masks=scene_masks(SCENES, RESULTS),
    output:
        directory(f"{RESULTS}/{{scene}}/labels.zarr"),
    params:
        options=scene_section("labels"),
        prompts=scene_prompts(SCENES),  # the class order: a reordering re-runs the composite
    log:
        "logs/{scene}/composite.log",
    benchmark:
        "benchmarks/runs/{scene}/composite.tsv"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=30,
    shell:
        "srfpipe composite --images {input.images:q} --masks {input.masks:q} --options {params.options:q} "
        "--out {output:q} > {log:q} 2>&1"
