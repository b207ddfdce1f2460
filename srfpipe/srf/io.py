"""srf.zarr: the trained field as plain Zarr arrays (no pickle), and loading it back on CPU or CUDA.

Layout (root attributes under the `srfpipe` namespace, see docs/artifacts.md):

    weights/<state-dict key>   one float32/bool array per parameter or buffer (the occupancy grid too)
    curve/<name>               training curve: step, seconds, loss, psnr, samples_per_ray
    eval_curve/<name>          optional held-out curve: step, seconds, psnr, miou
    attrs: model_config, classes, scene_from_world, world_from_scene, bounds_world, scene_scale,
           holdout_every, train_views, heldout_views, train (options used), train_seconds, ...
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from srfpipe.artifacts import create_artifact, meta, open_artifact

FORMAT = "srfpipe-srf-1"
# weights an older srf.zarr may lack, with the model's initial value meaning the same as their absence
OPTIONAL_WEIGHTS = ("occupancy.seen0", "occupancy.seen1")


def write_srf(path, model, *, config: dict, inputs: list, curve: dict, eval_curve: dict | None = None,
              camera_adjustment: np.ndarray | None = None, **attrs) -> None:
    """Write a trained `SRFModel` and its metadata atomically to `path`; `camera_adjustment`: the
    (N, 6) pose corrections of train.camera_refinement (srf.camera_refinement), as cameras/adjustment."""
    state = model.state_dict()
    with create_artifact(path, stage="train", config=config, inputs=inputs, format=FORMAT,
                         model_config=model.config, **attrs) as group:
        weights = group.create_group("weights")
        for key, tensor in state.items():
            array = tensor.detach().cpu()
            array = array.numpy() if array.dtype == torch.bool else array.float().numpy()
            chunks = array.shape if array.size < (1 << 22) else (max(1, (1 << 22) // max(1, int(np.prod(array.shape[1:])))),) + array.shape[1:]
            weights.create_array(key, shape=array.shape, chunks=chunks or None, dtype=array.dtype)[...] = array
        for name, series in (("curve", curve), ("eval_curve", eval_curve or {})):
            sub = group.create_group(name)
            for key, values in series.items():
                values = np.asarray(values, dtype=np.float64)
                sub.create_array(key, shape=values.shape, dtype=np.float64)[...] = values
        if camera_adjustment is not None:
            adjustment = np.asarray(camera_adjustment, dtype=np.float64)
            group.create_group("cameras").create_array("adjustment", shape=adjustment.shape,
                                                       dtype=np.float64)[...] = adjustment


# Model-config keys that srf.zarr files written before them lack, with what the model did then
# (build_model_config writes every one of them today)
LEGACY_MODEL_CONFIG = {"density_bias": -1.0, "density_grid": False, "appearance_dim": 0, "color_layers": 2,
                       "semantic_octaves": 0, "color_threshold": 1e-4}


def attribute_problem(attrs: dict) -> str | None:
    """What is wrong with the attributes a field is loaded from (`SemanticRadianceField` reads them
    all), or None: each must be there, of its shape, and `classes` one name per semantic head."""
    config = attrs.get("model_config")
    if not isinstance(config, dict):
        return "attribute model_config is missing or not a mapping"
    classes = attrs.get("classes")
    if not isinstance(classes, list) or not all(isinstance(c, str) for c in classes):
        return "attribute classes is missing or not a list of names"
    heads = config.get("num_classes", len(classes))
    if heads != len(classes):
        return f"attribute classes names {len(classes)} classes {classes}, the model has {heads} semantic heads"
    for key, shape in (("scene_from_world", (4, 4)), ("world_from_scene", (4, 4)), ("bounds_world", (2, 3))):
        try:
            value = np.asarray(attrs.get(key), dtype=np.float64)
        except (TypeError, ValueError):
            value = np.zeros(0)
        if value.shape != shape or not np.all(np.isfinite(value)):
            return f"attribute {key} is missing or not a finite {shape[0]}x{shape[1]} array"
    scale = attrs.get("scene_scale")
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not np.isfinite(scale) or scale <= 0:
        return f"attribute scene_scale must be a positive number, got {scale!r}"
    return None


def read_srf(path, device="cpu"):
    """(model, attrs) from srf.zarr on `device` (a torch.device or string), in eval mode."""
    from srfpipe.srf.model import SRFModel

    path = Path(path)
    group = open_artifact(path, stage="train")
    attrs = meta(group)
    if attrs.get("format") != FORMAT:
        raise ValueError(f"{path}: unknown SRF format {attrs.get('format')!r}, this srfpipe reads {FORMAT}")
    if problem := attribute_problem(attrs):
        raise ValueError(f"{path}: {problem}; the artifact is damaged: delete it and re-run its stage 'train'")
    config = {**LEGACY_MODEL_CONFIG, **attrs["model_config"]}
    weights = group["weights"]
    for key in ("inner", "outer"):  # the torch layout, unless tiny-cuda-nn wrote the table
        if config.get(key):
            tcnn = f"field.{key}.encoding.params" in weights
            if tcnn and torch.device(device).type != "cuda":
                raise ValueError(f"{path}: trained with tiny-cuda-nn; load it on a CUDA device")
            config[key] = dict(config[key], prefer_tcnn=tcnn)
    try:
        model = SRFModel(config, device)
    except (KeyError, TypeError, ValueError, IndexError) as exc:  # a model_config no trainer wrote
        raise ValueError(f"{path}: attribute model_config does not describe a model ({type(exc).__name__}: {exc}); "
                         "the artifact is damaged: delete it and re-run its stage 'train'") from exc
    state = model.state_dict()
    # a trained parameter that is not finite renders nothing (NaN PSNR, an empty cache); buffers
    # may hold NaN on purpose (camera_centres of views no training image was taken from)
    parameters = {name for name, _ in model.named_parameters()}
    loaded = {}
    for key, tensor in state.items():
        if key not in weights and key in OPTIONAL_WEIGHTS:
            loaded[key] = tensor  # written before srfpipe marked unseen space: everything counts as seen
            continue
        if key not in weights:
            raise ValueError(f"{path}: weights/{key} is missing")
        array = np.asarray(weights[key][...])
        if tuple(array.shape) != tuple(tensor.shape):
            raise ValueError(f"{path}: weights/{key} has shape {array.shape}, the model expects {tuple(tensor.shape)}")
        if key in parameters and not np.all(np.isfinite(array)):
            raise ValueError(f"{path}: weights/{key} holds {int(np.sum(~np.isfinite(array)))} NaN or infinite "
                             "values (a training that diverged, or a damaged file); re-run its stage 'train'")
        loaded[key] = torch.from_numpy(array).to(tensor.dtype)
    model.load_state_dict(loaded)
    return model.to(device).eval(), attrs


def read_camera_adjustment(path) -> np.ndarray | None:
    """The (N, 6) pose corrections a run with train.camera_refinement learned (None without)."""
    group = open_artifact(path, stage="train")
    if "cameras" not in group or "adjustment" not in group["cameras"]:
        return None
    adjustment = np.asarray(group["cameras"]["adjustment"][...], dtype=np.float64)
    if adjustment.ndim != 2 or adjustment.shape[1] != 6 or not np.all(np.isfinite(adjustment)):
        raise ValueError(f"{path}: cameras/adjustment must be finite (N, 6) pose corrections, got {adjustment.shape}")
    return adjustment


def read_curve(path, name: str = "curve") -> dict[str, np.ndarray]:
    group = open_artifact(path, stage="train")
    if name not in group:
        return {}
    return {key: np.asarray(array[...]) for key, array in group[name].arrays()}
