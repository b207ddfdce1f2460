"""Scene configuration: load a scene YAML, validate it against the schema, fill in defaults.

Errors name the scene file and the key (`config/scenes/x.yaml: poses.refine: 'yes' is not one of ...`).
"""

from __future__ import annotations

import copy
import difflib
import math
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


def validate_scene(scene: dict, source: str = "<scene>", whole: bool = False) -> dict:
    """Validate a scene dict in place (defaults filled in) and return it.

    `whole`: the dict is a whole scene (a scene file), not one section of it: the classes its
    occupancy section names are checked against its prompts even when it leaves segmentation at
    the defaults. A section alone (`{"occupancy": ...}`, as stages validate their options) does
    not know the scene's prompts, so unless it also holds `segmentation` that check is left out.
    """
    if scene is None:
        scene = {}
    if not isinstance(scene, dict):
        raise ConfigError(f"{source}: a scene file must hold a mapping, got {type(scene).__name__}")
    # the roles the scene itself names (the schema's default roles need not be among its prompts)
    occupancy = scene.get("occupancy")
    named_roles = {role: occupancy[role] for role in ("reach", "avoid")
                   if isinstance(occupancy, dict) and role in occupancy}
    knows_prompts = whole or "segmentation" in scene
    non_finite = list(_non_finite_numbers(scene))
    if non_finite:  # JSON's NaN and Infinity, YAML's .nan and .inf: a schema's minimum lets NaN and inf through
        raise ConfigError("\n".join(f"{source}: {key}: {value} is not a finite number" for key, value in non_finite))
    apply_preset(scene)
    check_schema(scene, "scene.schema.yaml", source)
    resolve_conditional_defaults(scene)
    problems = contradictions(scene)
    if knows_prompts:
        problems += unknown_role_classes(named_roles, scene["segmentation"]["prompts"])
    if problems:
        raise ConfigError("\n".join(f"{source}: {problem}" for problem in problems))
    return scene


def _non_finite_numbers(value, key: str = ""):
    """(dotted key, value) of every NaN or infinite float in a config's nested dicts and lists."""
    if isinstance(value, float) and not math.isfinite(value):
        yield key or "(top level)", value
    elif isinstance(value, dict):
        for name, item in value.items():
            yield from _non_finite_numbers(item, f"{key}.{name}" if key else str(name))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            yield from _non_finite_numbers(item, f"{key}[{index}]")


def check_schema(instance: dict, schema: str, source: str) -> None:
    """Validate `instance` against the schema file `schema`, filling in its defaults; ConfigError
    with one line per problem, each naming `source` and the key (and the key meant, for a typo)."""
    errors = sorted(DefaultFillingValidator(load_schema(schema)).iter_errors(instance), key=lambda e: list(e.path))
    if errors:
        raise ConfigError("\n".join(f"{source}: {'.'.join(str(p) for p in error.path) or '(top level)'}: "
                                    f"{error.message}{_suggestion(error)}" for error in errors))


def validate_workflow_config(config: dict, source: str = "config/config.yaml") -> dict:
    """Validate the workflow's config (config/config.yaml with any --config values) in place,
    defaults filled in, and return it. Snakemake's own `validate` printed the whole schema and named
    no file."""
    if not isinstance(config, dict):
        raise ConfigError(f"{source}: the workflow config must hold a mapping, got {type(config).__name__}")
    check_schema(config, "config.schema.yaml", source)
    return config


def resolve_conditional_defaults(scene: dict) -> None:
    """Defaults that depend on another key, which a schema's `default` cannot say. Filled into the
    scene, so that they are part of a rule's params: a scene they change is rebuilt, others are not.

    poses.refine_distortion: `stated` under poses.refine: colmap (a stated lens is refitted)."""
    poses = scene.get("poses")
    if isinstance(poses, dict) and poses.get("refine") == "colmap":
        poses.setdefault("refine_distortion", "stated")


