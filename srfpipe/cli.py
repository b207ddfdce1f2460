"""The `srfpipe` command: one subcommand per pipeline stage; the Snakemake rules call these.

Each stage module defines `add_arguments(parser)` and `run(args)`; heavy imports (torch, open3d,
pycolmap, onnxruntime) happen inside `run`, so `srfpipe --help` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from pathlib import Path

# (subcommand, module, one-line help). Order follows the data flow.
STAGES = [
    ("orchard", "srfpipe.scenes.orchard", "generate the built-in procedural orchard capture"),
    ("plant", "srfpipe.scenes.plant", "generate the built-in plant capture (a thin sapling, millimetres, few far views)"),
    ("frames", "srfpipe.poses.video", "choose a video's sharpest frames, spread over it -> a frames folder"),
    ("poses", "srfpipe.poses.stage", "import camera poses (nerfstudio|blender|colmap), or find them by SfM "
     "(images|video) [+ COLMAP refinement] -> poses.zarr"),
    ("downscale", "srfpipe.images", "undistort and downscale the images -> images.zarr"),
    ("segment", "srfpipe.segment.run", "per-prompt mask inference (onnx|import) -> masks/{prompt}.zarr"),
    ("composite", "srfpipe.segment.composite", "composite per-prompt masks into labels.zarr"),
    ("train", "srfpipe.srf.trainer", "train the semantic radiance field -> srf.zarr"),
    ("evaluate", "srfpipe.evaluate", "held-out PSNR/SSIM/IoU and renders -> eval/"),
    ("distill", "srfpipe.occupancy", "distill the field into the occupancy cache -> occupancy.zarr"),
    ("package", "srfpipe.sim.package", "package the scene for the simulator (manifest, fruit targets, meshes, MJCF) -> sim/"),
    ("sim", "srfpipe.sim.rollout", "run apple-reaching episodes in a package and write a GIF (wrist RGB | semantic | third person)"),
    ("summary", "srfpipe.batch", "one line per scene: done, FAILED at which stage (and why), or incomplete"),
]


# Arguments that name what a stage writes; every other path argument (metavar below) is an input.
OUTPUT_ARGUMENTS = ("out", "checkpoints", "metrics_log")
PATH_METAVARS = ("ZARR", "DIR", "FILE", "YAML", "GIF", "JSONL")


def stage_paths(parser: argparse.ArgumentParser, args) -> tuple[list[tuple[str, str]], list[tuple[str, str]]]:
    """(outputs, inputs) of the parsed stage command, each as (option, path) pairs: the outputs are
    OUTPUT_ARGUMENTS, the inputs every other argument whose metavar names a file or folder, and the
    capture folder a `--source` JSON object gives as `path`."""
    import json

    outputs, inputs = [], []
    for action in parser._actions:
        value = getattr(args, action.dest, None)
        if value is None or not action.option_strings:
            continue
        option = action.option_strings[-1]
        if action.dest in OUTPUT_ARGUMENTS:
            outputs.append((option, str(value)))
        elif action.metavar in PATH_METAVARS:
            inputs += [(option, str(v)) for v in (value if isinstance(value, list) else [value])]
        elif action.dest == "source" and isinstance(value, str):
            try:
                source = json.loads(value)
            except json.JSONDecodeError:
                continue  # the stage reports it
            if isinstance(source, dict) and isinstance(source.get("path"), str):
                inputs.append((f"{option} path", source["path"]))
    return outputs, inputs + scene_file_paths(getattr(args, "stage", None), getattr(args, "scene", None))


# The folders a stage reads through its --scene file rather than a path argument
SCENE_FILE_INPUTS = {"poses": [("source", "path")], "frames": [("source", "path")],
                     "segment": [("segmentation", "import", "path")]}


def scene_file_paths(stage: str | None, scene_file: str | None) -> list[tuple[str, str]]:
    """The folders `stage` reads through its scene file (the capture, imported masks), as (where,
    path): inputs as much as its path arguments are. A file that does not parse is left to the
    stage, which reports it."""
    import yaml

    if not scene_file or stage not in SCENE_FILE_INPUTS:
        return []
    try:
        scene = yaml.safe_load(Path(scene_file).read_text())
    except (OSError, yaml.YAMLError):
        return []
    found = []
    for where in SCENE_FILE_INPUTS[stage]:
        value = scene
        for key in where:
            value = value.get(key) if isinstance(value, dict) else None
        if isinstance(value, str):
            found.append((f"--scene {scene_file} {'.'.join(where)}", value))
    return found


def refuse_output_over_input(parser: argparse.ArgumentParser, args) -> None:
    """An output that is one of the stage's inputs, lies inside one, or holds one would be
    destroyed or replaced by the stage's atomic write (`downscale --out` equal to its `--poses`
    replaced the poses with images): refused before anything runs, naming both."""
    from pathlib import Path

    outputs, inputs = stage_paths(parser, args)
    for out_option, out in outputs:
        out_path = Path(out).expanduser().resolve()
        for in_option, path in inputs:
            in_path = Path(path).expanduser().resolve()
            if out_path == in_path:
                how = "is"
            elif out_path.is_relative_to(in_path):
                how = "lies inside"
            elif in_path.is_relative_to(out_path):
                how = "holds"
            else:
                continue
            raise ValueError(f"{out_option} {out} {how} the input {in_option} {path}: writing it would destroy "
                             f"the input; choose another output path")


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    """The argument parser; only the `selected` stage's module is imported (keeps --help fast)."""
    from srfpipe import __version__

    parser = argparse.ArgumentParser(
        prog="srfpipe",
        description="Build Semantic Radiance Field simulators from posed RGB captures. "
        "Each subcommand is one stage of the Snakemake workflow and writes one Zarr artifact.",
    )
    parser.add_argument("--version", action="version", version=f"srfpipe {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="stage", metavar="STAGE")
    for name, module_name, help_text in STAGES:
        if name != selected:
            sub.add_parser(name, help=help_text)
            continue
        module = importlib.import_module(module_name)
        stage_parser = sub.add_parser(
            name, help=help_text, description=(module.__doc__ or help_text).strip().split("\n\n")[0],
            formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        )
        module.add_arguments(stage_parser)
        stage_parser.set_defaults(_run=module.run, _parser=stage_parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    stage_names = {name for name, _, _ in STAGES}
    selected = next((arg for arg in argv if arg in stage_names), None)
    parser = build_parser(selected)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "stage", None):
        parser.print_help()
        return 2
    try:
        refuse_output_over_input(args._parser, args)
        result = args._run(args)
    except (ValueError, OSError, RuntimeError) as exc:
        # Bad input, a full disk, a read-only folder: one clear line naming the file and the
        # problem, no traceback noise (the artifact's partial directory is already removed).
        logging.getLogger("srfpipe").debug("traceback", exc_info=True)
        print(f"srfpipe {args.stage}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        # Ctrl-C: the stage's partial output is already removed (training keeps its checkpoints
        # and resumes from them); a traceback would only bury that
        logging.getLogger("srfpipe").debug("traceback", exc_info=True)
        print(f"srfpipe {args.stage}: interrupted: its output was not written", file=sys.stderr)
        return 130
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
