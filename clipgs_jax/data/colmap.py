"""COLMAP sparse models via pycolmap: poses, pinhole intrinsics, points.

pycolmap is imported by the functions that read or undistort a model, so
that the package, and a scene pack (scene.pack), load without it.
"""

import dataclasses
import hashlib
import os
import re
import shutil
import uuid

from absl import logging
import numpy as np

from clipgs_jax.data import colmap_check

# Models that are exactly pinhole when every distortion parameter is zero
# (polynomial radial/tangential terms only; fisheye projections are not).
_POLYNOMIAL_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
_PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")

# An orbit with fewer than this share of its cameras facing the centre of
# the camera positions is folded inside out (BUILD_NOTES.md, "Bonsai poses":
# the shared bonsai model has 0 %, a rebuilt one 100 %); at least
# _FOLD_MIN_VIEWS cameras make the share mean something.
_FOLDED_BELOW = 0.1
_FOLD_MIN_VIEWS = 8

_MODEL_FILES = ("cameras", "images", "points3D")
_FIX = ("re-run COLMAP (mapper or model_converter) to write "
        "sparse/0/{cameras,images,points3D}.bin")


@dataclasses.dataclass(frozen=True)
class Model:
  """A COLMAP model with pinhole cameras; images in natural name order.

  Attributes:
    names: tuple of N str, image names relative to `image_dir`, in
      `natural_key` order (capture order for numbered photos).
    rotations: float64 [N, 3, 3], world-to-camera rotations R.
    translations: float64 [N, 3], world-to-camera translations t.
    intrinsics: float64 [N, 4], (fx, fy, cx, cy) in pixels, COLMAP's
      convention (pixel centres at +0.5), the same as `camera.py`.
    sizes: int64 [N, 2], (width, height) in pixels.
    points: float32 [P, 3], sparse points in world coordinates.
    point_colors: uint8 [P, 3], their RGB colours.
    image_dir: str, folder the image names are relative to (the undistorted
      copy when the source cameras were distorted).
    sparse_dir: str, folder the model was read from.
    undistorted: bool, True if the images were undistorted by pycolmap.
    test_views: the positions in `names` of the capture's own held-out
      views (a transforms.json scene's transforms_test.json), or None.
  """
  names: tuple[str, ...]
  rotations: np.ndarray
  translations: np.ndarray
  intrinsics: np.ndarray
  sizes: np.ndarray
  points: np.ndarray
  point_colors: np.ndarray
  image_dir: str
  sparse_dir: str
  undistorted: bool
  test_views: tuple[int, ...] | None = None


def cache_root() -> str:
  """User cache folder: $CLIPGS_JAX_CACHE, else $XDG_CACHE_HOME/clipgs_jax."""
  if os.environ.get("CLIPGS_JAX_CACHE"):
    return os.environ["CLIPGS_JAX_CACHE"]
  base = os.environ.get("XDG_CACHE_HOME") or os.path.join(
      os.path.expanduser("~"), ".cache")
  return os.path.join(base, "clipgs_jax")


def default_cache_dir(scene_path: str) -> str:
  """Per-scene cache folder, keyed by the scene's real path.

  It lives in the user cache (never inside the scene), so read-only scenes
  work and datasets are never modified.
  """
  real = os.path.realpath(scene_path)
  digest = hashlib.sha1(real.encode()).hexdigest()[:12]
  name = os.path.basename(real.rstrip(os.sep)) or "scene"
  return os.path.join(cache_root(), "scenes", f"{name}-{digest}")


def _attr(obj, name):
  """Value of an attribute that is a method in some pycolmap versions."""
  value = getattr(obj, name)
  return value() if callable(value) else value


def find_sparse_dir(scene_path: str) -> str:
  """The model folder: `sparse/0`, else `sparse` if it holds a model."""
  if not os.path.isdir(scene_path):
    raise FileNotFoundError(f"scene folder not found: {scene_path}")
  for sub in (os.path.join("sparse", "0"), "sparse"):
    folder = os.path.join(scene_path, sub)
    if any(os.path.isfile(os.path.join(folder, f"cameras.{ext}"))
           for ext in ("bin", "txt")):
      return folder
  raise FileNotFoundError(
      f"no COLMAP model in {os.path.join(scene_path, 'sparse', '0')} "
      f"(cameras.bin or cameras.txt missing) and no transforms.json in "
      f"{scene_path}; {_FIX}.")


