"""Input and params functions for workflow/rules/segment.smk (kept out of the .smk files).

Each factory takes the workflow's scene table (name -> validated scene dict) and returns a
function of the rule's wildcards, as Snakemake expects.
"""

from __future__ import annotations

import json

from srfpipe.segment.run import prompt_options


def segment_params(scenes: dict):
    """The segment rule's params: only what matters for that prompt, as JSON (a rerun trigger)."""
    def params(wildcards) -> str:
        section = scenes[wildcards.scene]["segmentation"]
        return json.dumps(prompt_options(section, wildcards.prompt), sort_keys=True)

    return params


def segment_model(scenes: dict):
    """The ONNX model file as an input, so that a retrained or replaced model reruns the masks."""
    def model(wildcards) -> list[str]:
        section = scenes[wildcards.scene]["segmentation"]
        if section["backend"] != "onnx":
            return []
        if section["model"] == "builtin":
            from srfpipe.segment.onnx_backend import builtin_model_path

            return [str(builtin_model_path())]
        return [section["model"]]

    return model


def scene_masks(scenes: dict, results: str):
    """masks/{prompt}.zarr for the scene's prompts, in class order (the composite's inputs; none
    when the scene has no prompts)."""
    def masks(wildcards) -> list[str]:
        prompts = scenes[wildcards.scene]["segmentation"]["prompts"]
        return [f"{results}/{wildcards.scene}/masks/{prompt}.zarr" for prompt in prompts]

    return masks


def scene_prompts(scenes: dict):
    """The composite rule's prompts in class order, as JSON (a rerun trigger): the label values
    follow this order, and a new order leaves the set of mask inputs, which Snakemake compares as a
    set, unchanged."""
    def prompts(wildcards) -> str:
        return json.dumps(scenes[wildcards.scene]["segmentation"]["prompts"])

    return prompts
