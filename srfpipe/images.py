"""Undistort and downscale the posed images into `images.zarr`, one image in memory at a time.

For every frame of `poses.zarr`: read the image (OpenCV, turned upright by its EXIF orientation,
BGR -> RGB; alpha composited over white as nerfstudio does for Blender scenes; 16-bit scaled to
8-bit), undistort it when it has OpenCV distortion (the pinhole K is kept), resize it with
INTER_AREA by the scene's `images.downscale` factor to (round(w / f), round(h / f)) and scale the
intrinsics by the actual size ratio. The orchard's ground truth (`labels`, `depth`) goes through
the same undistortion and resize with nearest-neighbour sampling, so class ids and depths stay
exact values.

Memory: one full-resolution image plus its downscaled copy; each image is one Zarr chunk.
The artifact is written atomically (`srfpipe.artifacts.create_artifact`).
"""

from __future__ import annotations

import logging
import struct
from pathlib import Path

import numpy as np

from srfpipe import cameras
from srfpipe.config import add_options_arguments, stage_options, validate_scene

log = logging.getLogger(__name__)


def target_size(width: int, height: int, factor: float) -> tuple[int, int]:
    """(round(w / f), round(h / f)), at least 1 pixel each."""
    return max(1, int(round(width / factor))), max(1, int(round(height / factor)))


DOWNSCALE_CHOICES = (1, 2, 4)


def default_downscale(image_sizes, max_pixels: int) -> int:
    """The finest factor of DOWNSCALE_CHOICES at which all frames together hold at most `max_pixels`
    pixels, else the coarsest. A few views keep their detail; many views are as many rays as a run
    can fit at the coarsest factor already."""
    for factor in DOWNSCALE_CHOICES:
        total = sum(w * h for w, h in (target_size(int(w), int(h), factor) for w, h in image_sizes))
        if total <= max_pixels:
            return factor
    return DOWNSCALE_CHOICES[-1]


def opencv_camera_matrix(intrinsics) -> np.ndarray:
    """K in OpenCV's pixel frame, where pixel centres are integers (ours are at +0.5)."""
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    return cameras.intrinsic_matrix(fx, fy, cx - 0.5, cy - 0.5)


def undistorted_intrinsics(intrinsics, distortion, size) -> np.ndarray:
    """(fx, fy, cx, cy) of the pinhole image that undistortion makes of a frame: every pixel valid.

    Undistorting onto the lens's own K leaves pixels whose source lies outside the frame (black
    wedges along the edges: 1.5 % of a 605x806 phone frame with p1 0.011, p2 0.0096). Trained as
    content they are a black border that moves with the camera, which the field can only explain
    with floaters, and held-out views are scored against it. OpenCV's optimal new camera matrix
    with alpha 0 scales and shifts K so that the undistorted image holds valid pixels only (as
    COLMAP's image undistorter does). No distortion: the intrinsics as they are.
    """
    import cv2

    intrinsics = np.asarray(intrinsics, dtype=np.float64)
    if not np.any(np.asarray(distortion) != 0):
        return intrinsics
    size = tuple(int(v) for v in size)
    new, _ = cv2.getOptimalNewCameraMatrix(opencv_camera_matrix(intrinsics), np.asarray(distortion, np.float64),
                                           size, 0.0, size)
    # back from OpenCV's pixel-index principal point to the pixel-edge convention of intrinsics
    return np.array([new[0, 0], new[1, 1], new[0, 2] + 0.5, new[1, 2] + 0.5])


class Undistorter:
    """Undistortion maps for one calibration, reused while consecutive frames share it."""

    def __init__(self):
        self._key = None
        self._maps = None

    def maps(self, intrinsics, distortion, size):
        import cv2

        key = (tuple(np.asarray(intrinsics).tolist()), tuple(np.asarray(distortion).tolist()), tuple(size))
        if key != self._key:
            k = opencv_camera_matrix(intrinsics)
            # the undistorted image is a pinhole image with undistorted_intrinsics (all pixels valid)
            new = opencv_camera_matrix(undistorted_intrinsics(intrinsics, distortion, size))
            self._maps = cv2.initUndistortRectifyMap(
                k, np.asarray(distortion, np.float64), None, new, tuple(int(v) for v in size), cv2.CV_32FC1
            )
            self._key = key
        return self._maps

    def __call__(self, image, intrinsics, distortion, interpolation):
        import cv2

        if not np.any(np.asarray(distortion) != 0):
            return image
        map_x, map_y = self.maps(intrinsics, distortion, (image.shape[1], image.shape[0]))
        # a map entry within a pixel of the edge stays inside: replicate, not black
        return cv2.remap(image, map_x, map_y, interpolation, borderMode=cv2.BORDER_REPLICATE)


EXIF_ORIENTATION_TAG = 0x0112