def read_reconstruction(sparse_dir: str) -> "pycolmap.Reconstruction":
  """Reads a binary (preferred, as COLMAP does) or text model, checked."""
  import pycolmap  # pylint: disable=import-outside-toplevel
  binary = os.path.isfile(os.path.join(sparse_dir, "cameras.bin"))
  ext = "bin" if binary else "txt"
  for name in _MODEL_FILES:
    path = os.path.join(sparse_dir, f"{name}.{ext}")
    if not os.path.isfile(path):
      raise FileNotFoundError(f"COLMAP model file missing: {path}; {_FIX}.")
  if binary:
    colmap_check.check_binary(sparse_dir)
  else:
    colmap_check.check_text(sparse_dir)
  try:
    rec = pycolmap.Reconstruction(sparse_dir)
  except (ValueError, IndexError, RuntimeError, MemoryError) as e:
    msg = " ".join(str(e).split())[:200]
    raise ValueError(f"corrupt COLMAP model in {sparse_dir}: {msg}; "
                     f"{_FIX}.") from None
  return rec


def natural_key(name: str) -> tuple:
  """Sort key that compares runs of digits as numbers: 2.jpg before
  10.jpg, so numbered photos sort in capture order whether or not their
  numbers are zero-padded. On names whose numbers have equal widths (001,
  ..., 184) it is the plain string order; ties (1 and 01) fall back to it.
  """
  parts = re.split(r"(\d+)", name)    # text, digits, text, ...
  return tuple(int(p) if i % 2 else p for i, p in enumerate(parts)), name


def _registered(rec: "pycolmap.Reconstruction") -> list:
  images = []
  for image in rec.images.values():
    # pycolmap >= 3.12 says `has_pose`; older versions said `registered`.
    posed = _attr(image, "has_pose" if hasattr(image, "has_pose")
                  else "registered")
    if posed:
      images.append(image)
  return sorted(images, key=lambda im: natural_key(im.name))


def _pose(image) -> tuple[np.ndarray, np.ndarray]:
  """(R [3, 3], t [3]) world-to-camera, across pycolmap API versions."""
  if hasattr(image, "cam_from_world"):
    rigid = _attr(image, "cam_from_world")
    matrix = np.asarray(_attr(rigid, "matrix"), np.float64)   # [3, 4]
    return matrix[:, :3], matrix[:, 3]
  return (np.asarray(image.rotmat(), np.float64),
          np.asarray(image.tvec, np.float64))


def _needs_undistortion(cam) -> bool:
  """True for distorted cameras; raises for ones that cannot be handled."""
  name = _attr(cam, "model_name") if hasattr(cam, "model_name") else (
      cam.model.name)
  if name in _PINHOLE_MODELS:
    return False
  if hasattr(cam, "is_perspective") and not _attr(cam, "is_perspective"):
    raise ValueError(
        f"camera {cam.camera_id} uses the non-perspective model {name}, "
        "which cannot be undistorted to a pinhole; re-run COLMAP with a "
        "perspective camera model.")
  extra = np.asarray(cam.params)[list(_attr(cam, "extra_params_idxs"))]
  return not (name in _POLYNOMIAL_MODELS and np.all(extra == 0))


def _intrinsics(cam) -> np.ndarray:
  return np.array([_attr(cam, "focal_length_x"), _attr(cam, "focal_length_y"),
                   _attr(cam, "principal_point_x"),
                   _attr(cam, "principal_point_y")], np.float64)


