"""Typed settings (srfpipe/settings.py) agree with the scene schema key for key, so they cannot drift."""

from __future__ import annotations

import ast
import dataclasses
import subprocess
import sys
import types
import typing
from pathlib import Path

import pytest

from srfpipe import settings
from srfpipe.config import ConfigError, load_schema, validate_scene

REPO = Path(__file__).resolve().parent.parent
SCHEMA_TYPES = {"integer": int, "number": float, "string": str, "boolean": bool, "array": tuple, "object": dict,
                "null": type(None)}


def object_sections(schema: dict, path: str = ""):
    """(dotted path, object schema) of every section and nested section that has properties."""
    for key, sub in schema.get("properties", {}).items():
        if sub.get("type") == "object" and "properties" in sub:
            dotted = f"{path}.{key}" if path else key
            yield dotted, sub
            yield from object_sections(sub, dotted)


def settings_class(path: str):
    cls = settings.SECTIONS[path.split(".")[0]]
    for part in path.split(".")[1:]:
        f = next(f for f in dataclasses.fields(cls) if f.metadata.get("key", f.name) == part)
        cls = f.metadata["section"]
    return cls


def field_default(f: dataclasses.Field):
    if f.default is not dataclasses.MISSING:
        return f.default
    return f.default_factory()


def frozen(value):
    return tuple(frozen(v) for v in value) if isinstance(value, list) else value


def accepted_types(annotation: str, namespace: dict) -> set[type]:
    hint = eval(annotation, namespace)  # the generated module's annotations are strings
    args = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
    return {typing.get_origin(a) or a for a in args}


@pytest.mark.parametrize("path", [p for p, _ in object_sections(load_schema())])
def test_every_field_agrees_with_its_schema_key(path):
    schema = dict(object_sections(load_schema()))[path]
    cls = settings_class(path)
    assert cls.SECTION == path
    fields = {f.metadata.get("key", f.name): f for f in dataclasses.fields(cls)}
    assert list(fields) == list(schema["properties"]), f"{cls.__name__}: fields differ from schema keys of {path}"
    namespace = {**vars(settings), **vars(typing), "Any": typing.Any}
    for key, sub in schema["properties"].items():
        f = fields[key]
        if "section" in f.metadata:  # a nested section: its own fields are checked as a section
            assert sub["type"] == "object" and f.default_factory is f.metadata["section"]
            continue
        if "default" in sub:
            expected = sub["default"] if isinstance(sub["default"], dict) else frozen(sub["default"])
            assert field_default(f) == expected, f"{path}.{key}: default {field_default(f)!r} != schema {expected!r}"
        else:  # no schema default: absent means None
            assert field_default(f) is None, f"{path}.{key} has no schema default but defaults to {field_default(f)!r}"
        kinds = sub.get("type", [])
        kinds = set(kinds if isinstance(kinds, list) else [kinds])
        if "default" not in sub:
            kinds.add("null")
        assert accepted_types(f.type, namespace) == {SCHEMA_TYPES[k] for k in kinds}, \
            f"{path}.{key}: annotation {f.type} does not match schema type {sorted(kinds)}"


def test_every_field_is_documented():
    for path, schema in object_sections(load_schema()):
        for key, sub in schema["properties"].items():
            assert sub.get("description"), f"{path}.{key}: the schema gives no description"
    tree = ast.parse((REPO / "srfpipe" / "settings.py").read_text())
    for node in (n for n in tree.body if isinstance(n, ast.ClassDef)):
        body = node.body
        for i, statement in enumerate(body):
            if isinstance(statement, ast.AnnAssign) and statement.target.id != "SECTION":
                text = body[i + 1] if i + 1 < len(body) else None
                assert isinstance(text, ast.Expr) and isinstance(text.value, ast.Constant), \
                    f"{node.name}.{statement.target.id} has no docstring"


def test_generated_module_is_up_to_date():
    done = subprocess.run([sys.executable, str(REPO / "scripts" / "generate_settings.py"), "--check"],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_settings_round_trip_a_validated_scene():
    scene = validate_scene({"train": {"iterations": 5, "snapshot_seconds": [300]},
                            "segmentation": {"backend": "import", "import": {"path": "masks"}}})
    for section, cls in settings.SECTIONS.items():
        built = cls.from_section(scene[section])
        assert built.as_dict() == scene[section]
    train = settings.TrainSettings.from_section(scene["train"])
    assert train.iterations == 5 and train.snapshot_seconds == (300,)
    with pytest.raises(dataclasses.FrozenInstanceError):
        train.iterations = 6
    assert settings.SegmentationSettings.from_section(scene["segmentation"]).import_.path == "masks"


def test_from_options_validates_and_names_the_key():
    assert settings.TrainSettings.from_options({}).outer_samples == load_schema()["properties"]["train"][
        "properties"]["outer_samples"]["default"]
    with pytest.raises(ConfigError, match="train.iterations"):
        settings.TrainSettings.from_options({"iterations": "many"})
    with pytest.raises(ConfigError, match="hiden"):
        settings.TrainSettings.from_options({"hiden": 64})
