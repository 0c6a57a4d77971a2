"""Builds a RobustNeRF-layout transient benchmark from a static COLMAP scene.

  PYTHONPATH=. python experiments/make_transient_benchmark.py \
      --scene=COLMAP_DIR --distractors=PHOTO_DIR --out=DIR --seed=S \
      [--fraction=0.5] [--per_view=1..3] [--overwrite] [--cache_dir=DIR]

Every 8th registered image by sorted name becomes a clean test view
`images/1extraNNN.png`; the others become training views
`images/2clutterNNN.png`, and in `--fraction` of them 1 to 3 (`--per_view`)
real photos of people or clutter are pasted at random positions and scales
with soft-edged (ellipse or rounded-rectangle) masks. The clean training
images are kept as `images/0cleanNNN.png` (same cameras, for the clean upper
bound). `masks/2clutterNNN.png` holds the ground truth (white = transient;
all black for training views left clean, as the embedded default scene
does), `transients.json` lists every pasted photo, and `sparse/0` is the
source model with the images renamed (and the 0clean twins added).

Distorted scenes (e.g. SIMPLE_RADIAL) are built from the undistorted images
and PINHOLE model that `colmap.load_model` caches, so the pastes and masks
are in the pixel frame the trainer uses. The output is deterministic for a
seed: view k's pastes depend only on (seed, k), and the cluttered views of
a smaller fraction are a subset of those of a larger one.
"""

import json
import os
import shutil
import time
import uuid

from absl import app
from absl import flags
import numpy as np
import pycolmap

from clipgs_jax.data import colmap
from clipgs_jax.data import images
from clipgs_jax.data import scene as scene_lib

FLAGS = flags.FLAGS

# Categories of the photos in ../shared/data/distractors (see its README),
# by file stem. Other photos are accepted when their stem starts with
# `person` or `clutter`.
CATEGORIES = {
    "astronaut": "person", "camera": "person", "grace_hopper": "person",
    "basketball1": "person", "messi5": "person",
    "chelsea": "clutter", "coffee": "clutter", "rocket": "clutter",
}
PHOTO_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
SHAPES = ("ellipse", "rounded_rect")
# A pasted photo is 15-45 % of the view height, as people and objects that
# walk through a capture are in RobustNeRF.
MIN_HEIGHT, MAX_HEIGHT = 0.15, 0.45
# Up to this fraction of a photo may hang over the image border ("mostly
# inside"), so transients also appear cut off at the edges.
MAX_OVERHANG = 0.2
# Soft edge width: 3 % of the photo's short side, 1.5 to 6 pixels.
FEATHER_FRACTION, MIN_FEATHER, MAX_FEATHER = 0.03, 1.5, 6.0
CORNER_FRACTION = 0.2     # rounded-rect corner radius / short side
MASK_THRESHOLD = 0.5      # ground-truth mask: alpha > this


def _define_flags() -> None:
  # Defined only when run as a script, so tests can import this module.
  flags.DEFINE_string("scene", None, "COLMAP scene folder (images/, "
                      "sparse/0/) without transients.")
  flags.DEFINE_string("distractors", None, "Folder of photos to paste.")
  flags.DEFINE_string("out", None, "Output scene folder (must not exist or "
                      "be empty, unless --overwrite).")
  flags.DEFINE_integer("seed", None, "Random seed (>= 0).")
  flags.DEFINE_float("fraction", 0.5, "Fraction of training views that get "
                     "transients, in [0, 1].")
  flags.DEFINE_string("per_view", "1..3", "Photos pasted per cluttered view: "
                      "an integer or a range A..B (uniform).")
  flags.DEFINE_bool("overwrite", False, "Replace a non-empty --out.")
  flags.DEFINE_string("cache_dir", None, "Undistortion cache of --scene "
                      "(default: the one load_scene uses).")
  flags.mark_flags_as_required(["scene", "distractors", "out", "seed"])


def parse_per_view(text: str) -> tuple[int, int]:
  """(lo, hi) from "A..B" or "N"; raises app.UsageError when malformed."""
  parts = str(text).strip().split("..")
  try:
    lo, hi = (int(parts[0]), int(parts[-1])) if len(parts) <= 2 else (0, -1)
  except ValueError:
    lo, hi = 0, -1
  if not 1 <= lo <= hi:
    raise app.UsageError(f"--per_view={text} is not a count: pass an integer "
                         ">= 1 or a range A..B with 1 <= A <= B, e.g. 1..3.")
  return lo, hi


