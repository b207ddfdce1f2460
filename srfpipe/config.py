"""Scene configuration: load a scene YAML, validate it against the schema, fill in defaults.

Errors name the scene file and the key (`config/scenes/x.yaml: poses.refine: 'yes' is not one of ...`).
"""

from __future__ import annotations

import copy
from functools import lru_cache
from importlib import resources
from pathlib import Path

import jsonschema
import yaml

SCHEMA_DIRS = [
    Path(__file__).resolve().parent.parent / "workflow" / "schemas",  # a source checkout
]


class ConfigError(ValueError):
    """A scene or workflow config file is invalid."""


@lru_cache(maxsize=None)
def load_schema(name: str = "scene.schema.yaml") -> dict:
    for folder in SCHEMA_DIRS:
        path = folder / name
        if path.exists():
            return yaml.safe_load(path.read_text())
    packaged = resources.files("srfpipe").joinpath("schemas", name)
    return yaml.safe_load(packaged.read_text())


def _with_defaults(validator_class):
    validate_properties = validator_class.VALIDATORS["properties"]

    def set_defaults(validator, properties, instance, schema):
        if isinstance(instance, dict):
            for name, subschema in properties.items():
                if "default" in subschema:
                    # deepcopy: a default dict must never be shared between two scenes
                    instance.setdefault(name, copy.deepcopy(subschema["default"]))
        yield from validate_properties(validator, properties, instance, schema)

    return jsonschema.validators.extend(validator_class, {"properties": set_defaults})


DefaultFillingValidator = _with_defaults(jsonschema.Draft202012Validator)


def validate_scene(scene: dict, source: str = "<scene>") -> dict:
    """Validate a scene dict in place (defaults filled in) and return it."""
    if scene is None:
        scene = {}
    if not isinstance(scene, dict):
        raise ConfigError(f"{source}: a scene file must hold a mapping, got {type(scene).__name__}")
    errors = sorted(DefaultFillingValidator(load_schema()).iter_errors(scene), key=lambda e: list(e.path))
    if errors:
        lines = []
        for error in errors:
            key = ".".join(str(p) for p in error.path) or "(top level)"
            lines.append(f"{source}: {key}: {error.message}")
        raise ConfigError("\n".join(lines))
    return scene


def load_scene(path: str | Path) -> dict:
    """Read and validate one scene YAML file."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"{path}: scene file does not exist")
    try:
        scene = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from exc
    return validate_scene(scene, str(path))


def section_defaults(section: str) -> dict:
    """The defaults of one scene section, as validation fills them in."""
    return validate_scene({section: {}})[section]


def add_options_arguments(parser, section: str) -> None:
    """`--scene FILE` and `--options JSON`: how every stage CLI receives its section's values."""
    parser.add_argument(
        "--scene", metavar="YAML",
        help=f"scene file to read the '{section}' section from (validated, defaults filled in)",
    )
    parser.add_argument(
        "--options", metavar="JSON", default="{}",
        help=f"JSON object overriding keys of the scene's '{section}' section",
    )


def stage_options(args, section: str) -> dict:
    """Defaults <- scene file section <- --options JSON, validated against the schema."""
    import json

    scene = load_scene(args.scene) if getattr(args, "scene", None) else validate_scene({})
    values = dict(scene.get(section, {}))
    try:
        overrides = json.loads(args.options or "{}")
    except json.JSONDecodeError as exc:
        raise ConfigError(f"--options: not valid JSON ({exc})") from exc
    if not isinstance(overrides, dict):
        raise ConfigError("--options: must be a JSON object")
    values.update(overrides)
    return validate_scene({section: values}, "--options")[section]
