# Per-prompt masks (one job per prompt) and their composite into labels.zarr.
# Each segment job's params hold only what matters for its prompt (srfpipe.segment.run.prompt_options),
# so adding or changing one prompt reruns that prompt's job and the composite, nothing else.
import json

from srfpipe.segment.run import prompt_options


wildcard_constraints:
    prompt="[A-Za-z0-9_-]+",


def segment_params(wildcards):
    section = SCENES[wildcards.scene]["segmentation"]
    return json.dumps(prompt_options(section, wildcards.prompt), sort_keys=True)


def segment_model(wildcards):
    """The ONNX model file, an input so that a retrained model reruns the masks."""
    section = SCENES[wildcards.scene]["segmentation"]
    if section["backend"] != "onnx":
        return []
    if section["model"] == "builtin":
        from srfpipe.segment.onnx_backend import builtin_model_path

        return [str(builtin_model_path())]
    return [section["model"]]


def scene_masks(wildcards):
    """masks/{prompt}.zarr for the scene's prompts, in class order."""
    prompts = SCENES[wildcards.scene]["segmentation"]["prompts"]
    return [f"{RESULTS}/{wildcards.scene}/masks/{prompt}.zarr" for prompt in prompts]


rule segment:
    input:
        images=rules.downscale.output[0],
        model=segment_model,
    output:
        directory(f"{RESULTS}/{{scene}}/masks/{{prompt}}.zarr"),
    params:
        options=segment_params,
    log:
        "logs/{scene}/segment_{prompt}.log",
    benchmark:
        "benchmarks/runs/{scene}/segment_{prompt}.tsv"
    threads: 2
    resources:
        mem_mb=4000,
        runtime=60,
        gpu=0,
    shell:
        "srfpipe segment --images {input.images} --prompt {wildcards.prompt} --threads {threads} "
        "--no-progress --options {params.options:q} --out {output} > {log} 2>&1"


rule composite:
    input:
        masks=scene_masks,
    output:
        directory(f"{RESULTS}/{{scene}}/labels.zarr"),
    params:
        options=scene_section("labels"),
    log:
        "logs/{scene}/composite.log",
    benchmark:
        "benchmarks/runs/{scene}/composite.tsv"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=30,
    shell:
        "srfpipe composite --masks {input.masks} --no-progress --options {params.options:q} "
        "--out {output} > {log} 2>&1"