def photo_category(path: str) -> str:
  """"person" or "clutter" for a distractor photo, from its file name."""
  stem = os.path.splitext(os.path.basename(path))[0].lower()
  if stem in CATEGORIES:
    return CATEGORIES[stem]
  for category in ("person", "clutter"):
    if stem.startswith(category):
      return category
  raise app.UsageError(
      f"--distractors: no category for {path}; rename it to person_* or "
      f"clutter_*, or use the photos {sorted(CATEGORIES)}.")


def list_photos(folder: str) -> list[tuple[str, str]]:
  """Sorted [(path, category)] of the photos in `folder`."""
  if not os.path.isdir(folder):
    raise app.UsageError(f"--distractors={folder} is not a folder; pass the "
                         "folder of photos, e.g. ../shared/data/distractors.")
  paths = sorted(os.path.join(folder, f) for f in os.listdir(folder)
                 if f.lower().endswith(PHOTO_EXTENSIONS))
  if not paths:
    raise app.UsageError(f"--distractors={folder} has no photos "
                         f"({'/'.join(PHOTO_EXTENSIONS)}); add some.")
  return [(p, photo_category(p)) for p in paths]


def split_views(num: int) -> tuple[list[int], list[int]]:
  """(train, test) indices into sorted names: every 8th (0, 8, ...) tests."""
  test = list(range(0, num, scene_lib.TEST_EVERY))
  return [i for i in range(num) if i % scene_lib.TEST_EVERY], test


def choose_cluttered(num_train: int, fraction: float, seed: int) -> set[int]:
  """round(fraction * num_train) training-view positions, nested in fraction.

  One permutation per seed, so a smaller fraction's views are a subset of a
  larger one's and benchmarks at several fractions differ only there.
  """
  order = np.random.default_rng([seed, 0]).permutation(num_train)
  return set(order[:int(np.floor(fraction * num_train + 0.5))].tolist())


def view_rng(seed: int, k: int) -> np.random.Generator:
  """Generator of training view k, independent of every other view's."""
  return np.random.default_rng([seed, 1, k])


def shape_alpha(width: int, height: int, shape: str) -> np.ndarray:
  """Soft mask of an ellipse or rounded rectangle filling a box.

  alpha = clip(0.5 - d / feather, 0, 1) for the signed distance d to the
  shape's outline (negative inside); the outline is inset by feather / 2 +
  0.5 pixel, so alpha is 0 at the centres of the box's border pixels and
  the cut edges of the photo never show.

  Args:
    width, height: int, box size in pixels.
    shape: "ellipse" or "rounded_rect".

  Returns:
    float32 [height, width] in [0, 1].
  """
  feather = float(np.clip(FEATHER_FRACTION * min(width, height), MIN_FEATHER,
                          MAX_FEATHER))
  a = max(width / 2 - feather / 2 - 0.5, 0.5)    # outline half extents
  b = max(height / 2 - feather / 2 - 0.5, 0.5)
  # Pixel centres at +0.5, relative to the box centre.
  x = np.abs(np.arange(width) + 0.5 - width / 2)[None, :]     # [1, W]
  y = np.abs(np.arange(height) + 0.5 - height / 2)[:, None]   # [H, 1]
  if shape == "ellipse":
    k = np.sqrt((x / a) ** 2 + (y / b) ** 2)
    grad = np.sqrt((x / a ** 2) ** 2 + (y / b ** 2) ** 2)
    # First-order distance k (k - 1) / |grad k|; near the centre (k < 0.5,
    # where grad -> 0) the distance is at least min(a, b) / 2.
    dist = np.where(k > 0.5, k * (k - 1) / np.maximum(grad, 1e-12),
                    -0.5 * min(a, b))
  elif shape == "rounded_rect":
    r = CORNER_FRACTION * min(a, b)
    qx, qy = x - (a - r), y - (b - r)
    outside = np.hypot(np.maximum(qx, 0), np.maximum(qy, 0))
    dist = outside + np.minimum(np.maximum(qx, qy), 0) - r
  else:
    raise ValueError(f"unknown shape {shape!r}; expected one of {SHAPES}.")
  return np.clip(0.5 - dist / feather, 0, 1).astype(np.float32)


