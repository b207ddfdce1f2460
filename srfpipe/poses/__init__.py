"""Camera poses: import a capture (nerfstudio | blender | colmap | llff | orchard), bound it, refine it.

Modules, and the one direction imports flow in (a module imports only from those above it):

* `capture`: the imported `Capture` and the checked helpers every importer shares.
* `bounds`: scene bounds (config | ground truth | sparse points | camera frusta).
* `align`: pose perturbation, similarity alignment of camera sets, pose errors.
* `nerfstudio`, `blender`, `colmap`, `llff`: one importer per format; `ground_truth`: the built-in
  captures' `ground_truth/` folder.
* `colmap_refine`: COLMAP triangulation + bundle adjustment of the imported poses.
* `stage`: the `poses` stage (`srfpipe poses`): dispatch, refinement, `poses.zarr`.

The names below are re-exported so that `from srfpipe.poses import read_nerfstudio` works; no
module of the package imports from this one, so re-exporting the stage creates no cycle.
"""

from srfpipe.poses.align import align_poses, perturb_poses, pose_errors, similarity_align
from srfpipe.poses.blender import read_blender
from srfpipe.cameras import focus_point
from srfpipe.poses.bounds import bounds_from_frusta, bounds_from_points, resolve_bounds
from srfpipe.poses.capture import Capture, validate_capture
from srfpipe.poses.colmap import colmap_camera_parameters, read_colmap
from srfpipe.poses.ground_truth import attach_ground_truth
from srfpipe.poses.llff import read_llff
from srfpipe.poses.nerfstudio import read_nerfstudio
from srfpipe.poses.stage import FORMATS, import_poses, load_capture

__all__ = [
    "FORMATS", "Capture", "align_poses", "attach_ground_truth", "bounds_from_frusta", "bounds_from_points",
    "colmap_camera_parameters", "focus_point", "import_poses", "load_capture", "perturb_poses", "pose_errors",
    "read_blender", "read_colmap", "read_llff", "read_nerfstudio", "resolve_bounds", "similarity_align",
    "validate_capture",
]
