"""Write srfpipe/settings.py from the scene schema: one frozen dataclass per schema section.

The schema (workflow/schemas/scene.schema.yaml) stays the one place where a key, its type, its
default and its description are written; the dataclasses give code a typed view of a validated
section, so no stage reads a key with a literal fallback. tests/test_settings.py checks every
field against its schema key (name, default, type), whether or not this script wrote it.

Usage: python scripts/generate_settings.py [--check]
"""

from __future__ import annotations

import argparse
import keyword
import sys
import textwrap
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from srfpipe.config import frozen_value  # noqa: E402  (the function from_section freezes values with)

REPO = Path(__file__).resolve().parent.parent
SCHEMA = REPO / "workflow" / "schemas" / "scene.schema.yaml"
OUT = REPO / "srfpipe" / "settings.py"

HEADER = '''"""Typed settings: one frozen dataclass per section of the scene schema.

Generated from workflow/schemas/scene.schema.yaml by `python scripts/generate_settings.py`; edit
the schema, not this file (tests/test_settings.py fails when a field and its schema key disagree
in name, default or type). Build one from a section with `TrainSettings.from_options(values)`,
which validates the values and fills in the schema's defaults first; `as_dict()` gives the
section back as the schema spells it (what provenance records). A field's text is the first
sentence of its schema description; config/README.md has the whole.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from srfpipe.config import SettingsSection
'''

PYTHON_TYPES = {"integer": "int", "number": "float", "string": "str", "boolean": "bool",
                "array": "tuple", "object": "dict[str, Any]", "null": "None"}


def class_name(section: str) -> str:
    return "".join(part.capitalize() for part in section.split("_")) + "Settings"


def field_name(key: str) -> str:
    return f"{key}_" if keyword.iskeyword(key) else key


def annotation(schema: dict) -> str:
    kinds = schema.get("type", "object")
    kinds = kinds if isinstance(kinds, list) else [kinds]
    names = [PYTHON_TYPES[k] for k in kinds if k != "null"] or ["Any"]
    optional = "null" in kinds or "default" not in schema
    return " | ".join(names + (["None"] if optional else []))


def first_sentence(text: str | None, limit: int = 240) -> str:
    """The description up to its first sentence end outside parentheses (a '. ' before a capital
    letter, or a ';'), at most `limit` characters."""
    text = " ".join((text or "").split())
    depth, end = 0, len(text)
    for i, char in enumerate(text):
        depth += (char == "(") - (char == ")")
        if depth == 0 and (char == ";" or (char == "." and text[i + 1:i + 3].strip()[:1].isupper())):
            end = i
            break
    sentence = text[:end].rstrip(" .:")
    if len(sentence) > limit:
        sentence = sentence[:limit].rsplit(" ", 1)[0] + " ..."
    return sentence.replace('"""', "'''").replace("\\", "\\\\")


def default_code(schema: dict, nested: str | None, key: str) -> str:
    metadata = [] if field_name(key) == key else [f'"key": {key!r}']
    if nested:
        metadata.append(f'"section": {nested}')
        return f"field(default_factory={nested}, metadata={{{', '.join(metadata)}}})"
    if "default" not in schema:  # absent from a validated section: None, and left out by as_dict
        metadata.append('"unset": True')
    value = frozen_value(schema["default"]) if "default" in schema else None
    if isinstance(value, dict):
        code = f"field(default_factory=lambda: {value!r}" if value else "field(default_factory=dict"
        return code + (f", metadata={{{', '.join(metadata)}}})" if metadata else ")")
    if metadata:
        return f"field(default={value!r}, metadata={{{', '.join(metadata)}}})"
    return repr(value)


def section_class(name: str, path: str, schema: dict, out: list[str]) -> str:
    """Append the dataclass of one object schema (its nested sections first) and return its name."""
    fields = []
    for key, sub in schema.get("properties", {}).items():
        nested = None
        if sub.get("type") == "object" and "properties" in sub:
            nested = section_class(f"{name}_{key}", f"{path}.{key}", sub, out)
        kind = nested if nested else annotation(sub)
        text = first_sentence(sub.get("description"))
        lines = [f"    {field_name(key)}: {kind} = {default_code(sub, nested, key)}"]
        if len(lines[0]) > 110:  # field( on its own line, its arguments on the next
            head, arguments = lines[0].split("field(", 1)
            lines = [f"{head}field(", f"        {arguments}"]
        if text:
            wrapped = textwrap.wrap(text, 100 - 7)
            lines.append(f'    """{wrapped[0]}' + ('"""' if len(wrapped) == 1 else ""))
            lines += [f"    {line}" for line in wrapped[1:]]
            if len(wrapped) > 1:
                lines[-1] += '"""'
        fields.append("\n".join(lines))
    cls = class_name(name)
    doc = first_sentence(schema.get("description"))
    doc = "\n    ".join(textwrap.wrap(f"`{path}`: {doc}", 100 - 7))
    out.append(f"@dataclass(frozen=True)\nclass {cls}(SettingsSection):\n"
               f'    """{doc}"""\n\n    SECTION: ClassVar[str] = {path!r}\n\n'
               + "\n".join(fields) + "\n")
    return cls


def generate() -> str:
    schema = yaml.safe_load(SCHEMA.read_text())
    classes: list[str] = []
    names = []
    for section, sub in schema["properties"].items():
        if sub.get("type") == "object":
            names.append(section_class(section, section, sub, classes))
    index = "SECTIONS = {\n" + "".join(f"    {n}.SECTION: {n},\n" for n in names) + "}\n"
    return HEADER + "\n\n" + "\n\n".join(classes) + "\n\n" + index


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 when srfpipe/settings.py is out of date")
    args = parser.parse_args()
    text = generate()
    if args.check:
        if OUT.read_text() != text:
            print(f"{OUT}: out of date with {SCHEMA}; run python scripts/generate_settings.py", file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text)
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