def sample_paste(rng: np.random.Generator, photo_sizes, width: int,
                 height: int) -> dict:
  """Random photo, shape and placement in a width x height view.

  Args:
    rng: the view's generator.
    photo_sizes: list of (width, height) of the candidate photos.
    width, height: int, the view's size.

  Returns:
    {"index": photo index, "shape", "x0", "y0", "w", "h"}: the photo is
    resized to w x h (aspect kept) with its top-left corner at (x0, y0),
    which may lie outside the view by up to MAX_OVERHANG of w (h).
  """
  index = int(rng.integers(len(photo_sizes)))
  shape = SHAPES[int(rng.integers(len(SHAPES)))]
  pw, ph = photo_sizes[index]
  h = max(1, int(round(rng.uniform(MIN_HEIGHT, MAX_HEIGHT) * height)))
  w = max(1, int(round(h * pw / ph)))
  if w > width:                          # keep the aspect, fit the width
    w, h = width, max(1, int(round(width * ph / pw)))
  ox, oy = int(MAX_OVERHANG * w), int(MAX_OVERHANG * h)
  x0 = int(rng.integers(-ox, width - w + ox + 1))
  y0 = int(rng.integers(-oy, height - h + oy + 1))
  return {"index": index, "shape": shape, "x0": x0, "y0": y0, "w": w, "h": h}


def composite(view: np.ndarray, photo: np.ndarray, alpha: np.ndarray,
              x0: int, y0: int) -> tuple[np.ndarray, np.ndarray]:
  """Pastes `photo` with `alpha` at (x0, y0), clipped to the view.

  Args:
    view: float32 [H, W, 3].
    photo: float32 [h, w, 3], already resized.
    alpha: float32 [h, w] in [0, 1].
    x0, y0: int, top-left corner (may be negative).

  Returns:
    (alpha * photo + (1 - alpha) * view: float32 [H, W, 3], the paste's
    alpha in view coordinates: float32 [H, W]).
  """
  height, width = view.shape[:2]
  h, w = alpha.shape
  vx0, vy0 = max(x0, 0), max(y0, 0)
  vx1, vy1 = min(x0 + w, width), min(y0 + h, height)
  full = np.zeros((height, width), np.float32)
  full[vy0:vy1, vx0:vx1] = alpha[vy0 - y0:vy1 - y0, vx0 - x0:vx1 - x0]
  placed = np.zeros_like(view)
  placed[vy0:vy1, vx0:vx1] = photo[vy0 - y0:vy1 - y0, vx0 - x0:vx1 - x0]
  out = full[..., None] * placed + (1 - full[..., None]) * view
  return out.astype(np.float32), full


def clutter_view(view: np.ndarray, photos, rng: np.random.Generator,
                 per_view: tuple[int, int]):
  """Pastes per_view[0]..per_view[1] random photos into one view.

  Args:
    view: float32 [H, W, 3], the clean view.
    photos: list of (name, category, float32 [h, w, 3] pixels).
    rng: the view's generator.
    per_view: (lo, hi), inclusive range of the number of photos.

  Returns:
    (image float32 [H, W, 3], mask bool [H, W] (union of alpha > 0.5),
    transients: list of {"photo", "category", "box", "shape"}; box is
    [x0, y0, x1, y1] of the pasted photo clipped to the view, x1/y1
    exclusive).
  """
  height, width = view.shape[:2]
  sizes = [(p.shape[1], p.shape[0]) for _, _, p in photos]
  image, mask, transients = view, np.zeros((height, width), bool), []
  for _ in range(int(rng.integers(per_view[0], per_view[1] + 1))):
    paste = sample_paste(rng, sizes, width, height)
    name, category, pixels = photos[paste["index"]]
    resized = images.resize_area(pixels, paste["w"], paste["h"])
    alpha = shape_alpha(paste["w"], paste["h"], paste["shape"])
    image, full = composite(image, resized, alpha, paste["x0"], paste["y0"])
    mask |= full > MASK_THRESHOLD
    x0, y0 = paste["x0"], paste["y0"]
    transients.append({
        "photo": name, "category": category, "shape": paste["shape"],
        "box": [max(x0, 0), max(y0, 0), min(x0 + paste["w"], width),
                min(y0 + paste["h"], height)]})
  return image, mask, transients


