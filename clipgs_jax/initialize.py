"""Initial Gaussians from a sparse point cloud (or random points), packed
into a fixed capacity with an alive mask."""

import numpy as np

from clipgs_jax import config as config_lib
from clipgs_jax import gaussians
from clipgs_jax import sh

# Rows of the query block in the kNN search: the block's distance matrix is
# chunk x P float64 (about 80 MB at P = 20k), so memory stays bounded.
_KNN_CHUNK = 512
# Scale of a lone point (no neighbours), in scene units.
_LONE_POINT_SCALE = 0.01


def knn_mean_distance(points: np.ndarray, k: int = 3,
                      chunk: int = _KNN_CHUNK) -> np.ndarray:
  """float64 [P], mean Euclidean distance of each point to its k nearest
  other points (exact, chunked brute force: O(P^2 / chunk) passes).

  Duplicated points count as neighbours at distance 0. With fewer than k
  other points, all of them are used; a single point gets NaN.
  """
  pts = np.asarray(points, np.float64)
  # Centring shrinks |p|^2 and with it the cancellation in the expansion
  # |p - q|^2 = |p|^2 + |q|^2 - 2 p.q for close points far from the origin.
  pts = pts - pts.mean(axis=0) if len(pts) else pts
  n = pts.shape[0]
  k = min(k, n - 1)
  if k <= 0:
    return np.full((n,), np.nan)
  sq = np.sum(pts * pts, axis=1)
  out = np.empty((n,), np.float64)
  for start in range(0, n, chunk):
    q = pts[start:start + chunk]
    d2 = sq[start:start + chunk, None] + sq[None, :] - 2.0 * q @ pts.T
    # Exclude each point itself (its distance may round to a tiny non-zero).
    d2[np.arange(q.shape[0]), np.arange(start, start + q.shape[0])] = np.inf
    nearest = np.partition(d2, k - 1, axis=1)[:, :k]
    out[start:start + chunk] = np.mean(np.sqrt(np.maximum(nearest, 0.0)),
                                       axis=1)
  return out


def auto_capacity(num_points: int, cfg: config_lib.GaussiansConfig) -> int:
  """cfg.capacity, or (when 0) 2 x points rounded up to a power of two,
  at least min_capacity and at most max_capacity (but >= num_points)."""
  if cfg.capacity:
    return cfg.capacity
  want = max(2 * num_points, cfg.min_capacity, 1)
  cap = 1 << int(np.ceil(np.log2(want)))
  return max(min(cap, cfg.max_capacity), num_points)


def from_points(points: np.ndarray, colors: np.ndarray, capacity: int,
                cfg: config_lib.GaussiansConfig
                ) -> tuple[gaussians.GaussianParams, np.ndarray]:
  """Gaussians at `points` in the first P of `capacity` slots.

  Args:
    points: float [P, 3] world positions.
    colors: float [P, 3] RGB in [0, 1]; become the SH DC term.
    capacity: C >= P.
    cfg: sh_degree, init_opacity, init_min_scale, init_neighbors.

  Returns:
    GaussianParams with capacity C (dead rows zero, identity rotation) and
    bool [C] alive. Scales are isotropic: log of the mean distance to the
    `init_neighbors` nearest points, floored at init_min_scale.
  """
  points = np.asarray(points, np.float32)
  colors = np.asarray(colors, np.float32)
  if points.ndim != 2 or points.shape[1] != 3 or colors.shape != points.shape:
    raise ValueError(f"initialize.from_points: points and colors must both "
                     f"be [P, 3], got {points.shape} and {colors.shape}.")
  n = points.shape[0]
  if n == 0:
    raise ValueError("initialize.from_points: no points; use random_points "
                     "for a scene without a point cloud.")
  if n > capacity:
    raise ValueError(f"initialize: {n} points exceed capacity {capacity}; "
                     "raise GaussiansConfig.capacity (0 = automatic).")
  if not np.all(np.isfinite(points)):
    raise ValueError("initialize.from_points: points contain non-finite "
                     "values; clean the point cloud.")
  dist = knn_mean_distance(points, cfg.init_neighbors)
  dist = np.where(np.isnan(dist), _LONE_POINT_SCALE, dist)
  log_scale = np.log(np.maximum(dist, cfg.init_min_scale)).astype(np.float32)
  opacity = cfg.init_opacity
  logit = np.float32(np.log(opacity / (1.0 - opacity)))

  empty, _ = gaussians.empty(capacity, cfg.sh_degree)
  params = gaussians.GaussianParams(
      means=empty.means.at[:n].set(points),
      log_scales=empty.log_scales.at[:n].set(
          np.repeat(log_scale[:, None], 3, axis=1)),
      quats=empty.quats,                               # identity rotation
      opacity_logits=empty.opacity_logits.at[:n].set(logit),
      sh_dc=empty.sh_dc.at[:n].set(
          sh.rgb_to_dc(np.clip(colors, 0.0, 1.0))),
      sh_rest=empty.sh_rest)
  alive = np.zeros((capacity,), bool)
  alive[:n] = True
  return params, alive


def random_points(num: int, lo: np.ndarray, hi: np.ndarray, seed: int
                  ) -> tuple[np.ndarray, np.ndarray]:
  """float32 [num, 3] uniform points in the box [lo, hi] and random colours."""
  rng = np.random.default_rng(seed)
  lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
  points = lo + (hi - lo) * rng.random((num, 3))
  return points.astype(np.float32), rng.random((num, 3)).astype(np.float32)


def camera_box(centers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """Axis-aligned box of the camera centres [V, 3]; degenerate axes get
  the largest side's width so the box has volume."""
  lo, hi = centers.min(axis=0), centers.max(axis=0)
  side = max(float(np.max(hi - lo)), 1e-3)
  mid = 0.5 * (lo + hi)
  half = np.where(hi - lo > 1e-6 * side, 0.5 * (hi - lo), 0.5 * side)
  return mid - half, mid + half


def initialize(points: np.ndarray | None, colors: np.ndarray | None,
               camera_centers: np.ndarray, cfg: config_lib.GaussiansConfig,
               seed: int = 0
               ) -> tuple[gaussians.GaussianParams, np.ndarray]:
  """Initial Gaussians of a scene.

  Uses the scene's points when there are any; otherwise
  `cfg.random_init_points` uniform points inside the box spanned by the
  camera centres (an inward-facing capture surrounds its subject).
  """
  if points is None or len(points) == 0:
    points, colors = random_points(cfg.random_init_points,
                                   *camera_box(np.asarray(camera_centers)),
                                   seed)
  capacity = auto_capacity(len(points), cfg)
  return from_points(points, colors, capacity, cfg)
