"""Scene config validation: defaults, clear errors naming the file and the key."""

import pytest

from srfpipe.config import ConfigError, load_scene, section_defaults, validate_scene


def test_defaults_are_filled_in_and_not_shared():
    a = validate_scene({})
    b = validate_scene({})
    assert a["images"]["downscale"] is None  # from the capture (srfpipe.images.default_downscale)
    assert a["segmentation"]["prompts"] == ["apple", "branch", "leaf"]
    a["orchard"]["ring_heights"].append(9.0)
    assert b["orchard"]["ring_heights"] != a["orchard"]["ring_heights"]


def test_builtin_orchard_scene_is_valid():
    from tests.conftest import REPO

    scene = load_scene(REPO / "config" / "scenes" / "orchard.yaml")
    assert scene["source"]["format"] == "orchard"
    assert scene["images"]["downscale"] == 4


@pytest.mark.bad_input
def test_error_names_file_and_key(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("poses:\n  refine: yes_please\n")
    with pytest.raises(ConfigError) as err:
        load_scene(path)
    assert str(path) in str(err.value) and "poses.refine" in str(err.value)


@pytest.mark.bad_input
def test_unknown_key_and_format_are_rejected(tmp_path):
    path = tmp_path / "typo.yaml"
    path.write_text("source: {format: ply, path: x}\nimagez: {downscale: 2}\n")
    with pytest.raises(ConfigError) as err:
        load_scene(path)
    message = str(err.value)
    assert "source.format" in message and "imagez" in message


@pytest.mark.bad_input
def test_real_capture_requires_a_path():
    with pytest.raises(ConfigError, match="path"):
        validate_scene({"source": {"format": "nerfstudio"}}, "s.yaml")


@pytest.mark.bad_input
def test_missing_scene_file(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_scene(tmp_path / "nope.yaml")


@pytest.mark.bad_input
def test_a_binary_scene_file_is_a_clear_error(tmp_path):
    """A scene file that is not UTF-8 text ended in a UnicodeDecodeError naming no file (a
    traceback in Snakemake)."""
    path = tmp_path / "bin.yaml"
    path.write_bytes(b"\xff\xfe\x00train: {}")
    with pytest.raises(ConfigError, match=r"bin.yaml: not valid YAML \(not UTF-8 text"):
        load_scene(path)


def test_section_defaults():
    assert section_defaults("poses")["refine"] == "none"


def test_a_colmap_refinement_refits_a_stated_lens_unless_the_scene_says_otherwise():
    # filled into the scene, so that the poses rule's params change only for the scenes it changes
    assert validate_scene({"poses": {"refine": "colmap"}})["poses"]["refine_distortion"] == "stated"
    assert "refine_distortion" not in validate_scene({"poses": {}})["poses"]
    for given in (False, True):
        assert validate_scene({"poses": {"refine": "colmap", "refine_distortion": given}})["poses"]["refine_distortion"] is given
    with pytest.raises(ConfigError, match="poses.refine_distortion"):
        validate_scene({"poses": {"refine": "colmap", "refine_distortion": "always"}}, "s.yaml")


SCHEMA_KEYWORDS = {
    "$schema", "description", "type", "properties", "additionalProperties", "default", "enum", "const",
    "items", "minItems", "maxItems", "minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum",
    "pattern", "required", "if", "then", "else", "not", "oneOf", "anyOf", "allOf", "uniqueItems",
    "minLength", "maxLength", "format", "propertyNames", "minProperties",
}


def _schemas_in(node):
    if isinstance(node, dict):
        yield node
        for key in ("properties",):
            for sub in node.get(key, {}).values():
                yield from _schemas_in(sub)
        for key in ("items", "additionalProperties", "if", "then", "else", "not"):
            if isinstance(node.get(key), dict):
                yield from _schemas_in(node[key])
        for key in ("oneOf", "anyOf", "allOf"):
            for sub in node.get(key, []):
                yield from _schemas_in(sub)


def test_schema_uses_only_known_keywords():
    """A YAML slip (an unquoted comma in a flow mapping) turns prose into a silent keyword."""
    from srfpipe.config import load_schema

    for schema in _schemas_in(load_schema()):
        unknown = set(schema) - SCHEMA_KEYWORDS
        assert not unknown, f"unknown schema keywords {unknown} in {schema.get('description', schema)}"


def test_config_reference_is_up_to_date():
    import subprocess
    import sys

    from tests.conftest import REPO

    result = subprocess.run([sys.executable, str(REPO / "scripts" / "config_docs.py"), "--check"],
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def test_presets_fill_in_what_the_scene_does_not_set():
    from srfpipe.config import validate_scene

    balanced = validate_scene({})
    assert balanced["preset"] == "balanced" and balanced["train"]["time_budget"] == 600
    fast = validate_scene({"preset": "fast", "train": {"rays_per_batch": 1024}})
    assert fast["train"]["time_budget"] == 300 and fast["train"]["rays_per_batch"] == 1024  # the scene's key wins
    paper = validate_scene({"preset": "paper"})
    assert (paper["train"]["iterations"], paper["train"]["rays_per_batch"], paper["train"]["lr"]) == (500000, 4096, 0.01)
    assert paper["train"]["encoding"] == "hash" and paper["images"]["downscale"] == 4
    assert validate_scene({"preset": "accurate"})["train"]["time_budget"] == 1800


def test_an_unknown_preset_is_a_clear_error():
    from srfpipe.config import ConfigError, validate_scene

    with pytest.raises(ConfigError, match=r"scene.yaml: preset: 'quick' is not one of"):
        validate_scene({"preset": "quick"}, "scene.yaml")


@pytest.mark.bad_input
def test_nan_and_infinity_are_refused_naming_the_key(tmp_path):
    # JSON's NaN / Infinity and YAML's .nan / .inf pass the schema's minimum: an orchard with
    # ring_radius Infinity was rendered with NaN poses, tree_height NaN failed inside numpy
    path = tmp_path / "bad.yaml"
    path.write_text("orchard:\n  tree_height: .nan\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: orchard.tree_height: nan is not a finite number"):
        load_scene(path)
    with pytest.raises(ConfigError, match=r"orchard.ring_radius: inf is not a finite number"):
        validate_scene({"orchard": {"ring_radius": float("inf")}}, "--options")
    with pytest.raises(ConfigError, match=r"poses.bounds\[1\]\[2\]: -inf is not a finite number"):
        validate_scene({"poses": {"bounds": [[0, 0, 0], [1, 1, float("-inf")]]}})
    with pytest.raises(ConfigError, match=r"plant.elevations_deg\[0\]: nan"):
        validate_scene({"plant": {"elevations_deg": [float("nan")]}})


def test_nan_refusal_leaves_finite_values_alone():
    assert validate_scene({"poses": {"perturb_rot_deg": 1e300}})["poses"]["perturb_rot_deg"] == 1e300


@pytest.mark.bad_input
def test_a_negative_perturb_seed_is_refused_naming_the_key():
    # numpy's generator takes no negative seed: the poses stage failed with a bare
    # "expected non-negative integer", after the import
    with pytest.raises(ConfigError, match="poses.perturb_seed: -5 is less than the minimum of 0"):
        validate_scene({"poses": {"perturb_rot_deg": 1.0, "perturb_seed": -5}}, "--options")
