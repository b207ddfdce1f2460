"""Typed settings: one frozen dataclass per section of the scene schema.

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


@dataclass(frozen=True)
class SourceSettings(SettingsSection):
    """`source`: where the capture comes from"""

    SECTION: ClassVar[str] = 'source'

    format: str = 'orchard'
    """orchard and plant are built-in generators (sections orchard, plant) writing a nerfstudio
    capture with ground truth"""
    path: str | None = field(default=None, metadata={"unset": True})
    """capture folder (nerfstudio: holds transforms.json; blender: holds transforms_*.json; colmap:
    holds images/ and sparse/0 or a model folder; llff: holds poses_bounds.npy and images_4/ or
    images/; images: holds the photos, or an images/ ..."""
    images_dir: str | None = field(default=None, metadata={"unset": True})
    """colmap, llff and images, images folder relative to path (colmap default: images; llff
    default: images_4 if present, else images; llff pairs its files in sorted order with the rows
    of poses_bounds.npy and scales the focal length by their ..."""
    model_dir: str | None = field(default=None, metadata={"unset": True})
    """colmap only, sparse model folder relative to path (default sparse/0)"""
    max_frames: int | None = field(default=None, metadata={"unset": True})
    """video only, the most frames kept (absent: 150): the video is cut into this many windows of
    equal length and the sharpest frame of each (variance of the Laplacian) is kept, unless it is
    under half the median sharpness of the 16 frames round ..."""
    allowed_roots: tuple | None = field(default=None, metadata={"unset": True})
    """folders outside the capture that its image paths may lead into through symlinks (e.g. an
    images folder symlinked to shared storage)"""


@dataclass(frozen=True)
class OrchardSettings(SettingsSection):
    """`orchard`: parameters of the procedural apple tree (format orchard only)"""

    SECTION: ClassVar[str] = 'orchard'

    seed: int = 0
    """random seed of the tree, textures, sun and views"""
    n_apples: int = 24
    """apples hung on the tree"""
    branch_depth: int = 4
    """levels of branching from the trunk"""
    leaf_density: float = 1.0
    """multiplier on leaves per branch tip"""
    tree_height: float = 2.5
    """metres"""
    views: int = 80
    """camera views rendered"""
    width: int = 640
    """image width in pixels"""
    height: int = 480
    """image height in pixels"""
    fov_deg: float = 60
    """horizontal field of view"""
    ring_heights: tuple = (0.9, 2.2)
    """camera heights (metres) of the rings walked around the tree"""
    ring_radius: float = 3.5
    """metres from the trunk"""
    arc_deg: float | None = field(default=None, metadata={"unset": True})
    """spread each ring's views over this arc of azimuth on one side of the tree, every camera
    looking at it from there (a forward-facing capture, as LLFF's handheld ones; the rings only,
    `video` walks the whole turn)"""
    distortion: tuple | None = field(default=None, metadata={"unset": True})
    """render through an OpenCV lens with these k1, k2, p1, p2 (written to transforms.json, as a
    real capture's calibration)"""
    video: bool | None = field(default=None, metadata={"unset": True})
    """true = walk one continuous turn round the tree (the azimuth stepping evenly, the height
    climbing from the lowest ring height to the highest at ring_radius) and write the views also
    as video.avi (Motion-JPEG, 10 frames per second, frame i = ..."""


@dataclass(frozen=True)
class PlantSettings(SettingsSection):
    """`plant`: parameters of the procedural sapling (format plant only): a thin plant on a dark
    backdrop, few views from far away"""

    SECTION: ClassVar[str] = 'plant'

    seed: int = 0
    """random seed of the plant, textures, light, views and noise"""
    plant_height: float = 300
    """millimetres"""
    n_twigs: int = 8
    """side twigs along the stem"""
    leaves_per_twig: int = 4
    """leaves on each twig"""
    n_berries: int = 9
    """berries, in clusters of three near twig tips"""
    views: int = 18
    """camera views rendered"""
    width: int = 512
    """image width in pixels"""
    height: int = 512
    """image height in pixels"""
    fov_deg: float = 10
    """horizontal field of view"""
    distance: float = 2400
    """millimetres from the plant's centre to every camera"""
    elevations_deg: tuple = (10, 40)
    """one camera ring per elevation (degrees above the plant's centre)"""
    sensor_noise: float = 1.5
    """std of Gaussian noise on every image, 8-bit levels"""


@dataclass(frozen=True)
class PosesSettings(SettingsSection):
    """`poses`: camera poses: imported, refined by COLMAP or recovered by structure from motion
    (stage poses -> poses.zarr)"""

    SECTION: ClassVar[str] = 'poses'

    refine: str = 'none'
    """refine imported poses with COLMAP (pycolmap) triangulation + bundle adjustment"""
    refine_distortion: str | bool | None = field(default=None, metadata={"unset": True})
    """with refine: colmap, fit the calibrations' distortion (OpenCV k1, k2, p1, p2) in every bundle
    adjustment too, shared by the images that share a calibration"""
    matcher: str = 'auto'
    """COLMAP pair selection. auto = exhaustive up to 20 images, poses otherwise"""
    min_images: int = 2
    """frames whose image file is missing are skipped with a warning (and listed in poses.zarr)"""
    camera_model: str | None = field(default=None, metadata={"unset": True})
    """structure from motion only, the COLMAP camera model fitted (absent: RADIAL, one focal length,
    k1 and k2; SIMPLE_RADIAL has k1 only; OPENCV has fx, fy, k1, k2, p1, p2), written as the
    project's OpenCV intrinsics and distortion"""
    principal_point: str = 'auto'
    """structure from motion only"""
    up: str | None = field(default=None, metadata={"unset": True})
    """auto = turn the world about its origin so that the cameras' mean up vector (-y of each OpenCV
    camera) is +z, before the bounds are found (for structure from motion, whose world is
    arbitrarily oriented; poses.bounds are then in the turned ..."""
    perturb_rot_deg: float = 0
    """testing aid, rotate every imported pose by this many degrees about a random axis"""
    perturb_trans_frac: float = 0
    """testing aid, translate every pose by this fraction of the scene size"""
    perturb_seed: int = 0
    """seed of the perturbations (perturb_rot_deg, perturb_trans_frac)"""
    bounds: tuple | None = None
    """[[xmin, ymin, zmin], [xmax, ymax, zmax]] in world units"""
    points_box: str = 'near_cameras'
    """the box estimated from sparse points (when bounds are null and the capture has no ground
    truth): all = their 1-99 % percentiles plus 5 %"""


@dataclass(frozen=True)
class ImagesSettings(SettingsSection):
    """`images`: undistortion and downscaling of the posed images (stage downscale -> images.zarr)"""

    SECTION: ClassVar[str] = 'images'

    downscale: float | None = None
    """factor the images shrink by (OpenCV INTER_AREA). null = from the capture: the finest of 1, 2
    and 4 at which all its frames together hold at most max_pixels pixels, else 4 (orchard: 80
    frames of 640 x 480 -> 4; fox: 50 of 1080 x 1920 -> 4; ..."""
    max_pixels: int = 2000000
    """pixels of all frames together that a null downscale keeps at most"""


@dataclass(frozen=True)
class SegmentationImportSettings(SettingsSection):
    """`segmentation.import`: backend import, precomputed masks (e.g. SAM 3 run elsewhere)"""

    SECTION: ClassVar[str] = 'segmentation.import'

    path: str | None = None
    """folder holding the masks (relative paths are relative to the Snakemake work directory)"""
    format: str = 'masks'
    """masks = one grayscale PNG per image and prompt (binary 0/255 or 0/1, or soft 8/16-bit
    probabilities)"""
    pattern: str | None = None
    """file name inside path, with {name} (the image name as in images.zarr), {stem} (the name
    without an image extension such as .png, if it has one) and {prompt}. null =
    '{stem}_{prompt}.png' for masks, '{stem}.png' for labels"""
    values: dict[str, Any] = field(default_factory=lambda: {'apple': 1, 'branch': 2, 'leaf': 3})
    """format labels, the label value(s) of each prompt's class (the paper's table by default)"""


@dataclass(frozen=True)
class SegmentationSettings(SettingsSection):
    """`segmentation`: Per-prompt masks (stage segment, one rule per prompt -> masks/{prompt}.zarr)"""

    SECTION: ClassVar[str] = 'segmentation'

    backend: str = 'onnx'
    """onnx = run an ONNX model (class-channel or text-prompted)"""
    prompts: tuple = ('apple', 'branch', 'leaf')
    """one mask per prompt"""
    threshold: float = 0.5
    """a pixel belongs to a prompt's class when its probability is >= this"""
    thresholds: dict[str, Any] = field(default_factory=dict)
    """per-prompt overrides of threshold, e.g. {branch: 0.4}"""
    model: str = 'builtin'
    """onnx: path of the .onnx file, or 'builtin' for the orchard model shipped in srfpipe/models/
    (class-channel, classes apple, branch, leaf; trained on orchard seeds other than the demo's)"""
    kind: str = 'auto'
    """onnx model kind. classes = one image input, output (B, K, h, w) with one channel per class"""
    classes: tuple | None = None
    """class-channel models, names of the output channels"""
    prompt_text: dict[str, Any] = field(default_factory=dict)
    """what to ask the model for each prompt (class-channel: a class name; text: the words to
    tokenize), e.g. {apple: "a red apple"}"""
    activation: str = 'auto'
    """how the model's outputs become probabilities. sigmoid = independent logits (multi-label),
    softmax over the class channels, none = already probabilities. auto = the model's
    metadata_props 'activation', else sigmoid"""
    input_size: tuple | None = None
    """[width, height] fed to the model"""
    fit: str = 'resize'
    """how an image meets a fixed model input size: resize the whole image (and the output back), or
    cut overlapping tiles of the input size and average the outputs where they overlap"""
    tile_overlap: float = 0.25
    """fit tile, overlap between neighbouring tiles as a fraction of the tile size"""
    pad_multiple: int | None = None
    """dynamic-size models, pad the image to a multiple of this (null = metadata_props
    'pad_multiple', else 1)"""
    mean: tuple | None = None
    """per-channel mean subtracted from RGB in [0, 1] (null = metadata_props 'mean', else [0, 0, 0])"""
    std: tuple | None = None
    """per-channel std dividing RGB in [0, 1] (null = metadata_props 'std', else [1, 1, 1])"""
    image_input: str | None = None
    """name of the image input (null = the model's floating-point input)"""
    text_input: str | None = None
    """text models, name of the token-id input (null = the integer input named like *ids*, else the
    first)"""
    attention_mask_input: str | None = None
    """text models, name of an attention-mask input (null = the other integer input, if any)"""
    output: str | None = None
    """name of the output to read (null = the first)"""
    tokenizer: str | None = None
    """text models, a JSON file: either {word: id or [ids]} or {"vocab": {...}, "bos": id, "eos":
    id, "pad": id, "length": L, "lowercase": true}"""
    text_length: int | None = None
    """text models, token sequence length (null = the tokenizer's 'length', else the model's static
    length, else unpadded)"""
    batch_size: int = 8
    """images (or tiles) per model call"""
    device: str = 'auto'
    """auto = CUDAExecutionProvider when onnxruntime has it, else the CPU"""
    import_: SegmentationImportSettings = field(
        default_factory=SegmentationImportSettings, metadata={"key": 'import', "section": SegmentationImportSettings})
    """backend import, precomputed masks (e.g. SAM 3 run elsewhere)"""


@dataclass(frozen=True)
class LabelsSettings(SettingsSection):
    """`labels`: compositing the prompts' masks into labels.zarr (stage composite)"""

    SECTION: ClassVar[str] = 'labels'

    bounds: str = 'auto'
    """the model's bounds every later stage uses. masks = the box of the visual hull of the labelled
    pixels (the frusta carved by the masks; on an empty background, by each frame's silhouette
    against the backdrop as well, so masks of some parts ..."""
    background: str = 'auto'
    """what the pixels that no mask marks show. scene = anything (a table, a room, the ground: masks
    name only the prompted objects), so the geometry comes from the cameras and the sparse points
    and the masks supervise the semantic heads only"""
    keep_empty_classes: bool = False
    """keep a class that no frame contains (by default it is reported and left out of the heads)"""
    min_pixels: int = 0
    """a class with at most this many pixels over all frames counts as empty"""
    rescale_soft_masks: bool = True
    """read each class's masks on their own scale: a class whose masks peak at h < 1 over all frames
    (soft masks: a blurred thin part, a segmenter never sure of a small object) has its
    probabilities divided by h before the threshold and the ..."""
    colors: dict[str, Any] = field(default_factory=dict)
    """RGBA colour per class name for the NGFF image-label table, e.g. {apple: [220, 30, 30, 255]}"""


@dataclass(frozen=True)
class TrainSettings(SettingsSection):
    """`train`: training of the semantic radiance field (stage train -> srf.zarr)"""

    SECTION: ClassVar[str] = 'train'

    iterations: int = 20000
    """training steps at most"""
    rays_per_batch: int = 4096
    """rays drawn from the training views per step"""
    seed: int = 0
    """seed of the model's initial weights and of every step's ray sampling (a step's stream is a
    function of seed and step)"""
    lambda_sem: float = 1.0
    """weight of the semantic BCE (paper lambda)"""
    semantic_targets: str | None = field(default=None, metadata={"unset": True})
    """what the semantic heads' BCE compares each ray with: probabilities (each class's mask
    probability, labels.zarr probability: a pixel half covered by a thin part, or a soft mask's
    blurred rim, is neither in nor out) or labels (the composited ..."""
    semantic_positive_weight: float | None = field(default=None, metadata={"unset": True})
    """weight of each class's positive term in the BCE (torch's pos_weight): w > 1 marks a class
    where the masks of the views that see a point give it a mean probability of at least 1 / (1 +
    w), for masks that miss thin parts more often than they ..."""
    device: str = 'auto'
    """auto | cpu | cuda | cuda:N"""
    lr: float = 0.01
    """Adam learning rate at step 0 (paper 1e-2)"""
    lr_final: float = 0.001
    """learning rate at the last step (exponential decay)"""
    lr_hold: float = 0.0
    """fraction of the run (steps or time budget) trained at lr before the exponential decay to
    lr_final begins"""
    precision: str = 'auto'
    """auto = bf16/fp16 autocast on CUDA, fp32 on the CPU"""
    cuda_graph: bool = True
    """on CUDA, replay each training step as one CUDA graph (the dense grid, batches up to 8192
    rays; not with fp16 or tv_samples, which read values back on the host)"""
    encoding: str = 'auto'
    """auto = the dense grid, which measured best on the CPU and on an H100
    (srfpipe.srf.model.default_encoding)"""
    detail_size: float | None = None
    """grid cell size in world units (metres for the orchard)"""
    default_cells: int | None = None
    """cells along the largest extent when detail_size is null (null = from the images: 96, up to
    192 when 96 cells would each span more than 2 pixels, fewer (one pixel each, at least 24)
    when they would span less than one)"""
    grid_levels: int | None = None
    """dense grids at this many resolutions, each half as fine as the next (the finest has the cells
    set by detail_size / default_cells)"""
    max_resolution: int = 256
    """cap on grid points per axis (memory)"""
    grid_frame: str = 'auto'
    """auto = perspective where the cameras all look one way (they do not stand round their focus
    point and their viewing directions agree: a forward-facing capture), box otherwise"""
    fine_levels: int | None = None
    """dense encoding: levels finer than the grid, each twice as fine as the one before, stored in a
    hashed table of 2^fine_log2_table_size rows (detail beyond what a dense grid can afford;
    samples and the occupancy grid keep the grid's cells). ..."""
    fine_log2_table_size: int = 22
    """rows of each fine level's table, as a power of two"""
    box_padding: float = 0.0
    """grow the model box by this fraction of its size per side"""
    contraction: bool = True
    """model space outside the box (ground, far objects) in a contracted shell"""
    empty_unseen: bool = True
    """space no training camera sees is empty (not sampled, not rendered, zero density in queries
    and the cache): nothing constrains it, and a held-out camera looking through it would see
    what the shared grid left there"""
    features: int | None = None
    """dense grid features per cell (per level; null = 16 for one level, 8 for several)"""
    outer_resolution: int = 48
    """dense grid points per axis of the contracted shell"""
    hidden: int = 64
    """MLP width"""
    geo_features: int = 15
    """size of the latent h"""
    sh_degree: int = 4
    """spherical-harmonic bands of the view direction"""
    background_sh_degree: int | None = None
    """spherical-harmonic bands of the direction that the background colour model (what a ray sees
    beyond the field) reads. null = from the capture: 2 (the direction itself: a smooth function
    that a new view between the training views ..."""
    appearance_dim: int | None = None
    """per-image appearance embedding size (0 = off; null = 8 for a real capture whose images form a
    sequence, a video or a walk, whose frames vary in exposure and white balance and a new view
    borrows its neighbours' appearance; 0 for photos in ..."""
    appearance_model: str = 'latent'
    """how the per-image appearance acts: latent (an input of the colour MLP, as NeRF-W and
    Nerfacto) or affine (a colour matrix and offset applied to each image's rendered pixels:
    exposure and white balance, and nothing a single view shows)"""
    appearance_smoothness: float = 0.0
    """weight of a penalty on how differently the colour MLP receives the latent appearance of each
    training image and of the image taken nearest to it (the one a new view there borrows): keeps
    what a single frame shows out of its embedding. 0 = ..."""
    novel_view_appearances: int = 2
    """with per-image appearance embeddings, a view no training image was taken from (a held-out
    view, Render(pose) of the simulator) is rendered as the mean of what the appearance of this
    many training images taken nearest to it makes of it, ..."""
    distortion: float | None = None
    """weight of mip-NeRF 360's distortion loss, which pulls each ray's weight into one short
    interval (against fog and floaters)"""
    object_rays: float = 0.1
    """when the pixels that show a class (dilated by 2 px) are fewer than this share of the training
    pixels, this share of every batch is drawn from them: a small object (a plant under 1 % of
    the frame) would otherwise get a few rays a step"""
    pixel_jitter: bool = False
    """true: each training ray passes through a uniformly random point of its pixel instead of its
    centre"""
    supersample: int = 1
    """each training pixel is rendered as the mean of s x s rays through a regular grid of points
    over its footprint (as evaluate renders a pixel), and that mean is compared with it:
    rays_per_batch / s^2 pixels a step. 1 = one ray through each ..."""
    background_opacity: float | None = None
    """weight of the loss on the opacity along the rays (the box and the shell beyond it) whose
    pixel shows none of the classes on an empty background (null: chosen from the data, see the
    README)"""
    background_rays: str = 'auto'
    """which rays the empty-background loss empties: unmasked (every pixel no mask marks) or
    backdrop (those that also have the backdrop's colour, so a part the masks miss keeps its
    matter)"""
    camera_refinement: bool | str = False
    """true: each training camera's pose is refined while training (Nerfacto's SO3xR3 camera
    optimizer: a rotation and a translation per image, Adam at camera_lr, an L2 penalty on their
    size; their common motion removed, so the cameras keep the ..."""
    camera_lr: float = 0.0006
    """Adam's learning rate of the camera corrections of camera_refinement (Nerfacto's), decayed
    with the field's schedule"""
    tv_density: float = 0.0
    """weight of the total-variation loss on the dense density grid (Plenoxels)"""
    tv_features: float = 0.0
    """weight of the total-variation loss on the dense feature grid"""
    tv_samples: int | None = None
    """estimate the total variation at this many random cells per grid and step (cheaper on the CPU
    for large grids)"""
    step_ratio: float = 1.0
    """sample spacing inside the box, in cells"""
    near: float = 0.05
    """near plane (scene-frame units)"""
    far: float = 200.0
    """far plane with contraction (scene-frame units)"""
    outer_samples: int = 32
    """samples beyond the box (uniform in disparity)"""
    before_samples: int = 8
    """samples between the camera and the box"""
    occupancy_threshold: float = 0.01
    """opacity per step below which a cell is skipped"""
    occupancy_update_every: int = 16
    """steps between two updates of the occupancy grid that skips empty space"""
    occupancy_warmup: int = 256
    """steps during which every cell is re-evaluated"""
    occupancy_outer_resolution: int = 32
    """occupancy grid cells per axis of the contracted shell"""
    checkpoint_every: int = 500
    """steps between checkpoints (0 = none)"""
    keep_checkpoints: bool = False
    """keep the checkpoint folder after success"""
    snapshot_seconds: tuple = ()
    """save the model's weights (no optimizer state) at the first step past each of these training
    seconds, as snapshot-<step>.pt in the checkpoint folder, kept after success (quality against
    time: benchmarks/peers.py)"""
    log_every: int = 25
    """steps between two lines of the metrics log (and the divergence check)"""
    eval_every: int = 0
    """held-out PSNR/mIoU every n steps, excluded from train time (0 = off)"""
    time_budget: float = 600
    """stop after this many seconds of training, with the learning-rate decay following the clock (0
    = run all iterations; only then is a resumed run bit-identical)"""
    color_layers: int = 1
    """hidden layers of the colour MLP"""
    color_threshold: float = 0.0001
    """samples with a smaller weight skip the colour and semantic heads (dense grids)"""
    initial_opacity: float | None = None
    """opacity per step of the untrained density grid (null = 0.01 when the bounds come from the
    config or the capture's ground truth, 0.001 when they were estimated: less initial fog to fit
    the views with)"""
    density_grid: bool | None = field(default=None, metadata={"unset": True})
    """sigma reads its own one-channel dense grid (no default: true for dense grids, false for hash
    grids)"""
    hash_levels: int | None = field(default=None, metadata={"unset": True})
    """hash grid levels (no default: 16)"""
    hash_log2_table_size: int | None = field(default=None, metadata={"unset": True})
    """log2 of the hash table size per level (no default: 19)"""
    density_decay: float = 0.0
    """decoupled weight decay of the dense log-density grids: Adam shrinks each value by lr *
    density_decay a step towards the initial opacity (Zip-NeRF decays its grids), so density the
    views stop supporting fades (0 = off)"""
    grid_lr_scale: float = 10.0
    """learning-rate multiplier of dense grid tables (DVGO-style fast grids)"""
    background_lr_scale: float | None = None
    """learning-rate multiplier of the background colour model (what a ray sees beyond the field),
    from background_lr_after of the run on. null = from the capture: 0.1 on an empty backdrop,
    where that model is most of every view and, once learnt, ..."""
    background_lr_after: float = 0.3
    """fraction of the run's progress (steps, or the time budget when that comes first) during which
    the background colour model learns at the field's rate before background_lr_scale applies: it
    has to learn the backdrop first (a tenth from the ..."""
    semantic_octaves: int = 4
    """frequency octaves of the position fed to the semantic head besides h.detach() (0 = h only)"""


@dataclass(frozen=True)
class EvaluateSettings(SettingsSection):
    """`evaluate`: held-out evaluation of the trained field (stage evaluate -> eval/)"""

    SECTION: ClassVar[str] = 'evaluate'

    holdout_every: int = 8
    """every k-th view is held out from training"""
    supersample: int | None = None
    """render each held-out pixel as the mean of s x s rays over its footprint, as a pixel (and a
    downscaled image's area average) integrates light over its area. null: 2 while a view's s x s
    rays stay within 262144 (views of up to 256 x 256 ..."""
    unlabelled_views: int = 8
    """sparse labels: when some training frames had no masks and the capture has ground-truth
    labels, this many of those frames (evenly spaced) are rendered and scored against the ground
    truth (metrics.json iou_unlabelled_gt, miou_unlabelled_gt: ..."""
    train_views: int = 3
    """the generalization check: this many training views (evenly spaced) are rendered like the
    held-out ones and scored (metrics.json train_view_psnr, generalization_gap_db =
    train_view_psnr - psnr; no renders written)"""


@dataclass(frozen=True)
class OccupancySettings(SettingsSection):
    """`occupancy`: distillation of the field into the occupancy cache (occupancy.zarr)"""

    SECTION: ClassVar[str] = 'occupancy'

    voxel_size: float | None = None
    """voxel edge in world units, an override"""
    voxels_across: int = 136
    """voxels along the largest extent of the scene bounds when voxel_size is null (136 = 1.99 cm on
    the 2.71 m orchard)"""
    supersample: int = 2
    """n^3 density samples per voxel (max kept, so thin branches survive)"""
    alpha_threshold: float = 0.2
    """occupied when the voxel opacity 1 - exp(-sigma * voxel_size) reaches this"""
    density_floor_alpha: float = 0.001
    """densities whose voxel opacity is below this are stored as 0 (empty space stores no chunks)"""
    semantic_alpha_min: float = 0.01
    """class probabilities are computed where the voxel opacity reaches this, 0 elsewhere"""
    class_threshold: float = 0.5
    """per-class occupancy: occupied and probability above this"""
    class_thresholds: dict[str, Any] = field(default_factory=dict)
    """per-class overrides of class_threshold, by class name"""
    avoid: tuple = ('branch',)
    """classes to avoid (collision), each gets a signed distance field"""
    reach: tuple = ('apple',)
    """classes to reach (goals), each gets a signed distance field"""
    distance_truncation: float | None = None
    """signed distances are clipped to +-this many world units, an override"""
    truncation_voxels: float = 15
    """signed distances are clipped to +-this many voxels when distance_truncation is null"""
    brick: int = 32
    """edge of the Zarr chunks (voxels) and of the compute bricks"""
    max_voxels: int = 134217728
    """a larger grid gets the finest coarser voxel that fits (a warning; asked and used sizes are
    recorded)"""
    batch_points: int = 262144
    """points per field query"""
    unit: str | None = None
    """OME-Zarr axis unit of the world frame, e.g. meter"""
    device: str = 'auto'
    """device the field is loaded on: auto | cpu | cuda | cuda:N"""


@dataclass(frozen=True)
class SimSettings(SettingsSection):
    """`sim`: simulator packaging (results/<scene>/sim/, srfpipe package) and the runtime's defaults"""

    SECTION: ClassVar[str] = 'sim'

    metres_per_unit: float | None = None
    """metres per world unit, an override"""
    min_instance_voxels: int = 4
    """smaller connected pieces of a reach class are not fruit"""
    split_min_radius_voxels: float = 1.5
    """touching fruit are split by a watershed at distance-map peaks at least this deep (voxels)"""
    match_radii: float = 2.0
    """an instance matches a ground-truth fruit whose centre is within this many of its radii"""
    arm_reach: float | None = None
    """arm reach (shoulder to tool tip) in metres, an override"""
    arm_reach_fraction: float = 0.5
    """the arm's reach relative to the scene bounds' largest extent"""
    approach_reach: float = 0.8
    """shoulder-to-fruit distance at a station, in reaches"""
    floor: str = 'bounds_min_z'
    """the lift stands no lower than the bounds' floor (bounds_min_z) or anywhere (none)"""
    success_margin: float = 0.5
    """success: the tool tip within this many fruit radii of the fruit's surface"""
    wrist_fovy_deg: float = 70.0
    """wrist camera vertical field of view"""
    timestep: float = 0.002
    """MuJoCo timestep (s)"""
    mesh_max_triangles: int = 60000
    """per-class meshes are decimated to at most this many triangles"""
    device: str = 'cpu'
    """device the field is loaded on to bake it: auto | cpu | cuda | cuda:N"""


SECTIONS = {
    SourceSettings.SECTION: SourceSettings,
    OrchardSettings.SECTION: OrchardSettings,
    PlantSettings.SECTION: PlantSettings,
    PosesSettings.SECTION: PosesSettings,
    ImagesSettings.SECTION: ImagesSettings,
    SegmentationSettings.SECTION: SegmentationSettings,
    LabelsSettings.SECTION: LabelsSettings,
    TrainSettings.SECTION: TrainSettings,
    EvaluateSettings.SECTION: EvaluateSettings,
    OccupancySettings.SECTION: OccupancySettings,
    SimSettings.SECTION: SimSettings,
}