def exif_orientation(exif: bytes) -> int:
    """The EXIF Orientation (1-8) in an EXIF block (TIFF header first); 1, upright, when the block
    has no such tag or cannot be parsed, as OpenCV treats it."""
    exif = exif.removeprefix(b"Exif\x00\x00")
    if exif[:4] not in (b"II*\x00", b"MM\x00*"):
        return 1
    order = "<" if exif[:2] == b"II" else ">"
    try:
        (ifd,) = struct.unpack_from(order + "I", exif, 4)
        (entries,) = struct.unpack_from(order + "H", exif, ifd)
        for index in range(entries):
            # IFD entry: tag, type, count, value; a SHORT value sits first in the 4-byte field
            tag, kind, _, value = struct.unpack_from(order + "HHIH", exif, ifd + 2 + 12 * index)
            if tag == EXIF_ORIENTATION_TAG:
                return value if kind == 3 and 1 <= value <= 8 else 1
    except struct.error:
        return 1
    return 1


def apply_orientation(image: np.ndarray, orientation: int) -> np.ndarray:
    """Pixels as stored, turned upright as EXIF `orientation` says (the same flips and transposes
    as OpenCV applies when it decodes with orientation)."""
    import cv2

    if orientation in (5, 6, 7, 8):
        image = cv2.transpose(image)
    flip = {2: 1, 3: -1, 4: 0, 6: 1, 7: -1, 8: 0}.get(orientation)  # cv2.flip code: 1 x, 0 y, -1 both
    return image if flip is None else cv2.flip(image, flip)


def check_jpeg_complete(path: Path) -> None:
    """Raise ValueError when a JPEG file ends inside its last scan: libjpeg decodes a truncated
    file with only a warning (the missing rows grey), so the end-of-image marker is checked here.
    Inside entropy-coded data 0xFF is always followed by 0x00 or a restart marker, so the last
    start-of-scan marker (FF DA) must be followed by an end-of-image marker (FF D9)."""
    with open(path, "rb") as handle:
        if handle.read(2) != b"\xff\xd8":
            return
        data = handle.read()
    if data.rfind(b"\xff\xd9") < data.rfind(b"\xff\xda"):
        raise ValueError(f"{path}: truncated JPEG (the file ends inside its image data, no end-of-image marker)")


# An image above this many pixels is refused before decoding (a 100-megapixel camera's frames
# have about 1e8): a header can claim any size, and a decoded frame of 6e4 x 6e4 px holds 10 GB.
MAX_DECODE_PIXELS = 250_000_000


def image_header_size(path: Path) -> tuple[int, int] | None:
    """(width, height) of an image file upright (EXIF orientation applied), from its header alone
    (Pillow reads no pixels to open a file); None for a format Pillow does not know (OpenCV may)."""
    from PIL import Image, UnidentifiedImageError

    limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None  # check_decodable judges the size
    try:
        with Image.open(path) as image:
            width, height = image.size
            # the EXIF block found while reading the header (JPEG's APP1, a PNG eXIf before its
            # pixels); Image.getexif would decode a PNG whole to look for one after them
            orientation = exif_orientation(image.info.get("exif") or b"")
    except UnidentifiedImageError:
        return None
    except (OSError, SyntaxError, ValueError) as exc:  # a damaged header
        raise ValueError(f"{path}: corrupt image header ({exc})") from None
    finally:
        Image.MAX_IMAGE_PIXELS = limit
    return (height, width) if orientation in (5, 6, 7, 8) else (width, height)


def check_decodable(path: Path, size: tuple[int, int] | None) -> None:
    """Refuse, before decoding, an image whose header claims more pixels than a frame may hold."""
    from srfpipe.memory import check_allocation

    if size is None:
        return
    width, height = size
    if width * height > MAX_DECODE_PIXELS:
        raise ValueError(f"{path}: its header claims {width} x {height} pixels, more than the "
                         f"{MAX_DECODE_PIXELS / 1e6:.0f} megapixels an image may have here (corrupt, or not a photo)")
    check_allocation(width * height * 4 * 2, f"{path}", f"decoding a {width} x {height} image")


