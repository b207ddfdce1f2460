"""ONNX segmentation back end: class-channel models and text-prompted (CLIPSeg-style) models.

Two kinds of model, told apart by their inputs (or by `segmentation.kind`):

* **class-channel** (`classes`): one image input, output (B, K, h, w), one channel per class.
  Class names come from `segmentation.classes`, else from the model's `metadata_props` key
  `classes` (a JSON list). A prompt selects its channel.
* **text-prompted** (`text`): an image input plus token ids (B, L) of integers (and optionally an
  attention mask); output one map (B, h, w) or (B, 1, h, w) for the prompt.

Images go in as float RGB in [0, 1], normalized by (x - mean) / std, NCHW or NHWC (read from the
model's input shape). An image meets the model's input size in one of three ways; all of them are
"cut a window of a canvas, resize it to the model input, resize the output back and add it in":

* dynamic-size model: the canvas is the image padded to `pad_multiple`, one window = the canvas;
* `fit: resize`: one window = the whole image, resized to the model's size;
* `fit: tile`: the canvas is cut into overlapping windows of the model's size, averaged.

Raw outputs (logits) are resized and averaged *before* the activation, like CLIPSeg upsamples its
logits, so probabilities stay calibrated at boundaries.

`metadata_props` keys read (config values override them): classes, activation, mean, std,
pad_multiple.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

log = logging.getLogger(__name__)

BUILTIN_MODEL = "orchard_segmenter.onnx"

_EXPECTED = {
    "classes": "an image input float (batch, 3, height, width) or (batch, height, width, 3); "
    "one output (batch, classes, h, w)",
    "text": "an image input float (batch, 3, height, width) or (batch, height, width, 3), "
    "token ids int (batch, length) [and an attention mask int (batch, length)]; "
    "one output (batch, h, w) or (batch, 1, h, w)",
}


def builtin_model_path() -> Path:
    """The orchard model shipped in srfpipe/models/ (classes apple, branch, leaf)."""
    return Path(str(resources.files("srfpipe").joinpath("models", BUILTIN_MODEL)))


def resolve_model(model: str) -> Path:
    """`builtin` -> the shipped model; otherwise a path that must exist."""
    path = builtin_model_path() if model == "builtin" else Path(model)
    if not path.is_file():
        problem = "is not a file (a folder?)" if path.exists() else "does not exist"
        raise FileNotFoundError(f"{path}: ONNX model file {problem} (segmentation.model)")
    return path


def execution_providers(device: str = "auto") -> list[str]:
    """CUDA when onnxruntime offers it (and the config allows), else the CPU."""
    import onnxruntime as ort

    available = ort.get_available_providers()
    has_cuda = "CUDAExecutionProvider" in available
    if device == "cuda" and not has_cuda:
        raise RuntimeError(
            f"segmentation.device is 'cuda' but onnxruntime offers only {available} "
            "(install onnxruntime-gpu on a CUDA machine)"
        )
    if device != "cpu" and has_cuda:
        return ["CUDAExecutionProvider", "CPUExecutionProvider"]
    return ["CPUExecutionProvider"]


# ----------------------------------------------------------------------------------------------
# Tokenizer (text-prompted models)


@dataclass
class Tokenizer:
    """A word-level vocabulary: each whitespace-separated word maps to one or more ids."""

    vocab: dict[str, list[int]]
    bos: int | None = None
    eos: int | None = None
    pad: int = 0
    length: int | None = None
    lowercase: bool = True
    source: str = "<tokenizer>"

    @classmethod
    def from_file(cls, path: str | Path) -> "Tokenizer":
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: tokenizer file does not exist (segmentation.tokenizer)")
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: tokenizer is not valid JSON ({exc})") from exc
        if not isinstance(data, dict):
            raise ValueError(f"{path}: tokenizer must be a JSON object")
        raw = data["vocab"] if isinstance(data.get("vocab"), dict) else data
        vocab: dict[str, list[int]] = {}
        for word, ids in raw.items():
            ids = [ids] if isinstance(ids, int) else ids
            if not (isinstance(ids, list) and ids and all(isinstance(i, int) for i in ids)):
                raise ValueError(f"{path}: vocab entry {word!r} must be an id or a list of ids, got {ids!r}")
            vocab[word] = ids
        spec = data if "vocab" in data else {}
        return cls(
            vocab=vocab, bos=spec.get("bos"), eos=spec.get("eos"), pad=int(spec.get("pad", 0)),
            length=spec.get("length"), lowercase=bool(spec.get("lowercase", True)), source=str(path),
        )

    def encode(self, text: str, length: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Token ids and attention mask (1 for real tokens), padded to `length` (or self.length)."""
        words = (text.lower() if self.lowercase else text).replace("_", " ").split()
        ids: list[int] = [] if self.bos is None else [self.bos]
        for word in words:
            if word not in self.vocab:
                raise ValueError(f"{self.source}: the word {word!r} of prompt {text!r} is not in the vocabulary")
            ids.extend(self.vocab[word])
        if self.eos is not None:
            ids.append(self.eos)
        length = length or self.length or len(ids)
        if len(ids) > length:
            raise ValueError(f"{self.source}: prompt {text!r} needs {len(ids)} tokens, the model takes {length}")
        mask = [1] * len(ids) + [0] * (length - len(ids))
        ids = ids + [self.pad] * (length - len(ids))
        return np.asarray(ids, dtype=np.int64), np.asarray(mask, dtype=np.int64)


