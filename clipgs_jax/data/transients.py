"""RobustNeRF-layout transient benchmarks built from a static COLMAP scene.

Every 8th registered image by name (colmap.natural_key order: capture
order for numbered photos, padded or not) becomes a clean test view
`images/1extraNNN.png`; the others become training views
`images/2clutterNNN.png`, with clean twins `images/0cleanNNN.png` (same
cameras, for the clean upper bound). Transients are real photos of people
or clutter (`transient_photos.list_photos`) with soft-edged alphas, in one of
two modes:

- "independent": each cluttered view gets 1-3 photos pasted at random 2D
  positions, independently of every other view (vanilla 3DGS averages them
  into a haze).
- "persistent": the training views, in capture order (the same name
  order), are cut into runs of k consecutive views; each chosen run gets
  1-3 photos on planar billboards placed in 3D in front of the scene and
  rendered into all k views (`billboards.py`), so each is one physical
  object that vanilla 3DGS can fit as a ghost. A billboard that no
  placement keeps in all k views (the camera path jumps inside the run)
  goes to the run's longest stretch of at least MIN_RUN_VIEWS consecutive
  views that can show it, or is left out ("unplaced" in the manifest);
  only when no chosen run can show any billboard is the build refused.

`masks/2clutterNNN.png` holds the ground truth (alpha > MASK_THRESHOLD;
all black for views left clean), `transients.json` lists every transient
(and, when persistent, each billboard's 3D corners and views), and
`sparse/0` is the source model with renamed images and the clean twins.
Distorted scenes are built from the loader's undistorted images and
PINHOLE model. Output is deterministic for a seed, and the views
cluttered at a smaller fraction are a subset of those at a larger one.
"""

import json
import os
import shutil
import uuid

import numpy as np
import pycolmap

from clipgs_jax.data import billboards
from clipgs_jax.data import colmap
from clipgs_jax.data import transient_photos
from clipgs_jax.data import images
from clipgs_jax.data import splits

MODES = ("independent", "persistent")
DEFAULT_PERSIST_VIEWS = 5   # views per billboard: RobustNeRF-like runs
# The fewest consecutive views a billboard may be shown in when its whole
# run cannot show it: one view would make it an independent paste, not a
# persistent object.
MIN_RUN_VIEWS = 2
MASK_THRESHOLD = transient_photos.MASK_THRESHOLD


def parse_per_view(text: str) -> tuple[int, int]:
  """(lo, hi) from "A..B" or "N"; ValueError when malformed."""
  parts = str(text).strip().split("..")
  try:
    lo, hi = (int(parts[0]), int(parts[-1])) if len(parts) <= 2 else (0, -1)
  except ValueError:
    lo, hi = 0, -1
  if not 1 <= lo <= hi:
    raise ValueError(f"--per_view={text} is not a count: pass an integer "
                     ">= 1 or a range A..B with 1 <= A <= B, e.g. 1..3.")
  return lo, hi


def split_views(num: int) -> tuple[list[int], list[int]]:
  """(train, test) indices into the model's names (colmap.natural_key
  order): every 8th (0, 8, ...) tests."""
  test = list(range(0, num, splits.TEST_EVERY))
  return [i for i in range(num) if i % splits.TEST_EVERY], test


def choose_cluttered(num: int, fraction: float, seed: int,
                     stream: int = 0) -> set[int]:
  """round(fraction * num) of range(num), nested in fraction.

  One permutation per (seed, stream), so a smaller fraction's choice is a
  subset of a larger one's and benchmarks at several fractions differ only
  there. Stream 0 chooses views (independent), 2 chooses runs (persistent).
  """
  order = np.random.default_rng([seed, stream]).permutation(num)
  return set(order[:int(np.floor(fraction * num + 0.5))].tolist())


def view_rng(seed: int, k: int) -> np.random.Generator:
  """Generator of training view k, independent of every other view's."""
  return np.random.default_rng([seed, 1, k])