def _check_images_exist(image_dir: str, images) -> None:
  if not os.path.isdir(image_dir) or not os.listdir(image_dir):
    what = "is empty" if os.path.isdir(image_dir) else "does not exist"
    raise FileNotFoundError(
        f"image folder {image_dir} {what} but the COLMAP model lists "
        f"{len(images)} images (e.g. {images[0].name}); put the photos the "
        "model was made from there.")
  for image in images:
    path = os.path.join(image_dir, image.name)
    if not os.path.isfile(path):
      raise FileNotFoundError(
          f"image listed in the COLMAP model is missing: {path}; restore it "
          "or remove it from the model.")


def _fingerprint(paths) -> str:
  parts = []
  for path in paths:
    st = os.stat(path)
    parts.append(f"{os.path.realpath(path)}|{st.st_size}|{st.st_mtime_ns}")
  return hashlib.sha1("\n".join(parts).encode()).hexdigest()[:12]


def _undistort(sparse_dir: str, image_dir: str, names, cache_dir: str) -> str:
  """Undistorted COLMAP workspace (images/ + sparse/) in the cache.

  Keyed by the model files, so a changed model is undistorted again. Built
  in a temp folder and renamed into place, so a crash never leaves a
  half-written copy that later runs would trust.
  """
  import pycolmap  # pylint: disable=import-outside-toplevel
  model_files = sorted(os.path.join(sparse_dir, f)
                       for f in os.listdir(sparse_dir)
                       if f.endswith((".bin", ".txt")))
  key = _fingerprint(model_files + [image_dir])
  final = os.path.join(cache_dir, f"undistorted-{key}")
  if os.path.isdir(os.path.join(final, "sparse")):
    return final
  os.makedirs(cache_dir, exist_ok=True)
  tmp = os.path.join(cache_dir, f".tmp-undistort-{os.getpid()}-"
                     f"{uuid.uuid4().hex[:8]}")
  level = pycolmap.logging.minloglevel
  try:
    # COLMAP logs one INFO line per image; keep warnings and errors.
    pycolmap.logging.minloglevel = 1
    pycolmap.undistort_images(tmp, sparse_dir, image_dir,
                              image_names=list(names), jpeg_quality=100)
  except Exception as e:  # pylint: disable=broad-except
    shutil.rmtree(tmp, ignore_errors=True)
    msg = " ".join(str(e).split())[:200]
    raise ValueError(f"pycolmap could not undistort {sparse_dir} into "
                     f"{cache_dir}: {msg}; undistort the scene with "
                     "`colmap image_undistorter` and load that.") from None
  finally:
    pycolmap.logging.minloglevel = level
  for name in names:
    # pycolmap logs and skips images it cannot read; never cache that.
    if not os.path.isfile(os.path.join(tmp, "images", name)):
      shutil.rmtree(tmp, ignore_errors=True)
      raise ValueError(f"pycolmap could not undistort "
                       f"{os.path.join(image_dir, name)} (unreadable "
                       "image?); replace it or remove it from the model.")
  # Only images/ and sparse/ are needed; the dense-stereo stubs are not.
  shutil.rmtree(os.path.join(tmp, "stereo"), ignore_errors=True)
  for f in os.listdir(tmp):
    if f.endswith(".sh"):
      os.remove(os.path.join(tmp, f))
  try:
    os.rename(tmp, final)
  except OSError:
    # Another process finished the same undistortion first; use its copy.
    shutil.rmtree(tmp, ignore_errors=True)
    if not os.path.isdir(os.path.join(final, "sparse")):
      raise
  return final


def poses(images) -> tuple[np.ndarray, np.ndarray]:
  """World-to-camera R [N, 3, 3] and t [N, 3] of posed pycolmap images."""
  pairs = [_pose(im) for im in images]
  return np.stack([r for r, _ in pairs]), np.stack([t for _, t in pairs])


