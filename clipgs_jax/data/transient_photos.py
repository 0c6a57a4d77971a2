"""Photos pasted into scenes as transients: categories, alphas, 2D pastes.

The folder of photos is prepare.py's --distractors (RobustNeRF's word for
them); here a distractor is only the paper's prompt set D.
"""

import os

import numpy as np

from clipgs_jax.data import images

CATEGORY_NAMES = ("person", "clutter")
# Categories of the photos in ../shared/data/distractors (see its README),
# by file stem, so that folder works without subfolders or a manifest.
BUILTIN_CATEGORIES = {
    "astronaut": "person", "camera": "person", "grace_hopper": "person",
    "basketball1": "person", "messi5": "person",
    "chelsea": "clutter", "coffee": "clutter", "rocket": "clutter",
}
# Optional manifest in a distractor folder: one `CATEGORY NAME` per line
# (NAME relative to the folder, may hold spaces; `#` starts a comment).
MANIFEST = "categories.txt"
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


def _is_photo(name: str) -> bool:
  return name.lower().endswith(PHOTO_EXTENSIONS)


def read_manifest(folder: str) -> dict[str, str]:
  """{relative photo name: category} from `folder`/categories.txt, or {}."""
  path = os.path.join(folder, MANIFEST)
  if not os.path.isfile(path):
    return {}
  listed = {}
  with open(path, encoding="utf-8") as f:
    for number, line in enumerate(f, 1):
      line = line.split("#", 1)[0].strip()
      if not line:
        continue
      category, _, name = line.partition(" ")
      name = name.strip()
      where = f"{path} line {number}"
      if category not in CATEGORY_NAMES or not name:
        raise ValueError(f"--distractors: {where} is {line!r}; write "
                         "`person NAME` or `clutter NAME`, NAME relative to "
                         "the folder.")
      if not os.path.isfile(os.path.join(folder, name)):
        raise FileNotFoundError(f"--distractors: {where} lists {name}, which "
                                f"is not in {folder}; fix the name or remove "
                                "the line.")
      listed[os.path.normpath(name)] = category
  return listed


def _name_category(name: str) -> str | None:
  """Category from a file name (built-in photo or person*/clutter* prefix)."""
  stem = os.path.splitext(os.path.basename(name))[0].lower()
  if stem in BUILTIN_CATEGORIES:
    return BUILTIN_CATEGORIES[stem]
  for category in CATEGORY_NAMES:
    if stem.startswith(category):
      return category
  return None


def list_photos(folder: str) -> list[tuple[str, str]]:
  """Sorted [(path, category)] of the distractor photos in `folder`.

  A photo's category ("person" or "clutter") comes from, in this order:
  its line in `folder`/categories.txt (see MANIFEST), its subfolder
  (`person/` or `clutter/`), or its file name (the photos of
  ../shared/data/distractors, or a `person`/`clutter` prefix).

  Raises:
    FileNotFoundError: no such folder, or a manifest line names no file.
    ValueError: no photos, a photo whose category cannot be told (named,
      with the fix), a bad or contradicting manifest line, or photos in a
      subfolder other than person/ and clutter/.
  """
  if not os.path.isdir(folder):
    raise FileNotFoundError(f"--distractors={folder} is not a folder; pass "
                            "the folder of photos, e.g. "
                            "../shared/data/distractors.")
  listed = read_manifest(folder)
  found = {}
  for entry in sorted(os.listdir(folder)):
    path = os.path.join(folder, entry)
    if os.path.isfile(path) and _is_photo(entry):
      found[entry] = None
    elif os.path.isdir(path):
      photos = sorted(n for n in os.listdir(path) if _is_photo(n) and
                      os.path.isfile(os.path.join(path, n)))
      if photos and entry not in CATEGORY_NAMES and not all(
          os.path.join(entry, n) in listed for n in photos):
        raise ValueError(f"--distractors: subfolder {path} holds photos but "
                         "is neither person/ nor clutter/; rename it or list "
                         f"its photos in {os.path.join(folder, MANIFEST)}.")
      for n in photos:
        found[os.path.join(entry, n)] = (entry if entry in CATEGORY_NAMES
                                         else None)
  if not found:
    raise ValueError(f"--distractors={folder} has no photos "
                     f"({'/'.join(PHOTO_EXTENSIONS)}); add some.")
  out = []
  for name, from_folder in sorted(found.items()):
    category = listed.get(name) or from_folder or _name_category(name)
    if name in listed and from_folder and listed[name] != from_folder:
      raise ValueError(f"--distractors: {MANIFEST} says {name} is "
                       f"{listed[name]} but it is in {from_folder}/; make "
                       "them agree.")
    if category is None:
      raise ValueError(
          f"--distractors: no category for {os.path.join(folder, name)}; "
          f"move it into {os.path.join(folder, 'person')}/ or "
          f"{os.path.join(folder, 'clutter')}/, or add the line "
          f"`person {name}` (or `clutter {name}`) to "
          f"{os.path.join(folder, MANIFEST)}.")
    out.append((os.path.join(folder, name), category))
  return out


def load_photos(folder: str) -> list[tuple[str, str, np.ndarray]]:
  """[(name relative to folder, category, float32 [h, w, 3] pixels)]."""
  return [(os.path.relpath(p, folder), c, images.read_image(p))
          for p, c in list_photos(folder)]


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


def paste_size(rng: np.random.Generator, photo_size, width: int,
               height: int) -> tuple[int, int]:
  """(w, h) of a photo pasted at MIN_HEIGHT..MAX_HEIGHT of the view height,
  aspect kept and shrunk to the view width if wider."""
  pw, ph = photo_size
  h = max(1, int(round(rng.uniform(MIN_HEIGHT, MAX_HEIGHT) * height)))
  w = max(1, int(round(h * pw / ph)))
  if w > width:
    w, h = width, max(1, int(round(width * ph / pw)))
  return w, h


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
  w, h = paste_size(rng, photo_sizes[index], width, height)
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
    (image float32 [H, W, 3], mask bool [H, W] (union of alpha >
    MASK_THRESHOLD), transients: list of {"photo", "category", "box",
    "shape"}; box is [x0, y0, x1, y1] of the pasted photo clipped to the
    view, x1/y1 exclusive).
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
