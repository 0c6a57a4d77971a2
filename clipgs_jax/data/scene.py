"""Scenes for training: poses (COLMAP or transforms.json), images, masks
and the train/test split."""

import dataclasses
import os
from typing import Callable

import jax
import numpy as np

from clipgs_jax import camera
from clipgs_jax import config as config_lib
from clipgs_jax import fileio
from clipgs_jax.data import canvas
from clipgs_jax.data import colmap
from clipgs_jax.data import images
from clipgs_jax.data import splits
from clipgs_jax.data import transforms

TRAIN_SPLITS = splits.TRAIN_SPLITS     # the values of data.train_split
# 3DGS's "cameras_extent": camera-centre radius with a 10% margin.
EXTENT_MARGIN = 1.1
MASK_THRESHOLD = 0.5
# The colour behind the subject of photos with an alpha channel
# (data.background): white, as the evaluations of the Blender scenes use,
# or black. The run renders onto it too (run.py).
BACKGROUNDS = config_lib.BACKGROUNDS
# Smallest image side: the SSIM window (losses.SSIM_WINDOW); the test
# metrics' SSIM needs one full window inside the image.
MIN_IMAGE_SIDE = 11
# A packed scene (`pack`) is one .npz file of a scene's loaded arrays at one
# downscale; `load_scene` reads it in place of the folder, without pycolmap
# or image decoding (e.g. on a GPU machine that has neither).
PACK_SUFFIX = ".npz"
# Format 2: masks cover every partly transient pixel (format-1 packs hold the
# masks of the old area >= 0.5 rule).
PACK_FORMAT = "clipgs_jax scene pack 2"
# Loaded images are 16-bit codes (images.load_image quantises them; 8-bit
# files are k / 255 = 257 k / 65535), so a pack stores uint16 exactly.
_CODES = 65535
_CAMERA_FIELDS = ("rotation", "translation", "fx", "fy", "cx", "cy")


@dataclasses.dataclass(frozen=True)
class Views:
  """Views of one split on one canvas.

  Attributes:
    cameras: camera.Camera whose array fields have a leading [V] axis
      (rotation [V, 3, 3], translation [V, 3], fx/fy/cx/cy [V]); width and
      height are the canvas's, shared by all views.
    images: float32 [V, H, W, 3] in [0, 1].
    names: tuple of V str, image names (COLMAP names), in
      colmap.natural_key order.
    masks: bool [V, H, W], True = transient pixel; None when the scene has
      no masks (test views never have masks).
    sizes: int32 [V, 2], each photo's width and height when some photo
      does not fill the canvas (photos of different sizes): each lies in
      the top-left corner of the H x W canvas, zero (and not transient)
      outside it. None when every photo fills it.
    ids: int [V], each view's position among all views of its split; None
      means 0..V-1. A process of a multi-host run holds only its own
      training views (load_scene's `train_views`).
  """
  cameras: camera.Camera
  images: np.ndarray
  names: tuple[str, ...]
  masks: np.ndarray | None
  sizes: np.ndarray | None = None
  ids: np.ndarray | None = None

  def __len__(self) -> int:
    return len(self.names)


@dataclasses.dataclass(frozen=True)
class Scene:
  """A loaded scene.

  Attributes:
    train, test: Views.
    points: float32 [P, 3], sparse SfM points (P may be 0).
    point_colors: float32 [P, 3] in [0, 1].
    extent: float, radius of the training camera centres around their mean,
      times 1.1 (3DGS's cameras_extent); scales learning rates and
      densification thresholds.
    path: str, the scene folder (or its pack file).
    train_cameras: every training camera (stacked), when `train` holds
      only some of the training views (a process of a multi-host run);
      None: train.cameras. For poses: the intrinsics of the views not held
      are scaled to images.downscaled_size without reading their photos.
    background: (r, g, b), the BACKGROUNDS colour the photos with an alpha
      channel were composited onto; None when no photo has one.
  """
  train: Views
  test: Views
  points: np.ndarray
  point_colors: np.ndarray
  extent: float
  path: str
  train_cameras: camera.Camera | None = None
  background: tuple[float, float, float] | None = None