def apply_preset(scene: dict) -> None:
    """Fill in the values of the scene's `preset` (workflow/schemas/presets.yaml) for every key the
    scene does not set itself; an unknown preset is left for the schema to report."""
    name = scene.get("preset", load_schema()["properties"]["preset"]["default"])
    if not isinstance(name, str):
        return
    for section, values in (load_schema("presets.yaml").get(name) or {}).items():
        own = scene.get(section)
        if own is None or isinstance(own, dict):
            scene[section] = {**values, **(own or {})}


def _suggestion(error) -> str:
    """'; did you mean ...?' for an unknown key close to a known one (a typo)."""
    if error.validator != "additionalProperties" or not isinstance(error.instance, dict):
        return ""
    known = list(error.schema.get("properties", {}))
    hints = []
    for key in error.instance:
        if key not in known:
            close = difflib.get_close_matches(str(key), known, n=1, cutoff=0.6)
            if close:
                hints.append(f"{key!r} -> {close[0]!r}")
    return f"; did you mean {', '.join(hints)}?" if hints else ""


def contradictions(scene: dict) -> list[str]:
    """Settings that are each valid but contradict each other, as 'key: problem' lines."""
    problems = []
    poses = scene.get("poses", {})
    if poses.get("refine_distortion") and poses.get("refine") != "colmap":
        value = poses["refine_distortion"]
        problems.append(f"poses.refine_distortion is {str(value).lower()} but poses.refine is {poses.get('refine')!r}: the distortion "
                        "is fitted in COLMAP's refinement of the given poses (poses.refine: colmap)")
    bounds = poses.get("bounds")
    if bounds is not None and not all(lo < hi for lo, hi in zip(bounds[0], bounds[1])):
        problems.append(f"poses.bounds: the minimum {bounds[0]} must be below the maximum {bounds[1]} on every axis")
    segmentation = scene.get("segmentation", {})
    prompts = segmentation.get("prompts")
    if prompts is not None:
        unknown = sorted(set(segmentation.get("thresholds") or {}) - set(prompts))
        if unknown:
            problems.append(f"segmentation.thresholds: {unknown} are not among segmentation.prompts {prompts}")
    if segmentation.get("backend") == "import" and prompts and not (segmentation.get("import") or {}).get("path"):
        problems.append("segmentation.backend is import but segmentation.import.path is not set")
    occupancy = scene.get("occupancy", {})
    both = sorted(set(occupancy.get("avoid") or []) & set(occupancy.get("reach") or []))
    if both:
        problems.append(f"occupancy: {both} are both to avoid and to reach")
    train = scene.get("train", {})
    if "near" in train and "far" in train and train["near"] >= train["far"]:
        problems.append(f"train.near {train['near']} must be below train.far {train['far']}")
    problem = split_pixel_problem(train.get("rays_per_batch"), train.get("supersample"))
    if problem:
        problems.append(problem)
    return problems


def split_pixel_problem(rays_per_batch, supersample) -> str | None:
    """The problem with a batch of `rays_per_batch` rays that would split a pixel's
    `supersample`^2 rays (train.supersample), or None (either unset counts as fine)."""
    if rays_per_batch is None or not supersample or rays_per_batch % (supersample * supersample) == 0:
        return None
    return (f"train.rays_per_batch {rays_per_batch} must be a multiple of train.supersample^2 = "
            f"{supersample * supersample} (each pixel's rays come in a row)")


def unknown_role_classes(roles: dict, prompts: list[str]) -> list[str]:
    """'occupancy.reach: 'aple' is not a prompt (...); did you mean 'apple'?' for every class a role
    names that segmentation.prompts does not have (its distance field would silently be missing)."""
    problems = []
    for role, names in roles.items():
        for name in names:
            if name in prompts:
                continue
            if not prompts:
                problems.append(f"occupancy.{role}: {name!r} is not a prompt (segmentation.prompts is empty: "
                                f"the scene has no classes; remove it or add the prompt)")
                continue
            close = difflib.get_close_matches(str(name), prompts, n=1, cutoff=0.6)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            problems.append(f"occupancy.{role}: {name!r} is not a prompt "
                            f"(segmentation.prompts: {', '.join(prompts)}){hint}")
    return problems


