"""Scenes to train on: poses for a folder of photos, a transient benchmark,
or a scene packed into one file.

  python experiments/prepare.py --prepare=reconstruct --images=DIR --out=DIR
      [--camera_model=SIMPLE_RADIAL] [--nosingle_camera]
  python experiments/prepare.py --prepare=benchmark --clean_scene=COLMAP_DIR
      --distractors=PHOTO_DIR --out=DIR --seed=S
      [--mode=independent|persistent] [--persist_views=5] [--fraction=0.5]
      [--per_view=1..3] [--overwrite] [--cache_dir=DIR]
  python experiments/prepare.py --prepare=pack --scene_folder=DIR
      --downscale=K --out=FILE.npz [--cache_dir=DIR]

reconstruct: SfM with pycolmap's global mapper (clipgs_jax/data/
  reconstruct.py); DIR gets database.db, sparse/0 and images -> --images,
  so it is a scene for train.py --scene=DIR. The summary says how many
  cameras face the centre of the camera positions (a folded orbit: ~0 %).
benchmark: a RobustNeRF-layout transient benchmark from a static scene
  (layout, modes, determinism: clipgs_jax/data/transients.py). Photo
  categories (person / clutter) come from PHOTO_DIR/person/ and
  PHOTO_DIR/clutter/, or PHOTO_DIR/categories.txt with one `CATEGORY NAME`
  per line, or the file names of ../shared/data/distractors.
pack: the scene's loaded arrays at downscale K (cameras, 16-bit images,
  masks, points; both train splits of a benchmark) in one compressed .npz,
  bit for bit what train.py loads from DIR; pass it as --scene=FILE.npz
  with --config.data.downscale=K. It needs neither pycolmap nor the image
  files, e.g. to train on a machine that has neither.
A bad input ends in one line on stderr; nothing is left in --out.
"""

import os
import time

from absl import flags

from clipgs_jax import cli
from clipgs_jax.data import reconstruct
from clipgs_jax.data import scene as scene_lib
from clipgs_jax.data import transients

_PREPARE = flags.DEFINE_enum("prepare", None,
                             ["reconstruct", "benchmark", "pack"],
                             "What to make.")
_OUT = flags.DEFINE_string("out", None, "Output scene folder (reconstruct: "
                           "without a sparse/ model yet; benchmark: absent "
                           "or empty unless --overwrite), or pack: the "
                           ".npz file.")
_IMAGES = flags.DEFINE_string("images", None, "reconstruct: folder of "
                              "photos.")
_CAMERA_MODEL = flags.DEFINE_string("camera_model", "SIMPLE_RADIAL",
                                    "reconstruct: COLMAP camera model.")
_SINGLE_CAMERA = flags.DEFINE_bool(
    "single_camera", True, "reconstruct: one set of intrinsics shared by "
    "every photo (one camera, fixed zoom).")
_CLEAN_SCENE = flags.DEFINE_string("clean_scene", None, "benchmark: COLMAP "
                                   "scene (images/, sparse/0/) without "
                                   "transients.")
_DISTRACTORS = flags.DEFINE_string(
    "distractors", None, "benchmark: photos to paste (person/ and clutter/ "
    "subfolders, or categories.txt).")
_SEED = flags.DEFINE_integer("seed", None, "benchmark: random seed (>= 0).")
_MODE = flags.DEFINE_enum(
    "mode", "independent", list(transients.MODES), "benchmark: independent: "
    "2D pastes, new in every view; persistent: 3D billboards seen by runs "
    "of --persist_views views.")
_PERSIST_VIEWS = flags.DEFINE_integer(
    "persist_views", transients.DEFAULT_PERSIST_VIEWS, "benchmark: "
    "consecutive training views per billboard (--mode=persistent).")
_FRACTION = flags.DEFINE_float("fraction", 0.5, "benchmark: fraction of "
                               "training views (runs, when persistent) with "
                               "transients, in [0, 1].")