def run_rng(seed: int, r: int) -> np.random.Generator:
  """Generator of persistent run r, independent of every other run's."""
  return np.random.default_rng([seed, 3, r])


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
  """The scene's pinhole model; errors name --clean_scene."""
  if not os.path.isdir(path):
    raise FileNotFoundError(f"--clean_scene={path} is not a folder; pass a "
                            "COLMAP scene folder with images/ and sparse/0/.")
  try:
    model = colmap.load_model(path, cache_dir=cache_dir)
  except (FileNotFoundError, ValueError) as e:
    raise ValueError(f"--clean_scene={path}: {e}") from None
  if len(model.names) < 2:
    raise ValueError(f"--clean_scene={path} has {len(model.names)} "
                     "registered image(s); a benchmark needs at least 2.")
  return model


def _prepare_out(out: str, overwrite: bool) -> None:
  if os.path.isfile(out):
    raise ValueError(f"--out={out} is a file; pass a folder path.")
  if os.path.isdir(out) and os.listdir(out) and not overwrite:
    raise ValueError(f"--out={out} exists and is not empty; pass "
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


def _camera(model: colmap.Model, i: int):
  return model.rotations[i], model.translations[i], model.intrinsics[i]


def _fit(rng, photo_size, model, train_idx, run):
  """(views, corners [4, 3]) of a billboard in the whole `run` (training
  positions), else in the first of its longest stretches of consecutive
  views (down to MIN_RUN_VIEWS) that can show it; (None, None) if none."""
  for length in range(len(run), min(MIN_RUN_VIEWS, len(run)) - 1, -1):
    for start in range(len(run) - length + 1):
      views = run[start:start + length]
      cams = [train_idx[v] for v in views]
      try:
        corners = billboards.place(
            rng, photo_size, model.rotations[cams], model.translations[cams],
            model.intrinsics[cams], model.sizes[cams], model.points)
      except billboards.PlacementError:
        continue
      return views, corners
  return None, None


def make_billboards(model, train_idx, photos, seed, fraction, per_view, k):
  """(billboards, unplaced) of the chosen runs.

  billboards: list of dicts with "corners" [4, 3], "run", "views" (training
  positions: the run, or its longest stretch that can show the billboard),
  photo name/category/shape, and the texture ("rgb" [h, w, 3], "alpha"
  [h, w]; not written to JSON). unplaced: list of {"run", "photo"}, the
  billboards no stretch of their run could show.

  Raises:
    ValueError: runs were chosen but none could show any billboard.
  """
  runs = billboards.make_runs(len(train_idx), k)
  chosen = sorted(choose_cluttered(len(runs), fraction, seed, stream=2))
  out, unplaced = [], []
  for r in chosen:
    rng = run_rng(seed, r)
    for _ in range(int(rng.integers(per_view[0], per_view[1] + 1))):
      index = int(rng.integers(len(photos)))
      shapes = transient_photos.SHAPES
      shape = shapes[int(rng.integers(len(shapes)))]
      name, category, pixels = photos[index]
      views, corners = _fit(rng, pixels.shape[1::-1], model, train_idx,
                            runs[r])
      if views is None:
        unplaced.append({"run": r, "photo": name})
        continue
      mid = train_idx[views[len(views) // 2]]
      tw, th = billboards.texture_size(corners, model.rotations[mid],
                                       model.translations[mid],
                                       model.intrinsics[mid])
      out.append({"id": len(out), "run": r, "views": views, "photo": name,
                  "category": category, "shape": shape, "corners": corners,
                  "rgb": images.resize_area(pixels, tw, th),
                  "alpha": transient_photos.shape_alpha(tw, th, shape)})
  if chosen and not out:
    raise ValueError(
        f"could not place a billboard seen by {min(MIN_RUN_VIEWS, k)} or "
        f"more consecutive views of any of the {len(chosen)} chosen runs "
        f"({billboards.TRIES} tries per stretch); the camera path may jump "
        "between consecutively named photos: check the names' order, pass "
        "a smaller --persist_views, or use --mode=independent.")
  return out, unplaced


def _persistent_view(pixels, model, i, boards):
  """Renders the billboards `boards` into training view (model index) i."""
  image, mask, transients = pixels, np.zeros(pixels.shape[:2], bool), []
  for board in boards:
    image, alpha = billboards.render(image, board["corners"], board["rgb"],
                                     board["alpha"], *_camera(model, i))
    own = alpha > MASK_THRESHOLD
    mask |= own
    ys, xs = np.nonzero(alpha > 0)
    box = ([int(xs.min()), int(ys.min()), int(xs.max()) + 1,
            int(ys.max()) + 1] if len(xs) else [0, 0, 0, 0])
    transients.append({"photo": board["photo"], "category":
                       board["category"], "shape": board["shape"],
                       "billboard": board["id"], "box": box,
                       "mask_pixels": int(own.sum())})
  return image, mask, transients


def _write_views(model, tmp, photos, seed, fraction, per_view, mode, k):
  """Writes images/ and masks/; returns (views, tests, renames, twins,
  boards, unplaced)."""
  train_idx, test_idx = split_views(len(model.names))
  width = max(3, len(str(max(len(train_idx), len(test_idx)))))
  boards, unplaced, cluttered = [], [], set()
  if mode == "persistent":
    boards, unplaced = make_billboards(model, train_idx, photos, seed,
                                       fraction, per_view, k)
  else:
    cluttered = choose_cluttered(len(train_idx), fraction, seed)
  views, tests, renames, twins = [], [], {}, {}
  for j, i in enumerate(test_idx):
    source = model.names[i]
    name = f"1extra{j:0{width}d}.png"
    pixels = images.read_image(os.path.join(model.image_dir, source))
    images.write_png(os.path.join(tmp, "images", name), pixels)
    renames[source] = name
    tests.append({"name": name, "source": source})
  for j, i in enumerate(train_idx):
    source = model.names[i]
    name, clean = f"2clutter{j:0{width}d}.png", f"0clean{j:0{width}d}.png"
    pixels = images.read_image(os.path.join(model.image_dir, source))
    image, mask, transients = pixels, np.zeros(pixels.shape[:2], bool), []
    if mode == "persistent":
      image, mask, transients = _persistent_view(
          pixels, model, i, [b for b in boards if j in b["views"]])
    elif j in cluttered:
      image, mask, transients = transient_photos.clutter_view(
          pixels, photos, view_rng(seed, j), per_view)
    images.write_png(os.path.join(tmp, "images", clean), pixels)
    images.write_png(os.path.join(tmp, "images", name), image)
    # Views left clean get an all-black mask, as in the default scene.
    images.write_png(os.path.join(tmp, "masks", name), mask)
    renames[source], twins[name] = name, clean
    views.append({"name": name, "source": source, "clean": clean,
                  "mask": f"masks/{name}", "mask_pixels": int(mask.sum()),
                  "transients": transients})
  return views, tests, renames, twins, boards, unplaced


def _describe(boards, views):
  return [{"id": b["id"], "run": b["run"], "photo": b["photo"],
           "category": b["category"], "shape": b["shape"],
           "corners": np.round(b["corners"], 9).tolist(),
           "texture_size": list(b["alpha"].shape[::-1]),
           "views": [views[v]["name"] for v in b["views"]]} for b in boards]


def billboard_summary(manifest: dict) -> str:
  """One phrase on a persistent manifest's billboards, e.g. "71 billboards
  of 5 views", or with the stretches that replaced runs and what could not
  be placed: "70 billboards: 68 of 5 views, 2 of 3 (their runs could not
  show them in all 5); 1 not placed, run 7 skipped"."""
  boards, k = manifest["billboards"], manifest["persist_views"]
  lengths = sorted({len(b["views"]) for b in boards}, reverse=True)
  if lengths in ([], [k]):
    text = f"{len(boards)} billboards of {k} views"
  else:
    counts = ", ".join(
        f"{sum(len(b['views']) == n for b in boards)} of {n}" +
        (" views" if i == 0 else "") for i, n in enumerate(lengths))
    text = (f"{len(boards)} billboards: {counts} (their runs could not show "
            f"them in all {k})")
  unplaced = manifest.get("unplaced", [])
  if unplaced:
    skipped = sorted({u["run"] for u in unplaced}
                     - {b["run"] for b in boards})
    text += f"; {len(unplaced)} not placed"
    if skipped:
      text += (f", run{'s' if len(skipped) > 1 else ''} "
               f"{', '.join(map(str, skipped))} skipped")
  return text


def check_args(fraction: float, seed, mode: str,
               persist_views: int) -> None:
  """ValueError naming the flag when a build argument is out of range."""
  if not 0.0 <= fraction <= 1.0:
    raise ValueError(f"--fraction={fraction} is outside [0, 1]; pass "
                     "e.g. 0.5 (1.0 clutters every training view).")
  if seed is None or seed < 0:
    raise ValueError(f"--seed={seed} must be an integer >= 0.")
  if mode not in MODES:
    raise ValueError(f"--mode={mode}: expected one of {', '.join(MODES)}.")
  if persist_views < 1:
    raise ValueError(f"--persist_views={persist_views} must be >= 1; pass "
                     "e.g. 5 (3-8 views per billboard).")


def build(scene: str, distractor_dir: str, out: str, seed: int,
          fraction: float = 0.5, per_view: str = "1..3",
          overwrite: bool = False, cache_dir: str | None = None,
          mode: str = "independent",
          persist_views: int = DEFAULT_PERSIST_VIEWS) -> dict:
  """Builds the benchmark scene in `out` (see the module docstring).

  Args:
    scene: str, COLMAP scene folder without transients.
    distractor_dir: str, folder of photos (see `transient_photos.list_photos`).
    out: str, output folder (must not exist or be empty, unless overwrite).
    seed: int >= 0.
    fraction: float in [0, 1], fraction of training views (independent) or
      of runs (persistent) with transients.
    per_view: str, "A..B" or "N", photos per cluttered view (independent)
      or billboards per chosen run (persistent).
    overwrite: bool, replace a non-empty `out`.
    cache_dir: str or None, undistortion cache of `scene`.
    mode: "independent" or "persistent".
    persist_views: int, views per run (persistent mode).

  Returns:
    The manifest written to `out/transients.json` (`billboard_summary`
    says in a phrase how its billboards were placed).

  Raises:
    ValueError, FileNotFoundError: bad arguments, as one line naming the
      flag and the fix; nothing is left in `out` then.
  """
  check_args(fraction, seed, mode, persist_views)
  lo_hi = parse_per_view(per_view)
  out = os.path.abspath(out)
  _prepare_out(out, overwrite)
  transient_photos.list_photos(distractor_dir)   # its errors before any work
  model = load_source(scene, cache_dir)
  if mode == "persistent":     # checked before any work is done
    billboards.make_runs(len(split_views(len(model.names))[0]),
                         persist_views)
  photos = transient_photos.load_photos(distractor_dir)
  os.makedirs(os.path.dirname(out), exist_ok=True)
  tmp = f"{out}.tmp-{uuid.uuid4().hex[:8]}"
  try:
    views, tests, renames, twins, boards, unplaced = _write_views(
        model, tmp, photos, seed, fraction, lo_hi, mode, persist_views)
    write_model(model.sparse_dir, renames, twins,
                os.path.join(tmp, "sparse", "0"))
    counts = {}
    for view in views:
      for t in view["transients"]:
        counts[t["category"]] = counts.get(t["category"], 0) + 1
    manifest = {
        "generator": "clipgs_jax.data.transients.build", "mode": mode,
        "source_scene": os.path.realpath(scene),
        "undistorted": bool(model.undistorted), "seed": int(seed),
        "fraction": float(fraction), "per_view": list(lo_hi),
        "mask_threshold": MASK_THRESHOLD,
        "num_train": len(views), "num_test": len(tests),
        "num_cluttered": sum(bool(v["transients"]) for v in views),
        "transients_by_category": counts, "views": views, "tests": tests}
    if mode == "persistent":
      manifest["persist_views"] = int(persist_views)
      manifest["billboards"] = _describe(boards, views)
      if unplaced:    # absent when every billboard was placed
        manifest["unplaced"] = unplaced
    with open(os.path.join(tmp, "transients.json"), "w") as f:
      json.dump(manifest, f, indent=1, sort_keys=True)
    _move_into_place(tmp, out)
  finally:
    shutil.rmtree(tmp, ignore_errors=True)
  return manifest