def centers_and_axes(rotations: np.ndarray, translations: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
  """Camera centres -R^T t [N, 3] and unit optical axes R^T e_z [N, 3] in
  world space, from world-to-camera poses."""
  return (-np.einsum("nji,nj->ni", rotations, translations),
          rotations[:, 2, :])


def facing_fraction(centers: np.ndarray, axes: np.ndarray) -> float:
  """Share of cameras whose optical axis points towards the centre of the
  camera positions: ~1 for an object-centred orbit, ~0 when it is folded
  inside out (not meaningful for forward-facing or panorama captures)."""
  to_mid = centers.mean(axis=0) - centers
  return float(np.mean(np.sum(axes * to_mid, axis=1) > 0))


def fold_warning(rotations: np.ndarray, translations: np.ndarray,
                 where: str) -> str | None:
  """A warning when a model with world-to-camera poses (R [N, 3, 3], t
  [N, 3]) looks like an orbit folded inside out, else None.

  A fold keeps every reprojection error low, so nothing else catches it,
  and training on it ends far below the rebuilt model (bonsai at ds8,
  1,000 steps: 17.6 against 23.5 dB). Forward-facing captures sit near
  half and are left alone."""
  if len(rotations) < _FOLD_MIN_VIEWS:
    return None
  share = facing_fraction(*centers_and_axes(rotations, translations))
  if share >= _FOLDED_BELOW:
    return None
  return (f"{where}: {share:.0%} of the {len(rotations)} cameras face the "
          "centre of the camera positions; if the photos orbit an object, "
          "this model is folded inside out and will train to a blur. "
          "Rebuild its poses: python experiments/prepare.py "
          "--prepare=reconstruct --images=PHOTOS --out=NEW_SCENE")


def load_model(scene_path: str, cache_dir: str | None = None,
               image_folder: str = "images") -> Model:
  """Reads `<scene>/sparse/0` and returns pinhole cameras and points.

  SIMPLE_PINHOLE (fx = fy = f) and PINHOLE are used as they are, as are the
  polynomial models when all their distortion terms are exactly zero. Other
  cameras are undistorted once with pycolmap.undistort_images into
  `cache_dir` (default `default_cache_dir(scene_path)`), and the undistorted
  PINHOLE model and images are returned instead: a distorted camera is never
  treated as a pinhole.

  Args:
    scene_path: str, folder with `images/` and `sparse/0/` (binary or text).
    cache_dir: str or None, writable per-scene cache folder.
    image_folder: str, image folder name inside the scene.

  Returns:
    A `Model`; only images with a pose (registered) are included.
  """
  sparse_dir = find_sparse_dir(scene_path)
  rec = read_reconstruction(sparse_dir)
  images = _registered(rec)
  if not images:
    raise ValueError(f"COLMAP model {sparse_dir} has no registered images "
                     "(empty model?); " + _FIX + ".")
  image_dir = os.path.join(scene_path, image_folder)
  _check_images_exist(image_dir, images)
  undistorted = any(_needs_undistortion(rec.cameras[im.camera_id])
                    for im in images)
  if undistorted:
    cache_dir = cache_dir or default_cache_dir(scene_path)
    workspace = _undistort(sparse_dir, image_dir, [im.name for im in images],
                           cache_dir)
    sparse_dir = os.path.join(workspace, "sparse")
    image_dir = os.path.join(workspace, "images")
    rec = read_reconstruction(sparse_dir)
    images = _registered(rec)
    for im in images:
      if _needs_undistortion(rec.cameras[im.camera_id]):
        raise ValueError(f"{sparse_dir}: camera {im.camera_id} is still "
                         "distorted after undistortion; delete the cache "
                         f"folder {workspace} and retry.")
    _check_images_exist(image_dir, images)
  rotations, translations = poses(images)
  warning = fold_warning(rotations, translations, sparse_dir)
  if warning:
    logging.warning(warning)
  cams = [rec.cameras[im.camera_id] for im in images]
  ids = sorted(rec.points3D)
  points = np.array([rec.points3D[i].xyz for i in ids],
                    np.float32).reshape(-1, 3)
  colors = np.array([rec.points3D[i].color for i in ids],
                    np.uint8).reshape(-1, 3)
  return Model(
      names=tuple(im.name for im in images),
      rotations=rotations, translations=translations,
      intrinsics=np.stack([_intrinsics(c) for c in cams]),
      sizes=np.array([[c.width, c.height] for c in cams], np.int64),
      points=points, point_colors=colors, image_dir=image_dir,
      sparse_dir=sparse_dir, undistorted=undistorted)