def all_train_cameras(scene) -> camera.Camera:
  """Every training camera of `scene` (stacked), held or not."""
  cams = getattr(scene, "train_cameras", None)
  return scene.train.cameras if cams is None else cams


def subset(views: Views, ids) -> Views:
  """The views at positions `ids` of `views`, on the same canvas (`ids`
  records where they came from)."""
  ids = np.asarray(ids, np.int64)
  take = lambda x: None if x is None else np.asarray(x)[ids]
  return Views(cameras=jax.tree.map(lambda x: np.asarray(x)[ids],
                                    views.cameras),
               images=views.images[ids],
               names=tuple(views.names[i] for i in ids),
               masks=take(views.masks), sizes=take(views.sizes),
               ids=ids if views.ids is None else views.ids[ids])


def _mask_path(scene_path: str, name: str) -> str:
  stem = os.path.splitext(name)[0]
  return os.path.join(scene_path, "masks", stem + ".png")


def _load_views(model: colmap.Model, idx, scene_path: str, downscale: int,
                cache_dir: str, with_masks: bool, keep=None,
                background=None) -> Views:
  """Reads the images (and masks) of the views `idx` of `model`; with
  `keep` (a set of positions in idx) only those views; an alpha channel
  is composited onto `background` (see images.read_image)."""
  prescaled_dir = None
  if downscale > 1 and not model.undistorted:
    # RobustNeRF-style pre-scaled copies; for distorted scenes they are
    # distorted too, so the undistorted images are resized instead.
    prescaled_dir = os.path.join(scene_path, f"images_{downscale}")
    if not os.path.isdir(prescaled_dir):
      prescaled_dir = None
  resize_cache = os.path.join(cache_dir, f"images_{downscale}")
  ids = [k for k in range(len(idx)) if keep is None or k in keep]
  imgs, cams = [], []
  for i in (idx[k] for k in ids):
    name = model.names[i]
    src = os.path.join(model.image_dir, name)
    size = tuple(int(s) for s in model.sizes[i])
    prescaled = None
    if prescaled_dir is not None:
      prescaled = os.path.join(prescaled_dir, name)
      if not os.path.isfile(prescaled):
        raise FileNotFoundError(
            f"{prescaled} is missing although {prescaled_dir} exists; add "
            "it, or delete the folder to resize from images/.")
    image = images.load_image(src, factor=downscale, expected_size=size,
                              cache_dir=resize_cache,
                              prescaled_path=prescaled, background=background)
    h, w = image.shape[:2]
    if min(w, h) < MIN_IMAGE_SIDE:
      raise ValueError(
          f"{src} gives a {w}x{h} image at downscale {downscale}; views need "
          f"at least {MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE} pixels (one SSIM "
          "window); use a smaller --config.data.downscale or larger images.")
    cams.append(_camera(model, i, w, h))
    imgs.append(image)
  names = tuple(model.names[idx[k]] for k in ids)
  sizes = canvas.canvas_sizes([(c.width, c.height) for c in cams],
                              f"the views of {model.sparse_dir}")
  masks = _load_masks(scene_path, names, downscale,
                      [im.shape[:2] for im in imgs],
                      sizes) if with_masks else None
  return Views(cameras=_stack(cams), images=canvas.on_canvas(imgs, sizes),
               names=names, masks=masks, sizes=sizes,
               ids=None if keep is None else np.asarray(ids))


