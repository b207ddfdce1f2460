"""Write config/README.md from the JSON schemas, so the key reference never drifts from validation.

Usage: python scripts/config_docs.py [--check]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parent.parent
SCHEMAS = REPO / "workflow" / "schemas"
OUT = REPO / "config" / "README.md"

INTRO = """# Configuration

This file is generated from `workflow/schemas/*.schema.yaml` by `python scripts/config_docs.py`;
edit the schemas, not this file (and run `python scripts/generate_settings.py` too: code reads a
section through its typed view in `srfpipe/settings.py`). Config is validated when Snakemake
starts: an error names the file and the key. Keys left out take the defaults below.

* `config/config.yaml`: which scenes to build and where results go.
* `config/scenes/<scene>.yaml`: one file per scene. Drop a file in to add a scene; build it with
  `snakemake --cores 2 results/<scene>/occupancy.zarr`. Each stage receives only its own section, so
  changing a key re-runs the stage that reads it and everything downstream, nothing upstream.
"""


def _type(schema: dict) -> str:
    if "enum" in schema:
        return " \\| ".join(json.dumps(v) for v in schema["enum"])
    kind = schema.get("type", "")
    if isinstance(kind, list):
        return " or ".join(kind)
    if kind == "array" and isinstance(schema.get("items"), dict) and "type" in schema["items"]:
        return f"array of {schema['items']['type']}"
    return kind


def _rows(schema: dict, prefix: str = ""):
    for name, sub in schema.get("properties", {}).items():
        key = f"{prefix}{name}"
        if sub.get("type") == "object" and "properties" in sub:
            if sub.get("description"):
                yield key, "object", "", sub["description"]
            yield from _rows(sub, key + ".")
            continue
        default = json.dumps(sub["default"]) if "default" in sub else ""
        description = " ".join(str(sub.get("description", "")).split())
        yield key, _type(sub), default, description


def render() -> str:
    parts = [INTRO]
    for title, name in (("config/config.yaml", "config.schema.yaml"),
                        ("config/scenes/<scene>.yaml", "scene.schema.yaml")):
        schema = yaml.safe_load((SCHEMAS / name).read_text())
        parts.append(f"\n## `{title}`\n\n{' '.join(schema.get('description', '').split())}\n")
        parts.append("| key | type | default | meaning |\n|---|---|---|---|")
        for key, kind, default, description in _rows(schema):
            cell = lambda s: s.replace("|", "\\|") if "\\|" not in s else s
            parts.append(f"| `{key}` | {kind} | {cell(default) and '`' + default + '`'} | {cell(description)} |")
    return "\n".join(parts) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 when config/README.md is out of date")
    args = parser.parse_args()
    text = render()
    if args.check:
        if not OUT.exists() or OUT.read_text() != text:
            print(f"{OUT} is out of date: run python scripts/config_docs.py", file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