_PER_VIEW = flags.DEFINE_string("per_view", "1..3", "benchmark: photos per "
                                "cluttered view (billboards per run): an "
                                "integer or a range A..B.")
_OVERWRITE = flags.DEFINE_bool("overwrite", False,
                               "benchmark: replace a non-empty --out.")
_CACHE_DIR = flags.DEFINE_string("cache_dir", None, "benchmark, pack: "
                                 "undistortion and resize cache of the "
                                 "input scene.")
_SCENE_FOLDER = flags.DEFINE_string("scene_folder", None, "pack: the scene "
                                    "folder (sparse/0/ or transforms.json).")
_BACKGROUND = flags.DEFINE_enum(
    "background", "white", list(scene_lib.BACKGROUNDS), "pack: the colour "
    "behind photos with alpha (train.py's --config.data.background).")
_DOWNSCALE = flags.DEFINE_integer("downscale", None, "pack: image downscale "
                                  "factor K (train.py's "
                                  "--config.data.downscale).")
flags.mark_flags_as_required(["prepare", "out"])


def _reconstruct() -> None:
  cli.require(_IMAGES.value is not None, "images", None,
              "is needed: pass the folder of photos")
  # A failed reconstruction leaves no --out (or only what was there).
  with cli.output_dir(_OUT.value, keep="sparse"):
    rec = reconstruct.reconstruct(_IMAGES.value, _OUT.value,
                                  _CAMERA_MODEL.value, _SINGLE_CAMERA.value)
  print(reconstruct.summary(rec))
  print(f"scene ready: python experiments/train.py --scene={_OUT.value}")


def _benchmark() -> None:
  for flag in (_CLEAN_SCENE, _DISTRACTORS, _SEED):
    cli.require(flag.value is not None, flag.name, None,
                "is needed for --prepare=benchmark")
  tic = time.perf_counter()
  manifest = transients.build(
      _CLEAN_SCENE.value, _DISTRACTORS.value, _OUT.value, _SEED.value,
      fraction=_FRACTION.value, per_view=_PER_VIEW.value,
      overwrite=_OVERWRITE.value, cache_dir=_CACHE_DIR.value,
      mode=_MODE.value, persist_views=_PERSIST_VIEWS.value)
  counts = ", ".join(f"{n} {c}" for c, n in
                     sorted(manifest["transients_by_category"].items()))
  boards = (f", {transients.billboard_summary(manifest)}"
            if "billboards" in manifest else "")
  print(f"wrote {_OUT.value} ({manifest['mode']}): {manifest['num_train']} "
        f"training views ({manifest['num_cluttered']} cluttered; "
        f"transients: {counts or 'none'}{boards}), {manifest['num_test']} "
        f"test views, in {time.perf_counter() - tic:.1f} s")


def _pack() -> None:
  for flag in (_SCENE_FOLDER, _DOWNSCALE):
    cli.require(flag.value is not None, flag.name, None,
                "is needed for --prepare=pack")
  cli.require(_OUT.value.endswith(scene_lib.PACK_SUFFIX), "out", _OUT.value,
              f"must be a file name ending in {scene_lib.PACK_SUFFIX}")
  cli.require_folder("scene_folder", _SCENE_FOLDER.value)
  tic = time.perf_counter()
  splits = scene_lib.pack(_SCENE_FOLDER.value, _OUT.value, _DOWNSCALE.value,
                          cache_dir=_CACHE_DIR.value,
                          background=_BACKGROUND.value)
  size = os.path.getsize(_OUT.value) / 2**20
  print(f"wrote {_OUT.value} ({size:.1f} MiB; train splits: "
        f"{', '.join(splits) or 'one, no RobustNeRF names'}) in "
        f"{time.perf_counter() - tic:.1f} s; train on it with "
        f"--scene={_OUT.value} --config.data.downscale={_DOWNSCALE.value}")


def main(argv):
  cli.no_arguments(argv)
  {"reconstruct": _reconstruct, "benchmark": _benchmark,
   "pack": _pack}[_PREPARE.value]()


if __name__ == "__main__":
  cli.run(main)