def _load_masks(scene_path, names, downscale, shapes, sizes):
  """bool [V, H, W] on the views' canvas (`sizes`, canvas.on_canvas), or None
  if `masks/` has none of these views' masks.

  A mask is binarised at its full resolution (grey >= MASK_THRESHOLD), and a
  downscaled pixel is transient where *any* of its source pixels is: loss
  masking must not fit a pixel that is partly transient. (Thresholding the
  area-averaged mask at 0.5 left each transient's border pixels unmasked;
  on bird_persistent_f1.0 at downscale 8 that was 0.32 % of the transients'
  squared difference to the clean photos, against 0.007 % with this rule,
  and a 5,000-step loss-masked run fitted those borders into visible
  outlines: BUILD_NOTES.md, "Localized evidence".)
  """
  paths = [_mask_path(scene_path, n) for n in names]
  present = [os.path.isfile(p) for p in paths]
  if not any(present):
    return None
  if not all(present):
    missing = paths[present.index(False)]
    raise FileNotFoundError(
        f"mask {missing} is missing although other training views have "
        "masks; add it (white = transient) or remove the masks/ folder.")
  masks = []
  for path, (height, width) in zip(paths, shapes):
    full = images.read_image(path).mean(axis=-1) >= MASK_THRESHOLD
    if images.downscaled_size(full.shape[1], full.shape[0],
                              downscale) != (width, height):
      raise ValueError(f"mask {path} is {full.shape[1]}x{full.shape[0]} "
                       f"pixels, which gives no {width}x{height} image at "
                       f"downscale {downscale}; make it its image's size.")
    masks.append(images.resize_area(full, width, height) > 0)
  return canvas.on_canvas(masks, sizes, fill=False)


def _extent(cameras: camera.Camera) -> float:
  centres = camera.camera_center(cameras)
  radius = np.linalg.norm(centres - centres.mean(axis=0), axis=-1).max()
  # One camera (or coincident ones) has no spread; use unit scale instead
  # of scaling every learning rate to zero.
  return float(EXTENT_MARGIN * (radius if radius > 1e-8 else 1.0))


def load_scene(path: str, downscale: int = 1, train_split: str = "clutter",
               cache_dir: str | None = None,
               train_views: Callable[[int], bool] | None = None,
               background: str = "white") -> Scene:
  """Loads a scene (COLMAP, transforms.json, or a pack, see `pack`) with its
  train/test split.

  Splits: a transforms scene with transforms_test.json tests on its
  frames; with RobustNeRF names (`clutter`, `extra`, `clean` in the image
  names) the test views are `extra` and the training views are
  `train_split` (`clutter`, or `clean` for the clean upper bound); otherwise
  every 8th image by name (0, 8, 16, ...; in colmap.natural_key order) is a
  test view and `train_split` is ignored. Masks are read from
  `masks/<stem>.png` (white = transient) for the training views when
  present.

  Args:
    path: str, scene folder with `images/` and `sparse/0/`, or with
      transforms.json / transforms_train.json (data/transforms.py), or a
      `.npz` file written by `pack` (it must hold `downscale` and, for
      photos with alpha, `background`; `cache_dir` unused).
    downscale: int, image downscale factor K (uses `images_K/` if present).
    train_split: str, "clutter" or "clean" (RobustNeRF scenes only).
    cache_dir: str or None, writable folder for undistorted and resized
      images; default `colmap.default_cache_dir(path)`.
    train_views: None (all), or which training views to hold, by position
      among the training views: a process of a multi-host run reads only
      its own views' photos (Scene.train_centers keeps every camera).
    background: str, a BACKGROUNDS name: the colour photos with an alpha
      channel are composited onto.

  Returns:
    A `Scene`.
  """
  images.downscaled_size(1, 1, downscale)      # validates the factor
  if train_split not in TRAIN_SPLITS:
    raise ValueError(f"train_split must be one of {TRAIN_SPLITS}, got "
                     f"{train_split!r}.")
  check_background(background)
  if path.endswith(PACK_SUFFIX):
    return _load_pack(path, downscale, train_split, train_views, background)
  cache_dir = cache_dir or colmap.default_cache_dir(path)
  return _load_folder(_load_model(path, cache_dir), path, downscale,
                      train_split, cache_dir, train_views, background)


def check_background(background: str) -> None:
  """Raises ValueError unless `background` names a BACKGROUNDS colour."""
  if background not in BACKGROUNDS:
    raise ValueError(f"--config.data.background={background} is not one of "
                     f"{', '.join(BACKGROUNDS)} (the colour behind photos "
                     "with an alpha channel).")


def _load_model(path: str, cache_dir: str) -> colmap.Model:
  """The scene folder's cameras: transforms.json if it has one, else its
  COLMAP model."""
  if os.path.isdir(path) and transforms.files(path) is not None:
    return transforms.load_model(path)
  return colmap.load_model(path, cache_dir=cache_dir)