def _value(obj, name):
  """Attribute that is a method in some pycolmap versions."""
  value = getattr(obj, name)
  return value() if callable(value) else value


def write_model(sparse_dir: str, renames: dict[str, str],
                twins: dict[str, str], folder: str) -> None:
  """Writes the model of `sparse_dir` with renamed images, as binary.

  Intrinsics, poses, points3D and tracks are kept. Images not in `renames`
  (unregistered ones, which loaders skip) keep their names.

  Args:
    sparse_dir: str, the source (undistorted) model.
    renames: {old name: new name}.
    twins: {new name: twin name}: one more image per entry, with the same
      camera and pose and no observations (the 0clean copies).
    folder: str, output folder (created).
  """
  rec = colmap.read_reconstruction(sparse_dir)
  by_name = {im.name: im for im in rec.images.values()}
  poses = {}
  for old, new in renames.items():
    by_name[old].name = new
    poses[new] = (by_name[old].camera_id, _value(by_name[old],
                                                 "cam_from_world"))
  # add_image_with_trivial_frame gives the frame the image's id.
  next_id = max(list(rec.images) + list(rec.frames) + [0]) + 1
  for j, (name, twin) in enumerate(sorted(twins.items())):
    camera_id, pose = poses[name]
    rec.add_image_with_trivial_frame(
        pycolmap.Image(name=twin, camera_id=camera_id,
                       image_id=next_id + j), pose)
  os.makedirs(folder)
  rec.write_binary(folder)


def load_source(path: str, cache_dir: str | None) -> colmap.Model:
  """The scene's pinhole model; errors become one-line usage errors."""
  if not os.path.isdir(path):
    raise app.UsageError(f"--scene={path} is not a folder; pass a COLMAP "
                         "scene folder with images/ and sparse/0/.")
  try:
    model = colmap.load_model(path, cache_dir=cache_dir)
  except (FileNotFoundError, ValueError) as e:
    raise app.UsageError(f"--scene={path}: {e}") from None
  if len(model.names) < 2:
    raise app.UsageError(f"--scene={path} has {len(model.names)} registered "
                         "image(s); a benchmark needs at least 2.")
  return model


def _prepare_out(out: str, overwrite: bool) -> None:
  if os.path.isfile(out):
    raise app.UsageError(f"--out={out} is a file; pass a folder path.")
  if os.path.isdir(out) and os.listdir(out) and not overwrite:
    raise app.UsageError(f"--out={out} exists and is not empty; pass "
                         "--overwrite or another folder.")


def _move_into_place(tmp: str, out: str) -> None:
  """Renames the finished `tmp` to `out`, replacing what was there."""
  old = None
  if os.path.isdir(out):
    old = f"{out}.old-{uuid.uuid4().hex[:8]}"
    os.rename(out, old)
  os.rename(tmp, out)
  if old is not None:
    shutil.rmtree(old, ignore_errors=True)


def _write_views(model, tmp, photos, seed, fraction, per_view):
  """Writes images/ and masks/; returns (views, tests, renames, twins)."""
  train_idx, test_idx = split_views(len(model.names))
  width = max(3, len(str(max(len(train_idx), len(test_idx)))))
  cluttered = choose_cluttered(len(train_idx), fraction, seed)
  views, tests, renames, twins = [], [], {}, {}
  for k, i in enumerate(test_idx):
    source = model.names[i]
    name = f"1extra{k:0{width}d}.png"
    pixels = images.read_image(os.path.join(model.image_dir, source))
    images.write_png(os.path.join(tmp, "images", name), pixels)
    renames[source] = name
    tests.append({"name": name, "source": source})
  for k, i in enumerate(train_idx):
    source = model.names[i]
    name, clean = f"2clutter{k:0{width}d}.png", f"0clean{k:0{width}d}.png"
    pixels = images.read_image(os.path.join(model.image_dir, source))
    image, mask, transients = pixels, np.zeros(pixels.shape[:2], bool), []
    if k in cluttered:
      image, mask, transients = clutter_view(pixels, photos,
                                             view_rng(seed, k), per_view)
    images.write_png(os.path.join(tmp, "images", clean), pixels)
    images.write_png(os.path.join(tmp, "images", name), image)
    # Views left clean get an all-black mask, as in the default scene.
    images.write_png(os.path.join(tmp, "masks", name), mask)
    renames[source], twins[name] = name, clean
    views.append({"name": name, "source": source, "clean": clean,
                  "mask": f"masks/{name}", "mask_pixels": int(mask.sum()),
                  "transients": transients})
  return views, tests, renames, twins


