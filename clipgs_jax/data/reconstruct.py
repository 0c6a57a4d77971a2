"""Camera poses and SfM points for a folder of photos, with pycolmap.

SIFT features, exhaustive matching and *global* mapping (pycolmap's GLOMAP
pipeline), seeded. The scene folder gets database.db, sparse/0 and a
symlink images -> the photos, so it loads like any COLMAP scene
(distorted camera models are undistorted by the loader).

Why global mapping: on the shared 98-frame bonsai orbit, incremental
mapping folds the loop and returns cameras that look *away* from the
object they all photograph; global mapping recovers the orbit (numbers in
BUILD_NOTES.md, "Bonsai poses"). `colmap.facing_fraction` is the quick
check that caught it, and the loader warns on such a model.
"""

import os
import shutil
import time

from absl import logging
import numpy as np
import pycolmap

from clipgs_jax.data import colmap

SEED = 0   # feature matching RANSAC and the global mapper
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff")


def check_inputs(image_dir: str, scene_dir: str, camera_model: str
                 ) -> list[str]:
  """Photo names in `image_dir`; ValueError naming the problem otherwise."""
  if not os.path.isdir(image_dir):
    raise ValueError(f"--images={image_dir}: no such folder; pass the folder "
                     "that holds the photos.")
  names = sorted(n for n in os.listdir(image_dir)
                 if os.path.splitext(n)[1].lower() in IMAGE_EXTENSIONS)
  if len(names) < 3:
    raise ValueError(f"--images={image_dir}: {len(names)} photos "
                     f"(extensions {sorted(IMAGE_EXTENSIONS)}); "
                     "structure from motion needs at least 3.")
  if os.path.exists(os.path.join(scene_dir, "sparse")):
    raise ValueError(f"--out={scene_dir} already holds sparse/; delete it "
                     "or pick another folder.")
  try:
    pycolmap.CameraModelId(camera_model)
  except ValueError:
    raise ValueError(f"--camera_model={camera_model}: not a COLMAP camera "
                     "model (e.g. SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, "
                     "OPENCV).") from None
  return names


def _log_stage(stage: str, tic: float) -> float:
  """Logs the seconds since `tic` as the stage's own time; returns now."""
  now = time.perf_counter()
  logging.info("%s: %.0f s", stage, now - tic)
  return now


def reconstruct(image_dir: str, scene_dir: str, camera_model: str,
                single_camera: bool) -> pycolmap.Reconstruction:
  """Runs SfM; the finished model appears at scene_dir/sparse/0 atomically."""
  names = check_inputs(image_dir, scene_dir, camera_model)
  os.makedirs(scene_dir, exist_ok=True)
  db = os.path.join(scene_dir, "database.db")
  if os.path.exists(db):
    os.remove(db)  # A half-built database from an interrupted run.
  reader = pycolmap.ImageReaderOptions()
  reader.camera_model = camera_model
  mode = (pycolmap.CameraMode.SINGLE if single_camera
          else pycolmap.CameraMode.PER_IMAGE)
  tic = time.perf_counter()
  pycolmap.extract_features(db, image_dir, image_names=names,
                            camera_mode=mode, reader_options=reader)
  tic = _log_stage("features", tic)
  verification = pycolmap.TwoViewGeometryOptions()
  verification.ransac.random_seed = SEED
  pycolmap.match_exhaustive(db, verification_options=verification)
  tic = _log_stage("matching", tic)
  tmp = os.path.join(scene_dir, f".tmp-sparse-{os.getpid()}")
  shutil.rmtree(tmp, ignore_errors=True)
  os.makedirs(tmp)
  options = pycolmap.GlobalPipelineOptions()
  options.random_seed = SEED
  options.multiple_models = False
  models = pycolmap.global_mapping(db, image_dir, tmp, options)
  _log_stage("mapping", tic)
  if not models:
    shutil.rmtree(tmp, ignore_errors=True)
    # The photos, not a bug: a ValueError, reported as one line.
    raise ValueError(f"pycolmap could not register the photos in "
                     f"{image_dir} (too few matches between them); add "
                     "photos that overlap more.")
  # multiple_models=False: one model, which the mapper wrote to tmp/<key>.
  (key, rec), = models.items()
  staged = os.path.join(tmp, "sparse")
  os.makedirs(staged)
  os.rename(os.path.join(tmp, str(key)), os.path.join(staged, "0"))
  os.rename(staged, os.path.join(scene_dir, "sparse"))
  shutil.rmtree(tmp, ignore_errors=True)
  link = os.path.join(scene_dir, "images")
  if not os.path.lexists(link):
    os.symlink(os.path.abspath(image_dir), link)
  return rec


def summary(rec: pycolmap.Reconstruction) -> str:
  """One line: registered photos, points, reprojection error, the share of
  cameras facing the centre of the camera positions, the cameras."""
  cams = ", ".join(f"{c.model.name} {np.round(c.params, 4).tolist()}"
                   for c in rec.cameras.values())
  error = rec.compute_mean_reprojection_error()
  facing = colmap.facing_fraction(*colmap.centers_and_axes(
      *colmap.poses(rec.images.values())))
  return (f"{rec.num_reg_images()} photos registered, {rec.num_points3D()} "
          f"points, mean reprojection error {error:.3f} px; cameras facing "
          f"the centre of the camera positions: "
          f"{facing:.0%}; cameras: {cams}")
