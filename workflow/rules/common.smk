# Config loading and validation, the scene table and the batch sheet, and the small helpers the rules share.
import json
import re
from pathlib import Path

from srfpipe.batch import print_summary, read_sheet
from srfpipe.config import ConfigError, load_scene, validate_workflow_config


try:
    validate_workflow_config(config, " and ".join(map(str, workflow.configfiles or ["config"]))
                             + (" with --config" if workflow.config_settings.overwrite_config else ""))
except ConfigError as exc:
    raise WorkflowError(str(exc)) from None

RESULTS = config["results_dir"]
SCENES_DIR = Path(config["scenes_dir"])


# A scene's name becomes a folder under results/, part of every job's paths and of a wildcard's
# regular expression: letters, digits, '-' and '_' only ('..' or 'a.b' or a ';' would escape them).
SCENE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]*")


def _load_scenes():
    if not SCENES_DIR.is_dir():
        raise WorkflowError(f"scenes_dir {SCENES_DIR}: folder does not exist")
    scenes = {}
    for path in sorted(SCENES_DIR.glob("*.yaml")):
        if not SCENE_NAME.fullmatch(path.stem):
            raise WorkflowError(f"{path}: scene name {path.stem!r} may hold only letters, digits, '-' and '_' "
                                "(it names the scene's folder under results/); rename the file")
        try:
            scenes[path.stem] = load_scene(path)
        except ConfigError as exc:
            raise WorkflowError(str(exc)) from None
    return scenes


SCENES = _load_scenes()
SCENE_NAMES = config["scenes"] or sorted(SCENES)
for _name in SCENE_NAMES:
    if _name not in SCENES:
        raise WorkflowError(f"config scenes: no scene file {SCENES_DIR / f'{_name}.yaml'}")


wildcard_constraints:
    scene="|".join(re.escape(name) for name in sorted(SCENES)) or "NO_SCENES",


ARTIFACTS = {
    "poses": "poses.zarr",
    "images": "images.zarr",
    "labels": "labels.zarr",
    "srf": "srf.zarr",
    "eval": "eval",
    "occupancy": "occupancy.zarr",
    "sim": "sim",
}


def get_final_output(scenes=None):
    """The final artifact of each scene (the config's scenes by default), and its held-out
    evaluation when the final artifact comes after it (occupancy, sim: nothing else needs eval/, and
    the batch summary reads a finished scene's PSNR and mIoU from it)."""
    scenes = SCENE_NAMES if scenes is None else scenes
    names = list(ARTIFACTS)
    final = config["final_artifact"]
    wanted = [final] + (["eval"] if names.index(final) > names.index("eval") else [])
    return [f"{RESULTS}/{scene}/{ARTIFACTS[name]}" for scene in scenes for name in wanted]


def scene_section(section):
    """A params function: the scene's validated section as a JSON string (a rerun trigger)."""
    return lambda wildcards: json.dumps(SCENES[wildcards.scene][section], sort_keys=True)


# source.format values made by a built-in generator (rule <format>_capture, scene section <format>)
GENERATED_FORMATS = ("orchard", "plant")


def scenes_of_format(fmt):
    """A wildcard constraint matching exactly the scenes of one source format (never empty)."""
    names = [name for name, scene in SCENES.items() if scene["source"]["format"] == fmt]
    return "|".join(re.escape(name) for name in sorted(names)) or f"NO_{fmt.upper()}_SCENES"


# source.format values whose capture folder a rule writes from source.path (rule video_frames)
EXTRACTED_FORMATS = ("video",)


def capture_dir(wildcards):
    """The capture folder: generated for the built-in orchard and plant, a video's chosen frames
    (rule video_frames), a folder on disk otherwise."""
    source = SCENES[wildcards.scene]["source"]
    if source["format"] in GENERATED_FORMATS + EXTRACTED_FORMATS:
        return f"{RESULTS}/{wildcards.scene}/capture"
    return source["path"]


def holdout_every(wildcards):
    """The train rule's held-out views: evaluate.holdout_every (training leaves them out)."""
    return SCENES[wildcards.scene]["evaluate"]["holdout_every"]


def batch_scenes():
    """The scenes of the batch target: every scene file, or the rows of the sheet (config `sheet`)."""
    if not config.get("sheet"):
        return sorted(SCENES)
    try:
        return read_sheet(config["sheet"], known=list(SCENES))
    except ValueError as exc:
        raise WorkflowError(str(exc)) from None


def run_summary(log):
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
