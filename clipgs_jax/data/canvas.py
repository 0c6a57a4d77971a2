"""Photos of different sizes on one canvas: the largest width by the
largest height, each photo in its top-left corner (scene.Views.sizes)."""

import numpy as np

# A canvas costs its area in every render and in device memory for every
# photo, so a split whose canvas exceeds this many times the mean photo's
# area is refused (portrait and landscape photos of one camera are 1.33x
# at 4:3, 1.78x at 16:9; a thumbnail among full-size photos is far more;
# BUILD_NOTES.md, "Multi-device training").
MAX_CANVAS_WASTE = 4.0


def photo_size(views, i: int) -> tuple[int, int]:
  """(width, height) of view i's photo: its canvas corner or the canvas."""
  sizes = getattr(views, "sizes", None)
  if sizes is None:
    return int(views.cameras.width), int(views.cameras.height)
  return int(sizes[i][0]), int(sizes[i][1])


def crop(views, i: int, array):
  """`array` ([H, W, ...] on the canvas of `views`) cut to view i's photo."""
  width, height = photo_size(views, i)
  return array[:height, :width]


def on_canvas(arrays, sizes: np.ndarray | None, fill=0) -> np.ndarray:
  """[V, H, W, ...]: per-view arrays of (possibly) different sizes in the
  top-left corner of the canvas `sizes` spans, `fill` elsewhere.

  Args:
    arrays: V arrays [h_i, w_i, ...] of one dtype.
    sizes: int [V, 2] of their (w_i, h_i), or None when they share one
      size (then they are stacked as they are).
  """
  if sizes is None:
    return np.stack(arrays)
  width, height = (int(x) for x in np.max(sizes, axis=0))
  first = np.asarray(arrays[0])
  out = np.full((len(arrays), height, width) + first.shape[2:], fill,
                first.dtype)
  for i, a in enumerate(arrays):
    out[i, :a.shape[0], :a.shape[1]] = a
  return out


def canvas_sizes(sizes, what: str) -> np.ndarray | None:
  """int32 [V, 2] of the photos' (width, height), or None when they share
  one size.

  Raises:
    ValueError: the canvas holds more than MAX_CANVAS_WASTE times the
      mean photo's pixels.
  """
  sizes = np.asarray(sizes, np.int32).reshape(-1, 2)
  if len(sizes) == 0 or np.all(sizes == sizes[0]):
    return None
  width, height = np.max(sizes, axis=0)
  waste = width * height / np.mean(np.prod(sizes.astype(np.float64), -1))
  if waste > MAX_CANVAS_WASTE:
    small = sizes[np.argmin(np.prod(sizes, -1))]
    raise ValueError(
        f"{what}: photos from {small[0]}x{small[1]} to {width}x{height} "
        f"share a {width}x{height} canvas of {waste:.1f}x the mean photo's "
        f"pixels (at most {MAX_CANVAS_WASTE:g}x); resize or crop the "
        "photos to similar sizes, or train them as separate scenes.")
  return sizes
