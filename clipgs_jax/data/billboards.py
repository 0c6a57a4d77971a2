"""Persistent transients: photos on planar billboards placed in 3D.

A billboard is a rectangle in world space (corners TL, TR, BR, BL) that
carries a photo and its soft alpha. It stands between the cameras of a run
of consecutive views and the scene content they see, faces those cameras,
and is rendered into each of them by ray-plane intersection, so every view
of the run shows the same physical object (as RobustNeRF's distractors
stay put for several shots) and vanilla 3DGS can fit it as a 3D ghost.
"""

import numpy as np

from clipgs_jax.data import transient_photos

# Depth of the billboard centre along the middle view's optical axis, as a
# fraction of the near scene depth (NEAR_QUANTILE of the SfM points that
# view sees), in stages of (low, high, tries): well in front of the content
# first; a run whose cameras turn so far that no such billboard stays in
# all its views (parallax; on bonsai 5 views span 20-57 degrees) gets a
# deeper one, still in front of the near content.
DEPTH_STAGES = ((0.3, 0.6, 200), (0.6, 0.9, 300))
TRIES = sum(  # placements tried for one billboard, all stages together
    t for _, _, t in DEPTH_STAGES)
NEAR_QUANTILE = 0.1
# The centre is aimed at a pixel this far inside the middle view's border,
# and must project at least this far inside every view of the run, so the
# billboard is visible (its mask non-empty) in all of them.
CENTRE_MARGIN = 0.2
VISIBLE_MARGIN = 0.05
# Every corner must be at least this fraction of the near depth in front
# of every camera of the run (no billboard crosses a camera plane).
MIN_CORNER_DEPTH = 0.05
# Ghost labels (the diagnostic of lab/ghost_evidence.py; never used in
# training): a point belongs to a billboard's ghost when it lies within
# GHOST_DEPTH times the billboard's viewing distance (the mean distance
# from its cameras to its centre) of its plane, and its foot on the plane
# falls inside the rectangle grown by GHOST_MARGIN of each side. Vanilla
# 3DGS fits a billboard from its k views only, so the ghost spreads along
# their rays.
# The billboard stands at 0.3-0.9 of the near scene depth (DEPTH_STAGES),
# so the nearest content behind it is >= 0.11 viewing distances away
# (0.9 -> 1.0 of the near depth) and most of it much further.
GHOST_DEPTH = 0.1
GHOST_MARGIN = 0.05


class PlacementError(ValueError):
  """No billboard placement is seen by every camera of a run."""


def camera_centre(rotation: np.ndarray, translation: np.ndarray):
  """float64 [3], C = -R^T t for world-to-camera (R [3, 3], t [3])."""
  return -rotation.T @ translation


def project(points, rotation, translation, intrinsics):
  """Pixel coordinates (centres at +0.5) and depths of world points.

  Args:
    points: float [P, 3], world coordinates.
    rotation, translation: float64 [3, 3], [3], world-to-camera.
    intrinsics: float64 [4], (fx, fy, cx, cy).

  Returns:
    (float64 [P, 2] (x, y), float64 [P] depth z in the camera).
  """
  cam = np.asarray(points, np.float64) @ rotation.T + translation
  z = cam[:, 2]
  safe = np.where(np.abs(z) > 1e-12, z, 1e-12)
  fx, fy, cx, cy = intrinsics
  return np.stack([fx * cam[:, 0] / safe + cx,
                   fy * cam[:, 1] / safe + cy], -1), z


def make_runs(num_train: int, k: int) -> list[list[int]]:
  """Runs of k consecutive training views: [0, k), [k, 2k), ...

  When k does not divide num_train, the last run is the last k views (it
  overlaps the one before), so every run has exactly k views and every
  view is in at least one run.
  """
  if not 1 <= k <= num_train:
    raise ValueError(f"--persist_views={k} must be in [1, {num_train}] (the "
                     "number of training views); pass e.g. 5.")
  starts = list(range(0, num_train - k + 1, k))
  if num_train % k:
    starts.append(num_train - k)
  return [list(range(s, s + k)) for s in starts]


def near_depth(points, rotation, translation, intrinsics, size) -> float:
  """NEAR_QUANTILE of the depths of the points a view sees (ValueError when
  it sees none)."""
  xy, z = project(points, rotation, translation, intrinsics)
  inside = ((z > 0) & (xy[:, 0] >= 0) & (xy[:, 0] <= size[0]) &
            (xy[:, 1] >= 0) & (xy[:, 1] <= size[1]))
  if not inside.any():
    raise ValueError("a training view sees none of the scene's SfM points, "
                     "so a billboard cannot be put in front of its "
                     "content; use --mode=independent for this scene.")
  return float(np.quantile(z[inside], NEAR_QUANTILE))


