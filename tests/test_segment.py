"""Segmentation back ends (onnx class-channel, onnx text-prompted, import) and label compositing."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import zarr
import pytest

from srfpipe.artifacts import create_artifact, meta, open_artifact, reseal_artifact
from srfpipe.config import validate_scene
from srfpipe.segment.composite import composite_masks, label_image
from srfpipe.segment.run import prompt_options, segment_images

REPO = Path(__file__).resolve().parent.parent


# ------------------------------------------------------------------------------------- helpers


def options(**overrides) -> dict:
    """A validated segmentation section with overrides, as one prompt's rule sees it."""
    return validate_scene({"segmentation": overrides})["segmentation"]


def write_images(path: Path, images: np.ndarray, downscale: float = 1, labels: np.ndarray | None = None) -> Path:
    """A minimal images.zarr (stage downscale) holding `images` (N, H, W, 3) uint8."""
    n, height, width, _ = images.shape
    names = [f"frame_{i:05d}" for i in range(n)]
    with create_artifact(path, stage="downscale") as group:
        array = group.create_array("images", shape=images.shape, chunks=(1, height, width, 3), dtype="uint8")
        array[:] = images
        if labels is not None:
            gt = group.create_group("ground_truth")
            gt.create_array("labels", shape=labels.shape, dtype="uint8")[:] = labels
        group.attrs["srfpipe"] = {**group.attrs["srfpipe"], "names": names, "width": width, "height": height,
                                  "downscale": downscale}
    return path