# ----------------------------------------------------------------------------------------------
# Model inspection


@dataclass
class _Input:
    name: str
    shape: tuple  # ints or strings/None for dynamic dims
    dtype: str  # onnxruntime type string, e.g. "tensor(float)"

    @property
    def is_float(self) -> bool:
        return self.dtype in ("tensor(float)", "tensor(float16)", "tensor(double)")

    @property
    def is_int(self) -> bool:
        return self.dtype in ("tensor(int64)", "tensor(int32)")

    def describe(self) -> str:
        dims = ", ".join(str(d) if d is not None else "?" for d in self.shape)
        return f"{self.name!r} {self.dtype[7:-1]} ({dims})"


def _static(dim) -> int | None:
    return dim if isinstance(dim, int) and dim > 0 else None


def _metadata(session) -> dict[str, str]:
    return dict(session.get_modelmeta().custom_metadata_map or {})


def _json_metadata(meta: dict[str, str], key: str, path: Path):
    if key not in meta:
        return None
    try:
        return json.loads(meta[key])
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: metadata_props {key!r} is not valid JSON ({exc})") from exc


class OnnxSegmenter:
    """One ONNX model answering one prompt: `predict(images) -> probabilities`.

    `options` is the validated `segmentation` section (one prompt's view of it).
    """

    def __init__(self, options: dict, prompt: str, threads: int | None = None):
        import onnxruntime as ort

        self.options = options
        self.prompt = prompt
        self.path = resolve_model(options["model"])
        session_options = ort.SessionOptions()
        if threads:
            session_options.intra_op_num_threads = int(threads)
        session_options.log_severity_level = 3
        try:
            self.session = ort.InferenceSession(
                str(self.path), sess_options=session_options,
                providers=execution_providers(options["device"]),
            )
        except Exception as exc:  # onnxruntime raises its own exception types for bad files
            raise ValueError(f"{self.path}: onnxruntime cannot load the model ({exc})") from exc
        log.info("%s on %s", self.path, self.session.get_providers()[0])
        self.meta = _metadata(self.session)
        self.inputs = [_Input(i.name, tuple(i.shape), i.type) for i in self.session.get_inputs()]
        self.kind = self._detect_kind()
        self._bind_inputs()
        self._bind_output()
        self._read_preprocessing()
        self.query = options["prompt_text"].get(prompt, prompt)
        if self.kind == "classes":
            self.channel = self._class_channel()
        else:
            self._tokenize()

    # -- inputs and outputs ---------------------------------------------------------------------

    def _mismatch(self, problem: str) -> ValueError:
        have = "; ".join(i.describe() for i in self.inputs) or "no inputs"
        return ValueError(
            f"{self.path}: {problem}. A {self.kind if hasattr(self, 'kind') else 'segmentation'} "
            f"model is expected to have {_EXPECTED.get(getattr(self, 'kind', 'classes'))}; "
            f"this model has inputs {have}"
        )

    def _detect_kind(self) -> str:
        kind = self.options["kind"]
        if kind != "auto":
            return kind
        return "text" if any(i.is_int for i in self.inputs) else "classes"

    def _find_input(self, name: str | None, predicate, what: str, exclude=()) -> _Input | None:
        if name is not None:
            for item in self.inputs:
                if item.name == name:
                    return item
            raise self._mismatch(f"the configured {what} input {name!r} is not an input of the model")
        candidates = [i for i in self.inputs if predicate(i) and i.name not in exclude]
        return candidates[0] if candidates else None

    def _bind_inputs(self) -> None:
        opts = self.options
        image = self._find_input(opts.get("image_input"), lambda i: i.is_float, "image")
        if image is None or len(image.shape) != 4 or not image.is_float:
            raise self._mismatch("no floating-point 4-D image input")
        if _static(image.shape[1]) == 3:
            self.layout = "NCHW"
        elif _static(image.shape[3]) == 3:
            self.layout = "NHWC"
        else:
            raise self._mismatch(f"image input {image.describe()} has no channel axis of size 3")
        self.image_input = image
        used = {image.name}
        self.text_input = self.mask_input = None
        if self.kind == "text":
            ids_like = lambda i: i.is_int and "id" in i.name.lower()  # noqa: E731
            text = self._find_input(opts.get("text_input"), ids_like, "text", used) or self._find_input(
                None, lambda i: i.is_int, "text", used)
            if text is None or len(text.shape) != 2 or not text.is_int:
                raise self._mismatch("no integer token-id input (batch, length)")
            used.add(text.name)
            self.text_input = text
            mask = self._find_input(opts.get("attention_mask_input"), lambda i: i.is_int, "attention mask", used)
            if mask is not None:
                used.add(mask.name)
            self.mask_input = mask
        extra = [i for i in self.inputs if i.name not in used]
        if extra:
            raise self._mismatch("unexpected extra inputs " + ", ".join(i.describe() for i in extra))

    def _bind_output(self) -> None:
        outputs = self.session.get_outputs()
        name = self.options.get("output")
        if name is None:
            chosen = outputs[0]
        else:
            chosen = next((o for o in outputs if o.name == name), None)
            if chosen is None:
                raise ValueError(
                    f"{self.path}: segmentation.output {name!r} is not an output of the model "
                    f"(it has {[o.name for o in outputs]})"
                )
        self.output_name = chosen.name
        rank = len(chosen.shape)
        if self.kind == "classes" and rank != 4:
            raise ValueError(f"{self.path}: a class-channel model must output (batch, classes, h, w), "
                             f"output {chosen.name!r} has shape {chosen.shape}")
        if self.kind == "text" and rank not in (3, 4):
            raise ValueError(f"{self.path}: a text-prompted model must output (batch, h, w) or (batch, 1, h, w), "
                             f"output {chosen.name!r} has shape {chosen.shape}")
        self.output_shape = tuple(chosen.shape)

    def _read_preprocessing(self) -> None:
        opts, meta = self.options, self.meta
        mean = opts.get("mean") or _json_metadata(meta, "mean", self.path) or [0.0, 0.0, 0.0]
        std = opts.get("std") or _json_metadata(meta, "std", self.path) or [1.0, 1.0, 1.0]
        self.mean = np.asarray(mean, dtype=np.float32)
        self.std = np.asarray(std, dtype=np.float32)
        activation = opts["activation"]
        if activation == "auto":
            activation = meta.get("activation", "sigmoid")
        if activation not in ("sigmoid", "softmax", "none"):
            raise ValueError(f"{self.path}: metadata_props activation {activation!r} is not sigmoid|softmax|none")
        if activation == "softmax" and self.kind == "text":
            raise ValueError("segmentation.activation softmax needs a class-channel model (one map has nothing to normalize over)")
        self.activation = activation
        self.pad_multiple = int(opts.get("pad_multiple") or meta.get("pad_multiple", 1))
        shape = self.image_input.shape
        h_dim, w_dim = (shape[2], shape[3]) if self.layout == "NCHW" else (shape[1], shape[2])
        if opts.get("input_size"):
            width, height = opts["input_size"]
            if (_static(w_dim) and _static(w_dim) != width) or (_static(h_dim) and _static(h_dim) != height):
                raise self._mismatch(f"segmentation.input_size {width}x{height} differs from the model's "
                                     f"fixed input {w_dim}x{h_dim}")
            self.input_size = (int(width), int(height))
        elif _static(w_dim) and _static(h_dim):
            self.input_size = (int(w_dim), int(h_dim))
        else:
            self.input_size = None  # dynamic: the padded image itself
        batch = _static(shape[0])
        self.batch_size = batch or int(opts["batch_size"])
        self.input_dtype = np.float16 if self.image_input.dtype == "tensor(float16)" else np.float32

    def classes(self) -> list[str]:
        configured = self.options.get("classes")
        if configured:
            return list(configured)
        names = _json_metadata(self.meta, "classes", self.path)
        if names is None:
            raise ValueError(f"{self.path}: a class-channel model without metadata_props 'classes'; "
                             "name its output channels with segmentation.classes")
        return [str(n) for n in names]

    def _class_channel(self) -> int:
        names = self.classes()
        channels = _static(self.output_shape[1])
        if channels is not None and channels != len(names):
            raise ValueError(f"{self.path}: {len(names)} class names {names} for {channels} output channels")
        if self.query not in names:
            raise ValueError(
                f"unknown prompt {self.prompt!r}: the model {self.path} knows the classes {names} "
                "(map a prompt to one of them with segmentation.prompt_text)"
            )
        return names.index(self.query)

    def _tokenize(self) -> None:
        if not self.options.get("tokenizer"):
            raise ValueError(f"{self.path}: a text-prompted model needs segmentation.tokenizer (a JSON vocab file)")
        tokenizer = Tokenizer.from_file(self.options["tokenizer"])
        length = self.options.get("text_length") or tokenizer.length or _static(self.text_input.shape[1])
        self.token_ids, self.attention = tokenizer.encode(self.query, length)
        fixed = _static(self.text_input.shape[1])
        if fixed is not None and fixed != len(self.token_ids):
            raise self._mismatch(f"token length {len(self.token_ids)} differs from the model's {fixed}")
        self.token_dtype = np.int32 if self.text_input.dtype == "tensor(int32)" else np.int64

    # -- inference ------------------------------------------------------------------------------

    def _windows(self, height: int, width: int) -> tuple[tuple[int, int], list[tuple[int, int, int, int]], tuple[int, int]]:
        """Canvas size (h, w), windows (x0, y0, w, h) on it, and the model input size (w, h)."""
        if self.input_size is None:
            m = self.pad_multiple
            canvas = (-(-height // m) * m, -(-width // m) * m)
            return canvas, [(0, 0, canvas[1], canvas[0])], (canvas[1], canvas[0])
        tw, th = self.input_size
        if self.options["fit"] == "resize":
            return (height, width), [(0, 0, width, height)], (tw, th)
        canvas = (max(height, th), max(width, tw))
        overlap = float(self.options["tile_overlap"])
        xs = _tile_starts(canvas[1], tw, overlap)
        ys = _tile_starts(canvas[0], th, overlap)
        return canvas, [(x, y, tw, th) for y in ys for x in xs], (tw, th)

    def _run(self, batch: np.ndarray) -> np.ndarray:
        """Model outputs (B, K, h, w) for a batch of normalized images (B, h, w, 3) float32."""
        x = batch.transpose(0, 3, 1, 2) if self.layout == "NCHW" else batch
        feeds = {self.image_input.name: np.ascontiguousarray(x, dtype=self.input_dtype)}
        if self.kind == "text":
            feeds[self.text_input.name] = np.repeat(self.token_ids[None], len(batch), 0).astype(self.token_dtype)
            if self.mask_input is not None:
                feeds[self.mask_input.name] = np.repeat(self.attention[None], len(batch), 0).astype(self.token_dtype)
        try:
            (out,) = self.session.run([self.output_name], feeds)
        except Exception as exc:
            raise ValueError(f"{self.path}: inference failed on input {x.shape} ({exc})") from exc
        out = np.asarray(out, dtype=np.float32)
        if out.ndim not in (3, 4) or out.shape[0] != len(batch):
            raise ValueError(f"{self.path}: output {self.output_name!r} has shape {out.shape} for a batch of "
                             f"{len(batch)} images; expected {_EXPECTED[self.kind].split('; ')[-1]}")
        if np.isnan(out).any():
            raise ValueError(f"{self.path}: output {self.output_name!r} holds NaN for input {x.shape}")
        if out.ndim == 3:
            out = out[:, None]
        if self.kind == "text" and out.shape[1] != 1:
            raise ValueError(f"{self.path}: a text-prompted model must output one map, got shape {out.shape}")
        return out

    def predict(self, images: Iterable[np.ndarray], total: int | None = None, progress: bool = True) -> Iterator[np.ndarray]:
        """Probability maps (H, W) float32 in [0, 1], one per RGB uint8 image (H, W, 3), in order."""
        import cv2
        from tqdm import tqdm

        pending: list[tuple[int, np.ndarray]] = []  # (image index, model-sized input)
        state: dict[int, dict] = {}
        next_out = 0
        bar = tqdm(total=total, desc=f"segment {self.prompt}", unit="img", disable=not progress)
        for index, image in enumerate(images):
            image = np.asarray(image)
            height, width = image.shape[:2]
            canvas_hw, windows, model_wh = self._windows(height, width)
            rgb = (image.astype(np.float32) / 255.0 - self.mean) / self.std
            padded = _pad_to(rgb, canvas_hw)
            state[index] = {"size": (height, width), "sum": None, "weight": np.zeros(canvas_hw, np.float32),
                            "left": len(windows), "canvas": canvas_hw}
            for x0, y0, w, h in windows:
                crop = padded[y0:y0 + h, x0:x0 + w]
                if (w, h) != model_wh:
                    crop = cv2.resize(crop, model_wh, interpolation=_interp(w, model_wh[0]))
                pending.append((index, (x0, y0, w, h), crop))
            while len(pending) >= self.batch_size:
                self._flush(pending[: self.batch_size], state)
                del pending[: self.batch_size]
            while next_out in state and state[next_out]["left"] == 0:
                yield self._finish(state.pop(next_out))
                bar.update(1)
                next_out += 1
        if pending:
            self._flush(pending, state)
        while next_out in state:
            yield self._finish(state.pop(next_out))
            bar.update(1)
            next_out += 1
        bar.close()

    def _flush(self, items, state) -> None:
        import cv2

        outputs = self._run(np.stack([crop for _, _, crop in items]))
        for (index, (x0, y0, w, h), _), out in zip(items, outputs):
            entry = state[index]
            if entry["sum"] is None:
                entry["sum"] = np.zeros((out.shape[0], *entry["canvas"]), np.float32)
            maps = out.transpose(1, 2, 0)
            if maps.shape[:2] != (h, w):
                maps = cv2.resize(maps, (w, h), interpolation=cv2.INTER_LINEAR)
            maps = maps.reshape(h, w, -1).transpose(2, 0, 1)
            entry["sum"][:, y0:y0 + h, x0:x0 + w] += maps
            entry["weight"][y0:y0 + h, x0:x0 + w] += 1.0
            entry["left"] -= 1

    def _finish(self, entry) -> np.ndarray:
        height, width = entry["size"]
        raw = entry["sum"][:, :height, :width] / entry["weight"][None, :height, :width]
        if self.activation == "softmax":
            raw = raw - raw.max(axis=0, keepdims=True)
            expo = np.exp(raw)
            probs = expo / expo.sum(axis=0, keepdims=True)
        elif self.activation == "sigmoid":
            probs = 1.0 / (1.0 + np.exp(-np.clip(raw, -60, 60)))
        else:
            probs = np.clip(raw, 0.0, 1.0)
        channel = self.channel if self.kind == "classes" else 0
        if channel >= probs.shape[0]:
            raise ValueError(f"{self.path}: output has {probs.shape[0]} channels, class {self.query!r} is channel {channel}")
        return probs[channel].astype(np.float32)

    def describe(self) -> dict:
        from srfpipe.artifacts import file_sha256

        return {"path": str(self.path), "sha256": file_sha256(self.path), "kind": self.kind,
                "activation": self.activation, "layout": self.layout,
                "input_size": list(self.input_size) if self.input_size else None,
                "providers": self.session.get_providers(), "query": self.query}


def _tile_starts(extent: int, tile: int, overlap: float) -> list[int]:
    """Window starts covering [0, extent) with windows of `tile`, overlapping by about `overlap`."""
    if extent <= tile:
        return [0]
    stride = max(1, int(round(tile * (1.0 - overlap))))
    starts = list(range(0, extent - tile, stride))
    starts.append(extent - tile)
    return sorted(set(starts))


def _pad_to(image: np.ndarray, canvas_hw: tuple[int, int]) -> np.ndarray:
    """Pad (H, W, C) at the bottom/right by reflection so the model sees plausible context."""
    height, width = image.shape[:2]
    ph, pw = canvas_hw[0] - height, canvas_hw[1] - width
    if ph == 0 and pw == 0:
        return image
    mode = "reflect" if ph < height and pw < width else "edge"
    return np.pad(image, ((0, ph), (0, pw), (0, 0)), mode=mode)


def _interp(source: int, target: int) -> int:
    import cv2

    return cv2.INTER_AREA if target < source else cv2.INTER_LINEAR