def _frame(rotations, translations, centre):
  """Unit right, down and normal (towards the cameras) of a billboard at
  `centre` facing cameras (R [k, 3, 3], t [k, 3])."""
  eyes = np.stack([camera_centre(r, t) for r, t in zip(rotations,
                                                       translations)])
  normal = eyes.mean(axis=0) - centre
  normal /= np.linalg.norm(normal)
  right = rotations[:, 0, :].mean(axis=0)        # mean camera x in world
  right -= (right @ normal) * normal
  right /= np.linalg.norm(right)
  down = np.cross(-normal, right)                # forward x right = down
  return right, down, normal


def place(rng: np.random.Generator, photo_size, rotations, translations,
          intrinsics, sizes, points) -> np.ndarray:
  """Random billboard seen by every camera of a run.

  Its size in the middle view follows `transient_photos.paste_size` (15-45 %
  of the height); its centre lies on the ray of a random pixel of the middle
  view at a depth from DEPTH_STAGES (fractions of that view's near scene
  depth).

  Args:
    rng: the run's generator.
    photo_size: (width, height) of the photo, for its aspect.
    rotations, translations: float64 [k, 3, 3], [k, 3], the run's cameras.
    intrinsics: float64 [k, 4]; sizes: int [k, 2] (width, height).
    points: float [P, 3], the scene's SfM points.

  Returns:
    float64 [4, 3], corners TL, TR, BR, BL in world coordinates.

  Raises:
    PlacementError: no try put it in every view.
    ValueError: the middle view sees no SfM point.
  """
  mid = len(rotations) // 2
  near = near_depth(points, rotations[mid], translations[mid],
                    intrinsics[mid], sizes[mid])
  for low, high, tries in DEPTH_STAGES:
    corners = _try_place(rng, photo_size, rotations, translations,
                         intrinsics, sizes, near, low, high, tries)
    if corners is not None:
      return corners
  raise PlacementError(
      f"could not place a billboard seen by all {len(sizes)} views of a run "
      f"in {TRIES} tries; pass a smaller --persist_views.")


def _try_place(rng, photo_size, rotations, translations, intrinsics, sizes,
               near, low, high, tries):
  """Corners [4, 3] of the first of `tries` random placements at depth
  low..high * near that every camera sees, or None."""
  mid = len(rotations) // 2
  rot, trans, (fx, fy, cx, cy) = rotations[mid], translations[mid], (
      intrinsics[mid])
  width, height = sizes[mid]
  for _ in range(tries):
    w_pix, h_pix = transient_photos.paste_size(rng, photo_size, width, height)
    depth = rng.uniform(low, high) * near
    px = rng.uniform(CENTRE_MARGIN, 1 - CENTRE_MARGIN) * width
    py = rng.uniform(CENTRE_MARGIN, 1 - CENTRE_MARGIN) * height
    ray = np.array([(px - cx) / fx, (py - cy) / fy, 1.0])
    centre = camera_centre(rot, trans) + depth * (rot.T @ ray)
    right, down, _ = _frame(rotations, translations, centre)
    half_w, half_h = 0.5 * w_pix * depth / fx, 0.5 * h_pix * depth / fy
    corners = centre + np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) @ (
        np.stack([half_w * right, half_h * down]))
    if all(_visible(corners, centre, r, t, k, s, near) for r, t, k, s in
           zip(rotations, translations, intrinsics, sizes)):
      return corners
  return None


def _visible(corners, centre, rotation, translation, intrinsics, size,
             near) -> bool:
  _, z = project(corners, rotation, translation, intrinsics)
  xy, _ = project(centre[None], rotation, translation, intrinsics)
  lo, hi = VISIBLE_MARGIN * size, (1 - VISIBLE_MARGIN) * size
  return bool(np.all(z > MIN_CORNER_DEPTH * near) and
              np.all(xy[0] >= lo) and np.all(xy[0] <= hi))


def texture_size(corners, rotation, translation, intrinsics):
  """(w, h) in pixels of the billboard's texture: its projected edge
  lengths in a view (the middle one of its run), so one texel ~ a pixel."""
  xy, _ = project(corners, rotation, translation, intrinsics)
  w = 0.5 * (np.linalg.norm(xy[1] - xy[0]) + np.linalg.norm(xy[2] - xy[3]))
  h = 0.5 * (np.linalg.norm(xy[3] - xy[0]) + np.linalg.norm(xy[2] - xy[1]))
  return max(2, int(round(w))), max(2, int(round(h)))