def _load_folder(model: colmap.Model, path: str, downscale: int,
                 train_split: str, cache_dir: str,
                 train_views: Callable[[int], bool] | None,
                 background: str) -> Scene:
  """`load_scene` of the folder scene `path` whose model is `model`."""
  train_idx, test_idx = splits.split(model.names, train_split,
                                     model.sparse_dir, model.test_views)
  keep = None if train_views is None else {
      k for k in range(len(train_idx)) if train_views(k)}
  rgba = any(images.has_alpha(os.path.join(model.image_dir, name))
             for name in model.names)
  colour = BACKGROUNDS[background] if rgba else None
  train = _load_views(model, train_idx, path, downscale, cache_dir,
                      with_masks=True, keep=keep, background=colour)
  test = _load_views(model, test_idx, path, downscale, cache_dir,
                     with_masks=False, background=colour)
  cams = train.cameras if keep is None else _poses(model, train_idx,
                                                    downscale)
  return Scene(train=train, test=test, points=model.points,
               point_colors=model.point_colors.astype(np.float32) / 255,
               extent=_extent(cams), path=path,
               train_cameras=None if keep is None else cams,
               background=colour)


def _poses(model: colmap.Model, idx, downscale: int) -> camera.Camera:
  """The stacked cameras of the views `idx` without reading their photos
  (Scene.train_cameras): intrinsics scaled to images.downscaled_size."""
  return _stack([_camera(model, i, *images.downscaled_size(
      *(int(s) for s in model.sizes[i]), downscale)) for i in idx])


def _camera(model: colmap.Model, i: int, w: int, h: int) -> camera.Camera:
  """View i of `model` with its photo at w x h. Pixel centres at +0.5 in
  both grids make continuous image coordinates scale uniformly, so fx, cx
  (fy, cy) scale by w / W (h / H)."""
  sx, sy = w / model.sizes[i][0], h / model.sizes[i][1]
  fx, fy, cx, cy = model.intrinsics[i]
  return camera.Camera.create(model.rotations[i], model.translations[i],
                              fx * sx, fy * sy, cx * sx, cy * sy, w, h)


def _stack(cams: list[camera.Camera]) -> camera.Camera:
  """One Camera with a leading [V] axis, on the views' common canvas."""
  return camera.Camera(
      **{k: np.stack([getattr(c, k) for c in cams]) for k in _CAMERA_FIELDS},
      width=max(c.width for c in cams), height=max(c.height for c in cams))


def _views_arrays(prefix: str, views: Views) -> dict[str, np.ndarray]:
  codes = np.round(views.images * _CODES).astype(np.uint16)
  if not np.array_equal(codes.astype(np.float32) / np.float32(_CODES),
                        views.images):
    raise ValueError(f"{prefix} images are not 16-bit codes, so a pack "
                     "would change them; load them with images.load_image.")
  out = {f"{prefix}.{k}": np.asarray(getattr(views.cameras, k))
         for k in _CAMERA_FIELDS}
  out[f"{prefix}.size"] = np.array([views.cameras.width,
                                    views.cameras.height])
  if views.sizes is not None:
    out[f"{prefix}.sizes"] = views.sizes
  out[f"{prefix}.images"] = codes
  out[f"{prefix}.names"] = np.array(views.names, dtype=str)
  if views.masks is not None:
    out[f"{prefix}.masks"] = views.masks
  return out