def read_image(path: Path) -> np.ndarray:
    """An image file decoded as stored (bit depth, grey and alpha kept) and turned upright by its
    EXIF orientation: the one decoder for pixels (`read_rgb`); its header is checked first."""
    import cv2

    if not path.is_file():
        raise FileNotFoundError(f"{path}: image does not exist")
    check_decodable(path, image_header_size(path))
    # IMREAD_UNCHANGED keeps alpha and 16 bits but ignores the EXIF orientation (OpenCV applies
    # it only to converted reads, which drop alpha), so the tag is read and applied here.
    try:
        image, kinds, blocks = cv2.imreadWithMetadata(str(path), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        reason = str(exc).strip().splitlines()[-1] if str(exc).strip() else "unknown error"
        raise ValueError(f"{path}: corrupt or unreadable image (OpenCV: {reason})") from None
    if image is None or image.size == 0:
        raise ValueError(f"{path}: corrupt or unreadable image (OpenCV could not decode it)")
    check_jpeg_complete(path)
    for kind, block in zip(kinds, blocks):
        if kind == cv2.IMAGE_METADATA_EXIF:
            image = apply_orientation(image, exif_orientation(np.asarray(block).tobytes()))
    return image


def read_rgb(path: Path) -> np.ndarray:
    """An image file as (H, W, 3) uint8 RGB, upright (EXIF orientation applied); error naming the
    file when OpenCV cannot decode it."""
    import cv2

    image = read_image(path)
    if image.dtype == np.uint16:
        image = (image.astype(np.float32) / 257.0 + 0.5).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise ValueError(f"{path}: unsupported pixel type {image.dtype} (8- or 16-bit images only)")
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    if image.shape[2] == 4:
        # RGBA (Blender NeRF scenes): composite over white, as nerfstudio does for them.
        alpha = image[..., 3:4].astype(np.float32) / 255.0
        rgb = image[..., :3].astype(np.float32) * alpha + 255.0 * (1.0 - alpha)
        image = (rgb + 0.5).astype(np.uint8)
    return cv2.cvtColor(image[..., :3], cv2.COLOR_BGR2RGB)


def downscale_labels(labels: np.ndarray, width: int, height: int) -> np.ndarray:
    """Downscale a class-id image by area majority: each output pixel takes the class covering
    most of its footprint; on a tie the lower class value (background first) wins. Nearest-neighbour
    sampling would keep one sub-pixel in factor^2, a coin toss wherever an apple or a leaf covers
    part of the pixel."""
    import cv2

    if labels.shape == (height, width):
        return labels.astype(np.uint8)
    classes = np.unique(labels)
    coverage = np.stack([
        cv2.resize((labels == value).astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
        for value in classes
    ])
    return classes[np.argmax(coverage, axis=0)].astype(np.uint8)


def _ground_truth_files(ground_truth: Path, image_paths: list[str]) -> dict[str, list[Path]] | None:
    """labels/<stem>.png and depth/<stem>.npy per frame, when the capture has ground truth."""
    stems = [Path(p).stem for p in image_paths]
    files = {}
    for kind, suffix in (("labels", ".png"), ("depth", ".npy")):
        if (ground_truth / kind).is_dir():
            files[kind] = [ground_truth / kind / f"{stem}{suffix}" for stem in stems]
    return files or None


def _ground_truth_classes(ground_truth: Path) -> list[str] | None:
    """The class names of the label values (index = value) from ground_truth/scene.json, if it has them."""
    import json

    path = ground_truth / "scene.json"
    if not path.is_file():
        return None
    try:
        classes = json.loads(path.read_text()).get("classes")
    except (OSError, ValueError, AttributeError) as exc:
        raise ValueError(f"{path}: cannot read the ground-truth classes ({exc})") from exc
    if classes is None:
        return None
    if not isinstance(classes, list) or not classes or not all(isinstance(c, str) for c in classes):
        raise ValueError(f"{path}: classes must be a non-empty list of names (value 0 first), got {classes!r}")
    return classes


def _read_label(path: Path) -> np.ndarray:
    import cv2

    label = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if label is None:
        raise ValueError(f"{path}: corrupt or missing label image")
    if label.ndim != 2 or label.dtype != np.uint8:
        raise ValueError(f"{path}: a label image must be single-channel uint8, got {label.shape} {label.dtype}")
    return label


def _read_depth(path: Path) -> np.ndarray:
    try:
        depth = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read depth map ({exc})") from exc
    if depth.ndim != 2:
        raise ValueError(f"{path}: a depth map must be 2-D, got shape {depth.shape}")
    return depth.astype(np.float32)


def downscale_images(poses_path: str | Path, options: dict, out: str | Path, progress: bool = True) -> Path:
    """Write `images.zarr` from `poses.zarr` (see docs/artifacts.md); `options` is the `images` section."""
    import cv2
    from tqdm import tqdm

    from srfpipe.artifacts import create_artifact, meta, open_artifact, update_attrs

    options = validate_scene({"images": dict(options)}, "images options")["images"]
    poses = open_artifact(poses_path, stage="poses")
    info = meta(poses)
    root = Path(info["capture_root"])
    image_paths = list(info["image_paths"])
    intrinsics = poses["intrinsics"][:]
    distortion = poses["distortion"][:]
    image_size = poses["image_size"][:]
    n = len(image_paths)
    if options["downscale"] is None:
        factor = float(default_downscale(image_size, options["max_pixels"]))
        log.info("images.downscale %g: the finest of %s at which the %d frames hold at most %d pixels "
                 "(images.max_pixels)", factor, DOWNSCALE_CHOICES, n, options["max_pixels"])
    else:
        factor = float(options["downscale"])

    sizes = [target_size(w, h, factor) for w, h in image_size]
    width, height = sizes[0]
    for path, size in zip(image_paths, sizes):
        if size != (width, height):
            raise ValueError(
                f"{root / path}: downscaled size {size[0]}x{size[1]} differs from the first image's "
                f"{width}x{height} ({root / image_paths[0]}); all images of a capture must share one size"
            )
    scaled = np.stack([
        cameras.scale_intrinsics(undistorted_intrinsics(k, d, (w, h)), width / w, height / h)
        for k, d, (w, h) in zip(intrinsics, distortion, image_size)
    ])
    ground_truth = Path(info["ground_truth"]) if info.get("ground_truth") else None
    gt_files = _ground_truth_files(ground_truth, image_paths) if ground_truth else None
    gt_classes = _ground_truth_classes(ground_truth) if gt_files and "labels" in gt_files else None

    # the factor used, and where it came from: the options as given say null when it was derived
    config = {"images": {**options, "downscale": factor}, "downscale_from": "max_pixels" if options["downscale"] is None else "config"}
    with create_artifact(out, "downscale", config=config, inputs=[str(poses_path)]) as group:
        images = group.create_array("images", shape=(n, height, width, 3), chunks=(1, height, width, 3),
                                    dtype="uint8", dimension_names=("image", "y", "x", "c"))
        group.create_array("intrinsics", data=scaled, dimension_names=("image", "k"))
        group.create_array("camera_to_world", data=poses["camera_to_world"][:], dimension_names=("image", "row", "col"))
        gt_arrays = {}
        if gt_files:
            gt = group.create_group("ground_truth")
            if "labels" in gt_files:
                gt_arrays["labels"] = gt.create_array("labels", shape=(n, height, width), chunks=(1, height, width),
                                                      dtype="uint8", dimension_names=("image", "y", "x"))
            if "depth" in gt_files:
                gt_arrays["depth"] = gt.create_array("depth", shape=(n, height, width), chunks=(1, height, width),
                                                     dtype="float32", dimension_names=("image", "y", "x"))
        undistort = Undistorter()
        for i in tqdm(range(n), desc="downscale", unit="image", disable=not progress):
            path = root / image_paths[i]
            rgb = read_rgb(path)
            w, h = (int(v) for v in image_size[i])
            if rgb.shape[:2] != (h, w):
                raise ValueError(
                    f"{path}: image is {rgb.shape[1]}x{rgb.shape[0]} but its camera says {w}x{h}"
                )
            rgb = undistort(rgb, intrinsics[i], distortion[i], cv2.INTER_LINEAR)
            images[i] = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
            for kind, array in gt_arrays.items():
                gt_path = gt_files[kind][i]
                data = _read_label(gt_path) if kind == "labels" else _read_depth(gt_path)
                if data.shape != (h, w):
                    raise ValueError(f"{gt_path}: {kind} is {data.shape[1]}x{data.shape[0]}, the image is {w}x{h}")
                # nearest: class ids and depths must not be blended across edges
                data = undistort(data, intrinsics[i], distortion[i], cv2.INTER_NEAREST)
                if kind == "labels":
                    if gt_classes and data.max(initial=0) >= len(gt_classes):
                        raise ValueError(f"{gt_path}: label value {int(data.max())} has no class in "
                                         f"{ground_truth / 'scene.json'} (classes {gt_classes})")
                    array[i] = downscale_labels(data, width, height)
                else:
                    array[i] = cv2.resize(data, (width, height), interpolation=cv2.INTER_NEAREST_EXACT)
        update_attrs(
            group,
            names=info["names"],
            image_paths=image_paths,
            capture_root=str(root),
            width=width,
            height=height,
            downscale=factor,
            undistorted=bool(np.any(distortion != 0)),
            scene_from_world=info["scene_from_world"],
            world_from_scene=info["world_from_scene"],
            bounds_world=info["bounds_world"],
            bounds_source=info.get("bounds_source"),
            ground_truth=str(ground_truth) if ground_truth else None,
            ground_truth_classes=gt_classes,
        )
    log.info("wrote %s: %d images of %dx%d (downscale %g)", out, n, width, height, factor)
    return Path(out)


def add_arguments(parser) -> None:
    add_options_arguments(parser, "images")
    parser.add_argument("--poses", required=True, metavar="ZARR", help="poses.zarr written by `srfpipe poses`")
    parser.add_argument("--out", required=True, metavar="ZARR", help="images.zarr to write (atomically)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def run(args) -> int:
    options = stage_options(args, "images")
    downscale_images(args.poses, options, args.out, progress=not args.no_progress)
    return 0