def build(scene: str, distractors: str, out: str, seed: int,
          fraction: float = 0.5, per_view: str = "1..3",
          overwrite: bool = False, cache_dir: str | None = None) -> dict:
  """Builds the benchmark scene in `out` (see the module docstring).

  Args:
    scene: str, COLMAP scene folder without transients.
    distractors: str, folder of photos (see CATEGORIES).
    out: str, output folder.
    seed: int >= 0.
    fraction: float in [0, 1], fraction of training views with transients.
    per_view: str, "A..B" or "N", photos per cluttered view.
    overwrite: bool, replace a non-empty `out`.
    cache_dir: str or None, undistortion cache of `scene`.

  Returns:
    The manifest written to `out/transients.json`.

  Raises:
    app.UsageError: bad arguments, as one line naming the flag and the fix.
  """
  if not 0.0 <= fraction <= 1.0:
    raise app.UsageError(f"--fraction={fraction} is outside [0, 1]; pass "
                         "e.g. 0.5 (1.0 clutters every training view).")
  if seed is None or seed < 0:
    raise app.UsageError(f"--seed={seed} must be an integer >= 0.")
  lo_hi = parse_per_view(per_view)
  out = os.path.abspath(out)
  _prepare_out(out, overwrite)
  photo_list = list_photos(distractors)
  model = load_source(scene, cache_dir)
  photos = [(os.path.basename(p), c, images.read_image(p))
            for p, c in photo_list]
  os.makedirs(os.path.dirname(out), exist_ok=True)
  tmp = f"{out}.tmp-{uuid.uuid4().hex[:8]}"
  try:
    views, tests, renames, twins = _write_views(model, tmp, photos, seed,
                                                fraction, lo_hi)
    write_model(model.sparse_dir, renames, twins,
                os.path.join(tmp, "sparse", "0"))
    counts = {}
    for view in views:
      for t in view["transients"]:
        counts[t["category"]] = counts.get(t["category"], 0) + 1
    manifest = {
        "generator": "experiments/make_transient_benchmark.py",
        "source_scene": os.path.realpath(scene),
        "undistorted": bool(model.undistorted), "seed": int(seed),
        "fraction": float(fraction), "per_view": list(lo_hi),
        "num_train": len(views), "num_test": len(tests),
        "num_cluttered": sum(bool(v["transients"]) for v in views),
        "transients_by_category": counts, "views": views, "tests": tests}
    with open(os.path.join(tmp, "transients.json"), "w") as f:
      json.dump(manifest, f, indent=1, sort_keys=True)
    _move_into_place(tmp, out)
  finally:
    shutil.rmtree(tmp, ignore_errors=True)
  return manifest


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments {argv[1:]}")
  tic = time.perf_counter()
  manifest = build(FLAGS.scene, FLAGS.distractors, FLAGS.out, FLAGS.seed,
                   FLAGS.fraction, FLAGS.per_view, FLAGS.overwrite,
                   FLAGS.cache_dir)
  counts = ", ".join(f"{n} {c}" for c, n in
                     sorted(manifest["transients_by_category"].items()))
  print(f"wrote {FLAGS.out}: {manifest['num_train']} training views "
        f"({manifest['num_cluttered']} cluttered; transients: "
        f"{counts or 'none'}), {manifest['num_test']} test views, in "
        f"{time.perf_counter() - tic:.1f} s")


if __name__ == "__main__":
  _define_flags()
  app.run(main)