def _bilinear(tex: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
  """Samples tex [h, w, C] at texel coordinates (u, v) (centres at +0.5),
  zero outside."""
  h, w = tex.shape[:2]
  padded = np.pad(tex, ((1, 1), (1, 1), (0, 0)))
  x = np.clip(u - 0.5 + 1, 0, w + 1)
  y = np.clip(v - 0.5 + 1, 0, h + 1)
  x0 = np.minimum(np.floor(x).astype(np.int64), w)
  y0 = np.minimum(np.floor(y).astype(np.int64), h)
  fx, fy = (x - x0)[..., None], (y - y0)[..., None]
  return ((1 - fy) * ((1 - fx) * padded[y0, x0] + fx * padded[y0, x0 + 1]) +
          fy * ((1 - fx) * padded[y0 + 1, x0] + fx * padded[y0 + 1, x0 + 1]))


def render(view, corners, rgb, alpha, rotation, translation, intrinsics):
  """Composites a billboard over a view (no occlusion by the scene).

  Each pixel centre's ray meets the billboard's plane at (a, b) in [0, 1]^2
  (a along TL->TR, b along TL->BL); texture and alpha are sampled there
  (bilinear, premultiplied) and blended over the view.

  Args:
    view: float32 [H, W, 3].
    corners: float64 [4, 3], TL, TR, BR, BL.
    rgb: float32 [h, w, 3]; alpha: float32 [h, w], the billboard texture.
    rotation, translation, intrinsics: the view's camera.

  Returns:
    (float32 [H, W, 3] composite, float32 [H, W] the billboard's alpha).
  """
  height, width = view.shape[:2]
  full = np.zeros((height, width), np.float32)
  xy, z = project(corners, rotation, translation, intrinsics)
  if np.any(z <= 0):
    raise ValueError("billboard crosses the camera plane of a view it is "
                     "rendered into.")
  x0, y0 = np.maximum(np.floor(xy.min(axis=0)).astype(int), 0)
  x1 = min(int(np.ceil(xy[:, 0].max())), width)
  y1 = min(int(np.ceil(xy[:, 1].max())), height)
  if x1 <= x0 or y1 <= y0:
    return view, full
  fx, fy, cx, cy = intrinsics
  ys, xs = np.mgrid[y0:y1, x0:x1] + 0.5
  rays = np.stack([(xs - cx) / fx, (ys - cy) / fy, np.ones_like(xs)], -1)
  rays = rays @ rotation                          # R^T d, row vectors
  eye = camera_centre(rotation, translation)
  e_u, e_v = corners[1] - corners[0], corners[3] - corners[0]
  normal = np.cross(e_u, e_v)
  dist = (rays @ normal)
  s = ((corners[0] - eye) @ normal) / np.where(np.abs(dist) > 1e-12, dist,
                                               1e-12)
  hit = eye + s[..., None] * rays - corners[0]
  a = (hit @ e_u) / (e_u @ e_u)
  b = (hit @ e_v) / (e_v @ e_v)
  h, w = alpha.shape
  premul = np.concatenate([rgb * alpha[..., None], alpha[..., None]], -1)
  sample = _bilinear(premul, a * w, b * h) * (s > 0)[..., None]
  out = view.copy()
  patch_alpha = sample[..., 3]
  out[y0:y1, x0:x1] = sample[..., :3] + (1 - patch_alpha[..., None]) * (
      view[y0:y1, x0:x1])
  full[y0:y1, x0:x1] = patch_alpha
  return out.astype(np.float32), full


def on_billboard(points, corners, viewing_distance: float) -> np.ndarray:
  """bool [N]: the points that belong to the billboard's ghost.

  Args:
    points: float [N, 3], world positions (e.g. Gaussian means).
    corners: float [4, 3], the billboard's TL, TR, BR, BL.
    viewing_distance: float > 0, the mean distance from the cameras of the
      billboard's run to its centre (GHOST_DEPTH is a fraction of it).
  """
  corners = np.asarray(corners, np.float64)
  e_u, e_v = corners[1] - corners[0], corners[3] - corners[0]
  normal = np.cross(e_u, e_v)
  normal /= np.linalg.norm(normal)
  d = np.asarray(points, np.float64) - corners[0]
  a = (d @ e_u) / (e_u @ e_u)
  b = (d @ e_v) / (e_v @ e_v)
  inside = ((a >= -GHOST_MARGIN) & (a <= 1 + GHOST_MARGIN)
            & (b >= -GHOST_MARGIN) & (b <= 1 + GHOST_MARGIN))
  return inside & (np.abs(d @ normal) <= GHOST_DEPTH * viewing_distance)