def pack(path: str, out: str, downscale: int,
         cache_dir: str | None = None, background: str = "white"
         ) -> tuple[str, ...]:
  """Writes the folder scene `path` at `downscale` as one .npz file `out`.

  The file holds what `load_scene` returns for every train split the scene
  has (both for a RobustNeRF benchmark, whose clean upper bound reads
  `clean`), bit for bit; `load_scene(out, downscale, split)` gives it back
  without pycolmap or image files. Photos with an alpha channel are
  packed composited onto `background` (a BACKGROUNDS name), which a load
  of the pack must ask for. Written atomically, compressed.

  Returns:
    The RobustNeRF train splits packed; () for a scene without them.
  """
  if not out.endswith(PACK_SUFFIX):
    raise ValueError(f"pack output {out} must end in {PACK_SUFFIX}.")
  images.downscaled_size(1, 1, downscale)      # validates the factor
  check_background(background)
  cache_dir = cache_dir or colmap.default_cache_dir(path)
  model = _load_model(path, cache_dir)   # read once
  named = splits.train_splits(model.names)
  arrays = {"format": np.array(PACK_FORMAT), "downscale": np.array(downscale),
            "splits": np.array(named, dtype=str)}
  for split in named or TRAIN_SPLITS[:1]:
    scene = _load_folder(model, path, downscale, split, cache_dir, None,
                         background)
    arrays |= _views_arrays(f"train.{split if named else 'all'}",
                            scene.train)
  arrays |= _views_arrays("test", scene.test)
  arrays |= {"points": scene.points, "point_colors": scene.point_colors}
  if scene.background is not None:
    arrays["background"] = np.array(background)
  fileio.atomic_write(out, lambda tmp: np.savez_compressed(tmp, **arrays),
                      PACK_SUFFIX)
  return named


def _read_views(data, prefix: str, path: str) -> Views:
  width, height = (int(v) for v in data[f"{prefix}.size"])
  cameras = camera.Camera(**{k: data[f"{prefix}.{k}"] for k in _CAMERA_FIELDS},
                          width=width, height=height)
  for i in range(len(cameras.fx)):
    camera.validate(camera.Camera(
        **{k: getattr(cameras, k)[i] for k in _CAMERA_FIELDS},
        width=width, height=height), f"{path}: {prefix} camera {i}")
  masks = data.get(f"{prefix}.masks")
  sizes = data.get(f"{prefix}.sizes")
  return Views(
      cameras=cameras,
      images=data[f"{prefix}.images"].astype(np.float32) / np.float32(_CODES),
      names=tuple(str(n) for n in data[f"{prefix}.names"]),
      masks=None if masks is None else masks.astype(bool),
      sizes=None if sizes is None else sizes.astype(np.int32))


def _load_pack(path: str, downscale: int, train_split: str,
               train_views: Callable[[int], bool] | None,
               background: str) -> Scene:
  """The Scene that `pack` wrote to `path`."""
  if not os.path.isfile(path):
    raise FileNotFoundError(f"scene pack {path} does not exist; write it with "
                            "experiments/prepare.py --prepare=pack.")
  try:
    with np.load(path) as npz:
      data = {k: npz[k] for k in npz.files}
  except Exception as e:  # zipfile, pickle and format errors alike
    raise ValueError(f"{path} cannot be read as a scene pack ({e}); write it "
                     "again with experiments/prepare.py --prepare=pack.") from e
  if str(data.get("format", "")) != PACK_FORMAT:
    raise ValueError(f"{path} is not a scene pack ({PACK_FORMAT!r}); write "
                     "it with experiments/prepare.py --prepare=pack.")
  packed = int(data["downscale"])
  if packed != downscale:
    raise ValueError(f"scene pack {path} holds downscale {packed}, not "
                     f"{downscale}; pass --config.data.downscale={packed} or "
                     f"pack the scene again with --downscale={downscale}.")
  packed_splits = tuple(str(s) for s in data["splits"])
  if packed_splits and train_split not in packed_splits:
    raise ValueError(f"scene pack {path} has the train split(s) "
                     f"{packed_splits}, "
                     f"not {train_split!r}; pack a scene that has it.")
  packed_background = data.get("background")
  if packed_background is not None and str(packed_background) != background:
    raise ValueError(f"scene pack {path} holds photos composited onto "
                     f"{packed_background}, not {background}; pass "
                     f"--config.data.background={packed_background} or pack "
                     f"the scene again with --background={background}.")
  # Without RobustNeRF names train_split is ignored, as for the folder.
  train = _read_views(
      data, f"train.{train_split if packed_splits else 'all'}", path)
  cams = train.cameras
  if train_views is not None:
    train = subset(train, [k for k in range(len(train)) if train_views(k)])
  return Scene(train=train, test=_read_views(data, "test", path),
               points=data["points"], point_colors=data["point_colors"],
               extent=_extent(cams), path=path,
               train_cameras=None if train_views is None else cams,
               background=None if packed_background is None
               else BACKGROUNDS[background])