def load_scene(path: str | Path) -> dict:
    """Read and validate one scene YAML file."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"{path}: scene file does not exist")
    try:
        scene = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from exc
    except UnicodeDecodeError as exc:  # a binary or non-UTF-8 file: the decoder names no file
        raise ConfigError(f"{path}: not valid YAML (not UTF-8 text: {exc})") from exc
    return validate_scene(scene, str(path), whole=True)


def section_defaults(section: str) -> dict:
    """The defaults of one scene section, as validation fills them in."""
    return validate_scene({section: {}})[section]


class SettingsSection:
    """Base of the typed settings in srfpipe/settings.py (one frozen dataclass per schema section).

    Fields are the section's keys (a Python keyword gets a trailing underscore and records the
    key in its metadata); a nested section's field holds its own dataclass. Arrays are tuples.
    """

    SECTION = ""

    @classmethod
    def from_section(cls, values: dict):
        """From a section that validation already filled in (`validate_scene`)."""
        import dataclasses

        known = {f.metadata.get("key", f.name): f for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ConfigError(f"{cls.SECTION}: unknown keys {unknown}")
        kwargs = {}
        for key, value in values.items():
            f = known[key]
            nested = f.metadata.get("section")
            kwargs[f.name] = nested.from_section(value) if nested else frozen_value(value)
        return cls(**kwargs)

    @classmethod
    def from_options(cls, options):
        """From raw section values (or settings already built): validated, defaults filled in."""
        if isinstance(options, cls):
            return options
        path = cls.SECTION.split(".")
        scene: dict = {}
        inner = scene
        for part in path[:-1]:
            inner = inner.setdefault(part, {})
        inner[path[-1]] = dict(options or {})
        section = validate_scene(scene, f"the {cls.SECTION} options")
        for part in path:
            section = section[part]
        return cls.from_section(section)

    def as_dict(self) -> dict:
        """The section as the schema spells it (keys, lists): what provenance records."""
        import dataclasses

        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if value is None and f.metadata.get("unset"):  # a key without a default that was not set
                continue
            out[f.metadata.get("key", f.name)] = value.as_dict() if isinstance(value, SettingsSection) else _thawed(value)
        return out

    def replace(self, **changes):
        """A copy with some fields changed (the capture-dependent defaults a stage resolves)."""
        import dataclasses

        return dataclasses.replace(self, **{k: frozen_value(v) for k, v in changes.items()})


def frozen_value(value):
    """A value as a settings field holds it: lists become tuples (frozen), recursively."""
    if isinstance(value, list):
        return tuple(frozen_value(v) for v in value)
    return value


def _thawed(value):
    if isinstance(value, tuple):
        return [_thawed(v) for v in value]
    if isinstance(value, dict):
        return {k: _thawed(v) for k, v in value.items()}
    return value


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


def json_object_flag(text: str | None, flag: str) -> dict:
    """The JSON object a CLI flag holds (`--options`, `--source`), or a ConfigError naming the flag."""
    import json

    try:
        value = json.loads(text or "{}")
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{flag}: not valid JSON ({exc})") from exc
    if not isinstance(value, dict):
        raise ConfigError(f"{flag}: must be a JSON object")
    return value


def stage_options(args, section: str) -> dict:
    """Defaults <- scene file section <- --options JSON, validated against the schema."""
    scene = load_scene(args.scene) if getattr(args, "scene", None) else validate_scene({})
    values = dict(scene.get(section, {}))
    values.update(json_object_flag(args.options, "--options"))
    return validate_scene({section: values}, "--options")[section]