def red_blue_images(n: int = 2, width: int = 40, height: int = 30) -> np.ndarray:
    """Left half pure red, right half pure blue (the known answer for the colour models)."""
    images = np.zeros((n, height, width, 3), np.uint8)
    images[:, :, : width // 2, 0] = 255
    images[:, :, width // 2:, 2] = 255
    return images


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def read_masks(path: Path) -> np.ndarray:
    return np.asarray(open_artifact(path, stage="segment")["probability"][:]).astype(np.float32) / 255.0


def export(model, args, path: Path, input_names, output_names, dynamic_axes=None, metadata=None) -> Path:
    """Export a torch module to ONNX (legacy exporter: no onnxscript needed) with metadata_props."""
    import onnx
    import torch

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the legacy exporter is all we have offline
        torch.onnx.export(model, args, str(path), dynamo=False, input_names=input_names,
                          output_names=output_names, dynamic_axes=dynamic_axes or {})
    if metadata:
        proto = onnx.load(str(path))
        onnx.helper.set_model_props(proto, {k: json.dumps(v) if not isinstance(v, str) else v
                                            for k, v in metadata.items()})
        onnx.save(proto, str(path))
    return path


# -------------------------------------------------------------------- tiny models with answers


@pytest.fixture(scope="module")
def colour_text_model(tmp_path_factory):
    """A text-prompted model: the mask is high where the colour named by the prompt is bright.

    Inputs pixel_values (B, 3, 32, 32) normalized with mean = std = 0.5, input_ids and
    attention_mask (B, 4); output logits (B, 32, 32).
    """
    import torch

    class ColourPicker(torch.nn.Module):
        def __init__(self):
            super().__init__()
            table = torch.zeros(8, 3)
            table[5, 0] = table[6, 1] = table[7, 2] = 1.0  # red, green, blue token ids
            self.embed = torch.nn.Embedding.from_pretrained(table)

        def forward(self, pixel_values, input_ids, attention_mask):
            weights = (self.embed(input_ids) * attention_mask[..., None].float()).sum(1)  # (B, 3)
            return 10.0 * (pixel_values * weights[:, :, None, None]).sum(1)  # x in [-1, 1]: 0 at 0.5

    folder = tmp_path_factory.mktemp("text_model")
    ids = torch.tensor([[1, 5, 2, 0]])
    path = export(ColourPicker().eval(), (torch.zeros(1, 3, 32, 32), ids, torch.ones_like(ids)),
                  folder / "colour_text.onnx", ["pixel_values", "input_ids", "attention_mask"], ["logits"],
                  {"pixel_values": {0: "batch"}, "input_ids": {0: "batch"}, "attention_mask": {0: "batch"},
                   "logits": {0: "batch"}})
    tokenizer = folder / "vocab.json"
    tokenizer.write_text(json.dumps({"vocab": {"red": 5, "green": 6, "blue": 7}, "bos": 1, "eos": 2,
                                     "pad": 0, "length": 4}))
    return path, tokenizer


@pytest.fixture(scope="module")
def colour_class_model(tmp_path_factory):
    """A class-channel model with dynamic size: logits (B, 3, H, W) = 20 (rgb - 0.5)."""
    import torch

    class Channels(torch.nn.Module):
        def forward(self, image):
            return 20.0 * (image - 0.5)

    path = tmp_path_factory.mktemp("class_model") / "colour_classes.onnx"
    return export(Channels(), (torch.zeros(1, 3, 16, 16),), path, ["image"], ["logits"],
                  {"image": {0: "b", 2: "h", 3: "w"}, "logits": {0: "b", 2: "h", 3: "w"}},
                  metadata={"classes": ["red", "green", "blue"], "activation": "sigmoid"})


# ------------------------------------------------------------------------- onnx: text-prompted


@pytest.mark.parametrize("fit", ["resize", "tile"])
def test_text_prompted_model_answers_each_prompt(tmp_path, colour_text_model, fit):
    model, tokenizer = colour_text_model
    images = write_images(tmp_path / "images.zarr", red_blue_images(n=3, width=80, height=60))
    opts = options(model=str(model), tokenizer=str(tokenizer), mean=[0.5] * 3, std=[0.5] * 3, fit=fit,
                   batch_size=2)
    left = np.zeros((60, 80), bool)
    left[:, :40] = True
    for prompt, expected in [("red", left), ("blue", ~left), ("green", np.zeros_like(left))]:
        out = segment_images(images, prompt, prompt_options(opts, prompt), tmp_path / f"{prompt}.zarr",
                             progress=False)
        masks = read_masks(out)
        assert masks.shape == (3, 60, 80)
        for mask in masks:
            assert iou(mask >= 0.5, expected) >= 0.95, (prompt, fit)
        info = meta(open_artifact(out))
        assert info["prompt"] == prompt and info["model"]["kind"] == "text"
        assert info["model"]["sha256"] and info["threshold"] == 0.5


def test_text_prompt_words_come_from_prompt_text(tmp_path, colour_text_model):
    model, tokenizer = colour_text_model
    images = write_images(tmp_path / "images.zarr", red_blue_images(n=1))
    opts = options(model=str(model), tokenizer=str(tokenizer), mean=[0.5] * 3, std=[0.5] * 3,
                   prompt_text={"fruit": "red"})
    masks = read_masks(segment_images(images, "fruit", prompt_options(opts, "fruit"), tmp_path / "f.zarr",
                                      progress=False))
    assert masks[0][:, :20].mean() > 0.95 and masks[0][:, 20:].mean() < 0.05
    with pytest.raises(ValueError, match=r"vocab.json: the word 'purple'.*not in the vocabulary"):
        segment_images(images, "purple", prompt_options(opts, "purple"), tmp_path / "p.zarr", progress=False)
    assert not (tmp_path / "p.zarr").exists()


# ---------------------------------------------------------------------- onnx: class-channel


def test_class_channel_model_selects_the_prompt_channel(tmp_path, colour_class_model):
    images = write_images(tmp_path / "images.zarr", red_blue_images(n=2, width=36, height=20))
    opts = options(model=str(colour_class_model), pad_multiple=8)
    red = read_masks(segment_images(images, "red", prompt_options(opts, "red"), tmp_path / "r.zarr", progress=False))
    blue = read_masks(segment_images(images, "blue", prompt_options(opts, "blue"), tmp_path / "b.zarr", progress=False))
    assert red.shape == (2, 20, 36)
    assert red[:, :, :18].min() > 0.99 and red[:, :, 18:].max() < 0.01
    assert np.array_equal(blue >= 0.5, red < 0.5)


@pytest.mark.bad_input
def test_unknown_prompt_names_the_model_and_its_classes(tmp_path, colour_class_model):
    images = write_images(tmp_path / "images.zarr", red_blue_images(n=1))
    opts = options(model=str(colour_class_model))
    with pytest.raises(ValueError, match=r"unknown prompt 'apple'.*colour_classes.onnx.*'red', 'green', 'blue'"):
        segment_images(images, "apple", prompt_options(opts, "apple"), tmp_path / "a.zarr", progress=False)
    # config class names override the metadata
    opts = options(model=str(colour_class_model), classes=["apple", "grass", "sky"])
    masks = read_masks(segment_images(images, "apple", prompt_options(opts, "apple"), tmp_path / "a.zarr",
                                      progress=False))
    assert masks[0][:, :20].min() > 0.99


@pytest.mark.bad_input
def test_model_with_wrong_inputs_lists_what_was_expected(tmp_path):
    import torch

    class FiveChannels(torch.nn.Module):
        def forward(self, x):
            return x[:, :1]

    path = export(FiveChannels(), (torch.zeros(1, 5, 8, 8),), tmp_path / "five.onnx", ["spectral"], ["out"])
    images = write_images(tmp_path / "images.zarr", red_blue_images(n=1))
    opts = options(model=str(path), classes=["apple"])
    with pytest.raises(ValueError, match=r"five.onnx: image input 'spectral' float \(1, 5, 8, 8\) has no channel "
                                         r"axis of size 3.*expected to have an image input float \(batch, 3, height, width\)"):
        segment_images(images, "apple", prompt_options(opts, "apple"), tmp_path / "a.zarr", progress=False)
    with pytest.raises(FileNotFoundError, match=r"missing.onnx: ONNX model file does not exist"):
        segment_images(images, "apple", prompt_options(options(model=str(tmp_path / "missing.onnx")), "apple"),
                       tmp_path / "a.zarr", progress=False)
    with pytest.raises(FileNotFoundError, match=r"models: ONNX model file is not a file \(a folder\?\) "
                                                r"\(segmentation.model\)"):
        (tmp_path / "models").mkdir()
        segment_images(images, "apple", prompt_options(options(model=str(tmp_path / "models")), "apple"),
                       tmp_path / "a.zarr", progress=False)
    assert not (tmp_path / "a.zarr").exists()


@pytest.mark.bad_input
@pytest.mark.parametrize("answer, problem", [
    ("one_map", r"output 'out' has shape \(1, 2, 30, 40\) for a batch of 2 images; expected one output "
                r"\(batch, classes, h, w\)"),
    ("twice", r"output 'out' has shape \(4, 2, 30, 40\) for a batch of 2 images"),
    ("nan", r"output 'out' holds NaN"),
])
def test_model_whose_output_does_not_answer_the_batch_is_refused(tmp_path, answer, problem):
    """A model whose batch dimension is dynamic but answers one map for the whole batch (or two per
    image), or NaN, is refused naming the model: not a crash in the averaging, not masks of the
    wrong images or empty masks."""
    import torch

    class Broken(torch.nn.Module):
        def forward(self, image):
            two = image[:, :2]
            if answer == "one_map":
                return two.mean(0, keepdim=True)
            if answer == "twice":
                return torch.cat([two, two])
            return (two - two) / (two - two)

    path = export(Broken(), (torch.zeros(2, 3, 30, 40),), tmp_path / f"{answer}.onnx", ["image"], ["out"],
                  dynamic_axes={"image": {0: "batch"}, "out": {0: "batch"}})
    images = write_images(tmp_path / "images.zarr", red_blue_images(n=3))
    opts = prompt_options(options(model=str(path), classes=["apple", "leaf"], batch_size=2), "apple")
    with pytest.raises(ValueError, match=f"{answer}.onnx: " + problem):
        segment_images(images, "apple", opts, tmp_path / "apple.zarr", progress=False)
    assert not (tmp_path / "apple.zarr").exists()


@pytest.mark.bad_input
def test_text_model_without_token_input_is_rejected(tmp_path, colour_class_model):
    images = write_images(tmp_path / "images.zarr", red_blue_images(n=1))
    opts = options(model=str(colour_class_model), kind="text", tokenizer="unused.json")
    with pytest.raises(ValueError, match=r"no integer token-id input.*token ids int \(batch, length\).*"
                                         r"this model has inputs 'image' float \(b, 3, h, w\)"):
        segment_images(images, "red", prompt_options(opts, "red"), tmp_path / "r.zarr", progress=False)


# --------------------------------------------------------------------------------- import


def test_import_png_masks_binary_soft_and_full_resolution(tmp_path):
    images = write_images(tmp_path / "images.zarr", red_blue_images(n=2, width=40, height=30), downscale=2)
    folder = tmp_path / "sam3"
    folder.mkdir()
    truth = np.zeros((2, 30, 40), np.float32)
    truth[0, 5:15, 10:30] = 1.0
    truth[1, 10:25, 0:20] = 0.6
    # binary 0/255 (a 0/1 mask beside a soft one would be read as value/255 like it: one scale per prompt)
    cv2.imwrite(str(folder / "frame_00000_apple.png"), (truth[0] * 255).astype(np.uint8))
    full = cv2.resize((truth[1] * 255).astype(np.uint8), (80, 60), interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(folder / "frame_00001_apple.png"), full)  # soft, full resolution
    opts = options(backend="import", **{"import": {"path": str(folder)}})
    masks = read_masks(segment_images(images, "apple", prompt_options(opts, "apple"), tmp_path / "a.zarr",
                                      progress=False))
    assert np.array_equal(masks[0], truth[0])
    assert np.abs(masks[1] - truth[1]).max() <= 1 / 255 + 1e-6
    assert meta(open_artifact(tmp_path / "a.zarr"))["backend"] == "import"


def test_import_label_images_with_value_table(tmp_path):
    labels = np.zeros((2, 30, 40), np.uint8)
    labels[:, 2:8, 2:8] = 1
    labels[:, 10:20, :] = 7
    labels[1, 25:, 30:] = 9
    images = write_images(tmp_path / "images.zarr", red_blue_images(n=2, width=40, height=30))
    folder = tmp_path / "labels"
    folder.mkdir()
    for i, label in enumerate(labels):
        cv2.imwrite(str(folder / f"frame_{i:05d}.png"), label)
    spec = {"path": str(folder), "format": "labels", "pattern": "{frame}.png",
            "values": {"apple": 1, "leaf": [7, 9]}}
    with pytest.raises(ValueError, match=r"pattern '\{frame\}.png': unknown field 'frame'"):
        segment_images(images, "apple", prompt_options(options(backend="import", **{"import": spec}), "apple"),
                       tmp_path / "x.zarr", progress=False)
    spec["pattern"] = "{name}.png"
    opts = options(backend="import", **{"import": spec})
    for prompt, values in [("apple", [1]), ("leaf", [7, 9])]:
        masks = read_masks(segment_images(images, prompt, prompt_options(opts, prompt), tmp_path / f"{prompt}.zarr",
                                          progress=False))
        assert np.array_equal(masks == 1.0, np.isin(labels, values))
    with pytest.raises(ValueError, match=r"unknown prompt 'branch': segmentation.import.values has no label value"):
        segment_images(images, "branch", prompt_options(opts, "branch"), tmp_path / "b.zarr", progress=False)


@pytest.mark.bad_input
def test_import_missing_or_wrongly_sized_mask_names_the_file(tmp_path):
    images = write_images(tmp_path / "images.zarr", red_blue_images(n=2, width=40, height=30), downscale=4)
    folder = tmp_path / "masks"
    folder.mkdir()
    opts = options(backend="import", **{"import": {"path": str(folder)}})
    # no frame has a mask: a wrong folder or pattern, not a sparse labelling
    with pytest.raises(FileNotFoundError, match=r"frame_00000_apple.png: mask file does not exist, nor does any "
                                                r"other of the 2 frames' masks for prompt 'apple'"):
        segment_images(images, "apple", prompt_options(opts, "apple"), tmp_path / "a.zarr", progress=False)
    assert not (tmp_path / "a.zarr").exists()  # nothing that looks complete
    cv2.imwrite(str(folder / "frame_00000_apple.png"), np.zeros((30, 40), np.uint8))
    cv2.imwrite(str(folder / "frame_00001_apple.png"), np.zeros((31, 40), np.uint8))
    with pytest.raises(ValueError, match=r"frame_00001_apple.png: mask is 40x31, expected 40x30 "
                                         r"\(the size of images.zarr\) or 160x120 \(full resolution\)"):
        segment_images(images, "apple", prompt_options(opts, "apple"), tmp_path / "a.zarr", progress=False)


def test_frames_without_a_mask_are_unlabelled_not_empty(tmp_path):
    """Masks of some frames only: those frames are recorded as unlabelled, carry no semantic loss
    and no IoU, and do not carve the visual hull."""
    import torch

    from srfpipe.srf import losses
    from srfpipe.srf.data import load_posed_images

    images = write_images(tmp_path / "images.zarr", red_blue_images(n=4, width=40, height=30))
    group = zarr.open_group(str(images), mode="r+")  # a scene box, so that the loader reads the labels' frames
    group.create_array("intrinsics", data=np.tile([40.0, 40.0, 20.0, 15.0], (4, 1)))
    group.create_array("camera_to_world", data=np.tile(np.eye(4), (4, 1, 1)))
    group.attrs["srfpipe"] = {**group.attrs["srfpipe"], "bounds_world": [[-1, -1, 1], [1, 1, 3]],
                              "scene_from_world": np.eye(4).tolist()}
    reseal_artifact(images)  # a deliberate edit of a finished artifact, before the masks are made from it
    folder = tmp_path / "masks"
    folder.mkdir()
    for i in (0, 2):  # frames 1 and 3 were never labelled
        cv2.imwrite(str(folder / f"frame_{i:05d}_apple.png"), np.full((30, 40), 255, np.uint8))
    opts = options(backend="import", **{"import": {"path": str(folder)}})
    mask = segment_images(images, "apple", prompt_options(opts, "apple"), tmp_path / "apple.zarr", progress=False)
    info = meta(open_artifact(mask))
    assert info["labelled"] == [True, False, True, False]
    assert info["unlabelled_frames"] == ["frame_00001", "frame_00003"]
    out = composite_masks(images, [mask], validate_scene({})["labels"], tmp_path / "labels.zarr", progress=False)
    assert meta(open_artifact(out))["unlabelled_frames"] == ["frame_00001", "frame_00003"]
    # the semantic loss of a batch counts the labelled frames' rays only
    logits, labels = torch.full((4, 1), -8.0), torch.tensor([[1.0], [0.0], [1.0], [0.0]])
    valid = torch.tensor([True, False, True, False])
    assert float(losses.semantic_loss(logits, labels, valid)) > 7.9  # wrong on every labelled ray
    assert float(losses.semantic_loss(logits[~valid], labels[~valid])) < 1e-3
    data = load_posed_images(images, out)
    assert data.labelled.tolist() == [True, False, True, False]


# ------------------------------------------------------------------------------ composite


def write_mask(path: Path, prompt: str, probability: np.ndarray, threshold: float = 0.5,
               names: list[str] | None = None) -> Path:
    n, height, width = probability.shape
    with create_artifact(path, stage="segment") as group:
        group.create_array("probability", shape=probability.shape, chunks=(1, height, width),
                           dtype="uint8")[:] = np.round(probability * 255).astype(np.uint8)
        group.attrs["srfpipe"] = {**group.attrs["srfpipe"], "prompt": prompt, "threshold": threshold,
                                  "names": names or [f"frame_{i:05d}" for i in range(n)]}
    return path


def test_label_image_takes_the_most_probable_class_above_threshold():
    probs = np.array([[0.9, 0.6, 0.2, 0.55], [0.7, 0.8, 0.1, 0.45], [0.0, 0.0, 0.3, 0.1]], np.float32)
    labels = label_image(probs, [0.5, 0.5, 0.25], [1, 2, 3])
    # pixel 3: class 2 has the higher probability but is below its threshold
    assert labels.tolist() == [1, 2, 3, 1]


def blank_images(path: Path, n: int = 2, height: int = 4, width: int = 5) -> Path:
    return write_images(path, np.zeros((n, height, width, 3), np.uint8))


def test_composite_writes_labels_multihot_counts_and_drops_empty_classes(tmp_path):
    images = blank_images(tmp_path / "images.zarr")
    apple = np.zeros((2, 4, 5), np.float32)
    leaf = np.zeros_like(apple)
    branch = np.zeros_like(apple)  # the scene has no branch
    apple[0, 0, :3] = 0.9
    leaf[0, 0, 2:] = 0.7  # overlaps apple at (0, 0, 2): apple wins the label, both bits set
    leaf[1] = 0.6
    masks = [write_mask(tmp_path / "apple.zarr", "apple", apple), write_mask(tmp_path / "branch.zarr", "branch", branch),
             write_mask(tmp_path / "leaf.zarr", "leaf", leaf, threshold=0.65)]
    as_given = validate_scene({"labels": {"rescale_soft_masks": False}})["labels"]
    out = composite_masks(images, masks, as_given, tmp_path / "labels.zarr", progress=False)
    group = open_artifact(out, stage="composite")
    info = meta(group)
    label = np.asarray(group["label"][:])
    multihot = np.asarray(group["multihot"][:])
    assert info["classes"] == ["apple", "leaf"] and info["dropped_classes"] == ["branch"]
    assert info["mask_scale"] == {"apple": 1.0, "leaf": 1.0}
    assert info["class_values"] == {"apple": 1, "leaf": 3}  # values keep the prompt order
    assert label[0, 0].tolist() == [1, 1, 1, 3, 3] and (label[1] == 0).all()  # 0.6 < leaf's 0.65
    assert multihot.shape == (2, 4, 5, 2)
    assert multihot[0, 0, 2].tolist() == [1, 1]
    # the heads' soft targets: every kept class's probability, under its threshold too (leaf's 0.6)
    probability = np.asarray(group["probability"][:])
    assert probability.shape == multihot.shape and probability.dtype == np.uint8
    assert np.array_equal(probability, np.round(np.stack([apple, leaf], -1) * 255).astype(np.uint8))
    assert info["pixel_counts"] == {"apple": 3, "leaf": 3}
    assert info["label_pixel_counts"] == {"background": 35, "apple": 3, "leaf": 2}
    table = info["image-label"]
    assert [c["label-value"] for c in table["colors"]] == [0, 1, 3]
    assert {p["class"]: p["pixel_count"] for p in table["properties"]} == {"background": 35, "apple": 3, "leaf": 2}

    kept = composite_masks(images, masks, validate_scene({"labels": {"keep_empty_classes": True}})["labels"],
                           tmp_path / "all.zarr", progress=False)
    group = open_artifact(kept)
    assert meta(group)["classes"] == ["apple", "branch", "leaf"] and meta(group)["dropped_classes"] == []
    assert group["multihot"].shape == (2, 4, 5, 3)
    # by default each class is read on its own scale: apple peaks at 0.9 and leaf at 0.7, so leaf's
    # 0.6 is 0.86 of its certainty, over its threshold 0.65; branch (all 0) stays as given
    assert meta(group)["mask_scale"] == pytest.approx({"apple": 255 / 230, "branch": 1.0, "leaf": 255 / 178}, rel=1e-6)
    assert (np.asarray(group["label"][1]) == 3).all()
    assert np.asarray(group["probability"][0, 0, :3, 0]).tolist() == [255, 255, 255]


def test_soft_masks_of_a_thin_part_are_read_on_their_own_scale(tmp_path):
    """A stem one pixel wide whose masks were blurred (soft edges) peaks at 0.4: at the threshold 0.5
    it marks nothing and its class is dropped. Read on its own scale it marks the stem; a prompt
    whose masks stay under 0.25 (noise of something the images do not show) is still dropped."""
    import cv2

    n, height, width = 3, 24, 32
    images = blank_images(tmp_path / "images.zarr", n=n, height=height, width=width)
    truth = np.zeros((n, height, width), bool)
    truth[:, 4:20, 15] = True  # a vertical stem, one pixel wide
    stem = np.stack([cv2.GaussianBlur(t.astype(np.float32), (0, 0), 0.9) for t in truth])
    assert 0.35 < stem.max() < 0.5
    rng = np.random.default_rng(0)
    noise = rng.uniform(0.0, 0.2, size=truth.shape).astype(np.float32)  # "fruit": not in the images
    masks = [write_mask(tmp_path / "stem.zarr", "stem", stem), write_mask(tmp_path / "fruit.zarr", "fruit", noise)]
    out = composite_masks(images, masks, validate_scene({})["labels"], tmp_path / "labels.zarr", progress=False)
    info = meta(open_artifact(out, stage="composite"))
    assert info["classes"] == ["stem"] and info["dropped_classes"] == ["fruit"]
    label = np.asarray(open_artifact(out)["label"][:]) == 1
    near = np.stack([cv2.dilate(t.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) for t in truth])
    assert label[truth].all() and not label[~near].any()  # the whole stem, at most a pixel beside it
    assert info["mask_scale"]["stem"] == pytest.approx(1 / stem.max(), rel=0.01)
    assert info["highest_probability"]["fruit"] < 0.25
    # the heads' targets on the same scale: the stem's pixels near 1
    assert np.median(np.asarray(open_artifact(out)["probability"][:])[..., 0][truth]) >= 250
    # as given, the stem marks nothing: no class is left, and the error names the highest probability
    with pytest.raises(ValueError, match=r"no frame contains any of the classes \['stem', 'fruit'\] "
                                         r"\(stem: highest probability 0\.4\d*"):
        composite_masks(images, masks, validate_scene({"labels": {"rescale_soft_masks": False}})["labels"],
                        tmp_path / "given.zarr", progress=False)


def test_no_prompts_give_labels_with_zero_classes(tmp_path):
    # a capture without masks (a phone capture): valid config, and labels that say "no classes"
    assert validate_scene({"segmentation": {"prompts": []}}, "config/scenes/x.yaml")["segmentation"]["prompts"] == []
    images = blank_images(tmp_path / "images.zarr", n=3, height=6, width=7)
    out = composite_masks(images, [], validate_scene({})["labels"], tmp_path / "labels.zarr", progress=False)
    group = open_artifact(out, stage="composite")
    info = meta(group)
    assert info["classes"] == [] and info["class_values"] == {} and info["pixel_counts"] == {}
    assert info["names"] == [f"frame_{i:05d}" for i in range(3)] and (info["width"], info["height"]) == (7, 6)
    assert info["label_pixel_counts"] == {"background": 3 * 6 * 7}
    assert group["multihot"].shape == (3, 6, 7, 0)
    label = np.asarray(group["label"][:])
    assert label.shape == (3, 6, 7) and not label.any()
    assert any(entry["path"] == str(images) for entry in info["inputs"])

    # the CLI the rule runs: --masks with nothing after it
    result = subprocess.run([sys.executable, "-m", "srfpipe.cli", "composite", "--images", str(images),
                             "--masks", "--out", str(tmp_path / "cli.zarr"), "--no-progress"],
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert meta(open_artifact(tmp_path / "cli.zarr"))["classes"] == []
    result = subprocess.run([sys.executable, "-m", "srfpipe.cli", "composite", "--out", str(tmp_path / "l.zarr"),
                             "--masks"], capture_output=True, text=True)
    assert result.returncode != 0 and "--images" in result.stderr


@pytest.mark.bad_input
def test_prompts_that_all_come_out_empty_are_still_an_error(tmp_path):
    images = blank_images(tmp_path / "images.zarr")
    masks = [write_mask(tmp_path / f"{p}.zarr", p, np.zeros((2, 4, 5), np.float32)) for p in ("apple", "leaf")]
    with pytest.raises(ValueError, match=r"no frame contains any of the classes \['apple', 'leaf'\]"):
        composite_masks(images, masks, validate_scene({})["labels"], tmp_path / "labels.zarr", progress=False)
    assert not (tmp_path / "labels.zarr").exists()
    kept = composite_masks(images, masks, validate_scene({"labels": {"keep_empty_classes": True}})["labels"],
                           tmp_path / "kept.zarr", progress=False)
    assert meta(open_artifact(kept))["classes"] == ["apple", "leaf"]


@pytest.mark.bad_input
def test_prompts_whose_masks_cover_no_frame_together_are_refused(tmp_path):
    """A frame is labelled only where every prompt has a mask: imported masks of two prompts for
    disjoint frames leave no frame labelled, and labels that train no semantic head are refused,
    naming each mask artifact and how many frames it covers, and nothing is written."""
    images = blank_images(tmp_path / "images.zarr", n=4)
    masks = []
    for prompt, known in (("apple", [True, True, False, False]), ("leaf", [False, False, True, True])):
        path = write_mask(tmp_path / f"{prompt}.zarr", prompt, np.ones((4, 4, 5), np.float32))
        group = zarr.open_group(str(path), mode="r+")
        group.attrs["srfpipe"] = {**group.attrs["srfpipe"], "labelled": known}
        reseal_artifact(path)  # as the import back end records frames without a mask file
        masks.append(path)
    with pytest.raises(ValueError, match=r"no frame has a mask of every prompt \['apple', 'leaf'\] \(frames with a "
                                         r"mask: .*apple.zarr: 2 of 4; .*leaf.zarr: 2 of 4\)"):
        composite_masks(images, masks, {}, tmp_path / "labels.zarr", progress=False)
    assert not (tmp_path / "labels.zarr").exists()
    # one prompt alone keeps its labelled frames
    out = composite_masks(images, masks[:1], {}, tmp_path / "labels.zarr", progress=False)
    assert meta(open_artifact(out))["labelled"] == [True, True, False, False]


@pytest.mark.bad_input
def test_masks_must_match_the_frames_of_images_zarr(tmp_path):
    images = blank_images(tmp_path / "images.zarr")
    good = write_mask(tmp_path / "apple.zarr", "apple", np.full((2, 4, 5), 0.9, np.float32))
    small = write_mask(tmp_path / "leaf.zarr", "leaf", np.full((2, 4, 4), 0.9, np.float32))
    with pytest.raises(ValueError, match=r"leaf.zarr: masks of shape \(2, 4, 4\).*images.zarr: 2 frames of 5x4"):
        composite_masks(images, [good, small], {}, tmp_path / "labels.zarr", progress=False)
    other = write_mask(tmp_path / "branch.zarr", "branch", np.full((2, 4, 5), 0.9, np.float32),
                       names=["frame_00000", "IMG_0042"])
    with pytest.raises(ValueError, match=r"branch.zarr: masks are for other frames than .*images.zarr: frame 1 is "
                                         r"'IMG_0042' in the masks, 'frame_00001' in the images"):
        composite_masks(images, [good, other], {}, tmp_path / "labels.zarr", progress=False)
    assert not (tmp_path / "labels.zarr").exists()


def test_prompt_options_hold_only_that_prompts_keys():
    section = options(prompts=["apple", "branch"], thresholds={"branch": 0.3}, prompt_text={"apple": "red apple"})
    apple, branch = prompt_options(section, "apple"), prompt_options(section, "branch")
    assert apple["threshold"] == 0.5 and branch["threshold"] == 0.3
    assert apple["prompt_text"] == {"apple": "red apple"} and branch["prompt_text"] == {}
    assert "prompts" not in apple and "import" not in apple
    grown = options(prompts=["apple", "branch", "trunk"], thresholds={"branch": 0.3, "trunk": 0.7},
                    prompt_text={"apple": "red apple", "trunk": "tree trunk"})
    assert prompt_options(grown, "apple") == apple and prompt_options(grown, "branch") == branch


# ------------------------------------------------------------- the orchard through Snakemake

# The demo's look (640x480 renders downscaled by 4 to 160x120, the built-in model's working
# resolution), with few views so that the whole build takes seconds.
SMALL_ORCHARD = {
    "source": {"format": "orchard"},
    "orchard": {"seed": 0, "views": 4},
    "images": {"downscale": 4},
    "segmentation": {"prompts": ["apple", "leaf"]},
}


def dry_run_outputs(workflow, target: str) -> list[str]:
    """The outputs of the jobs a dry run would execute, relative to the work directory."""
    result = workflow.run("-n", target)
    outputs = []
    for line in result.stdout.splitlines():
        line = line.strip()
        if line.startswith("output:"):
            outputs.extend(part.strip() for part in line[len("output:"):].split(","))
    return sorted(outputs)


@pytest.mark.workflow
def test_orchard_masks_match_ground_truth_and_new_prompts_run_alone(workflow):
    import copy

    scene = copy.deepcopy(SMALL_ORCHARD)
    workflow.write_scene("small", scene)
    target = "results/small/labels.zarr"
    workflow.run(target)

    root = workflow.root / "results" / "small"
    truth = np.asarray(open_artifact(root / "images.zarr")["ground_truth/labels"][:])
    labels = open_artifact(root / "labels.zarr", stage="composite")
    assert meta(labels)["classes"] == ["apple", "leaf"]
    assert meta(labels)["class_values"] == {"apple": 1, "leaf": 2}  # the scene's prompt order
    label = np.asarray(labels["label"][:])
    # The built-in model on the demo tree (seed 0, never seen in training), 4 views only, against
    # the class covering most of each pixel (images.zarr's ground truth)
    assert iou(label == 1, truth == 1) >= 0.8
    assert iou(label == 2, truth == 3) >= 0.85
    assert (workflow.root / "logs/small/segment_apple.log").exists()

    # adding a prompt runs that prompt's segment job and the composite, nothing else
    scene["segmentation"]["prompts"] = ["apple", "leaf", "branch"]
    workflow.write_scene("small", scene)
    assert dry_run_outputs(workflow, target) == ["results/small/labels.zarr", "results/small/masks/branch.zarr"]
    workflow.run(target)
    labels = open_artifact(root / "labels.zarr", stage="composite")
    assert meta(labels)["classes"] == ["apple", "leaf", "branch"]
    branch = np.asarray(labels["multihot"][..., 2]).astype(bool)
    assert iou(branch, truth == 2) >= 0.7

    # a per-prompt threshold changes only that prompt; a labels option only the composite
    scene["segmentation"]["thresholds"] = {"leaf": 0.6}
    workflow.write_scene("small", scene)
    assert dry_run_outputs(workflow, target) == ["results/small/labels.zarr", "results/small/masks/leaf.zarr"]
    scene["segmentation"]["thresholds"] = {}
    scene["labels"] = {"keep_empty_classes": True}
    workflow.write_scene("small", scene)
    assert dry_run_outputs(workflow, target) == ["results/small/labels.zarr"]


@pytest.mark.workflow
def test_scene_without_prompts_builds_labels_without_segment_jobs(workflow):
    scene = {"source": {"format": "orchard"}, "orchard": {"seed": 0, "views": 3, "width": 32, "height": 24},
             "images": {"downscale": 1}, "segmentation": {"prompts": []}}
    workflow.write_scene("phone", scene)
    jobs = workflow.dry_run_jobs("results/phone/labels.zarr")
    assert jobs.get("composite") == 1 and "segment" not in jobs
    workflow.run("results/phone/labels.zarr")
    labels = open_artifact(workflow.root / "results/phone/labels.zarr", stage="composite")
    assert meta(labels)["classes"] == [] and labels["multihot"].shape == (3, 24, 32, 0)
    assert labels["label"].shape == (3, 24, 32) and not np.asarray(labels["label"][:]).any()


@pytest.mark.bad_input
def test_cli_reports_an_unknown_prompt_in_one_line(tmp_path):
    images = write_images(tmp_path / "images.zarr", red_blue_images(n=1))
    result = subprocess.run([sys.executable, "-m", "srfpipe.cli", "segment", "--images", str(images),
                             "--prompt", "trunk", "--out", str(tmp_path / "trunk.zarr")],
                            capture_output=True, text=True)
    assert result.returncode == 1
    assert "unknown prompt 'trunk'" in result.stderr and "['apple', 'branch', 'leaf']" in result.stderr
    assert "orchard_segmenter.onnx" in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "trunk.zarr").exists()


def test_background_auto_sees_a_backdrop_as_empty_and_a_room_as_a_scene(tmp_path):
    """labels.background auto: a uniform dark backdrop around the masked object is empty (hull box),
    a textured surrounding is a scene (the poses' box kept)."""
    rng = np.random.default_rng(0)
    object_mask = np.zeros((3, 30, 40), np.float32)
    object_mask[:, 10:20, 15:25] = 1.0
    backdrop = np.full((3, 30, 40, 3), 14, np.uint8) + rng.integers(0, 4, (3, 30, 40, 3), dtype=np.uint8)
    room = rng.integers(0, 255, (3, 30, 40, 3), dtype=np.uint8)
    found = {}
    for name, images in (("backdrop", backdrop), ("room", room)):
        path = write_images(tmp_path / f"{name}.zarr", images)
        mask = write_mask(tmp_path / f"{name}-apple.zarr", "apple", object_mask)
        out = composite_masks(path, [mask], {}, tmp_path / f"{name}-labels.zarr", progress=False)
        found[name] = meta(open_artifact(out))
    assert found["backdrop"]["background"] == "empty" and found["backdrop"]["background_spread"] <= 4
    assert found["room"]["background"] == "scene" and found["room"]["background_spread"] > 50
    assert found["room"]["background_from"] == "images"
    # the trainer's empty-background loss reads which pixels show the backdrop from these two
    assert np.allclose(found["backdrop"]["backdrop_colour"], 15.5, atol=1) and found["backdrop"]["backdrop_level"] == 12
    assert found["room"]["backdrop_level"] is None


def test_a_scene_that_says_its_background_is_empty_gets_the_backdrop_measured(tmp_path):
    """labels.background: empty from the config still measures the backdrop's colour, so the
    trainer knows which pixels show it; a scene without classes has nothing to measure against."""
    rng = np.random.default_rng(1)
    object_mask = np.zeros((3, 30, 40), np.float32)
    object_mask[:, 10:20, 15:25] = 1.0
    images = np.full((3, 30, 40, 3), 200, np.uint8) + rng.integers(0, 6, (3, 30, 40, 3), dtype=np.uint8)
    path = write_images(tmp_path / "white.zarr", images)
    mask = write_mask(tmp_path / "white-apple.zarr", "apple", object_mask)
    out = composite_masks(path, [mask], {"background": "empty"}, tmp_path / "labels.zarr", progress=False)
    info = meta(open_artifact(out))
    assert info["background"] == "empty" and info["background_from"] == "config"
    assert np.allclose(info["backdrop_colour"], 202.5, atol=1.5)
    assert info["backdrop_level"] == max(12, 3 * info["background_spread"])
