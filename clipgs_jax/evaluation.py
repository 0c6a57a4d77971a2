"""Test-set evaluation of a Gaussian model: renders and image metrics."""

import functools
from typing import Any, Iterator

import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import camera as camera_lib
from clipgs_jax import compiled
from clipgs_jax import config as config_lib
from clipgs_jax import gaussians
from clipgs_jax import metrics as metrics_lib
from clipgs_jax import sharding
from clipgs_jax.data import canvas
from clipgs_jax.render import rasterize


# A pixel is predicted transient where the flagged Gaussians cover more than
# half of it: the same 0.5 cut that turns grey mask PNGs into booleans
# (data.scene.MASK_THRESHOLD).
MASK_ALPHA_THRESHOLD = 0.5


@functools.lru_cache(maxsize=None)
def _render_fn(render_cfg: config_lib.RenderConfig):
  def fn(params, alive, cam, bg, degree):
    out = rasterize.render(params, alive, cam, bg, render_cfg, degree)
    return jnp.clip(out.image, 0.0, 1.0), out.alpha, out.num_overflow
  return jax.jit(fn)


def render_camera(params: gaussians.GaussianParams, alive,
                  cam: camera_lib.Camera, cfg: config_lib.Config
                  ) -> jax.Array:
  """float32 [H, W, 3]: one camera's render with all SH bands on
  cfg.train.background, clipped to [0, 1]; one compile per image size."""
  cam = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), cam)
  return _render_fn(cfg.render)(
      params, alive, cam, jnp.asarray(cfg.train.background, jnp.float32),
      jnp.asarray(params.sh_degree, jnp.int32))[0]


def renders(params: gaussians.GaussianParams, alive, views,
            cfg: config_lib.Config) -> Iterator[tuple[jax.Array, ...]]:
  """Renders each view of `views` with all SH bands on cfg.train.background.

  A view on a larger canvas (data.scene.Views.sizes) is rendered on it and
  cut to its photo: a pixel's colour does not depend on the others, so the
  cut render is the photo-sized render.

  Yields:
    (float32 [h, w, 3] colour clipped to [0, 1], float32 [h, w] alpha,
    int32 [] tile-list entries dropped) per view, in order; (w, h) is the
    view's photo size (canvas.photo_size).
  """
  render = _render_fn(cfg.render)
  bg = jnp.asarray(cfg.train.background, jnp.float32)
  degree = jnp.asarray(params.sh_degree, jnp.int32)
  cams = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), views.cameras)
  for i in range(len(views.images)):
    image, alpha, dropped = render(params, alive,
                                   camera_lib.camera_at(cams, i), bg, degree)
    yield (canvas.crop(views, i, image), canvas.crop(views, i, alpha),
           dropped)


@functools.lru_cache(maxsize=None)
def _metrics_fn(lpips_net: str | None):
  if lpips_net is None:
    return jax.jit(lambda a, b: metrics_lib.image_metrics(a, b, None))
  # LPIPS has its own jit; the rest is cheap.
  return functools.partial(metrics_lib.image_metrics, lpips_net=lpips_net)


def evaluate(params: gaussians.GaussianParams, alive, views,
             cfg: config_lib.Config, *, lpips_net: str | None = None,
             psnr_only: bool = False, keep_images: bool = False
             ) -> dict[str, Any]:
  """Renders every view of `views` and scores it against its image.

  All SH bands are used and the background is cfg.train.background.
  Renders are clipped to [0, 1] before scoring.

  Returns:
    dict with per-image lists "psnr" (and "ssim", "lpips" unless
    psnr_only), their means "mean/<name>", and "images" (float32
    [V, H, W, 3] numpy; a list of [h, w, 3] when the photos differ in
    size) when keep_images.
  """
  per_image: dict[str, list[float]] = {"psnr": []}
  if not psnr_only:
    per_image["ssim"] = []
    if lpips_net is not None:
      per_image["lpips"] = []
  images = []
  for i, (pred, _, _) in enumerate(renders(params, alive, views, cfg)):
    target = jnp.asarray(canvas.crop(views, i, views.images[i]),
                         jnp.float32)
    if psnr_only:
      values = {"psnr": metrics_lib.psnr(pred, target)}
    else:
      values = _metrics_fn(lpips_net)(pred[None], target[None])
    for name in per_image:
      per_image[name].append(float(np.asarray(values[name]).reshape(())))
    if keep_images:
      images.append(np.asarray(pred))
  result: dict[str, Any] = dict(per_image)
  for name, vals in per_image.items():
    result[f"mean/{name}"] = float(np.mean(vals)) if vals else float("nan")
  if keep_images:
    if getattr(views, "sizes", None) is not None:
      result["images"] = images
    else:
      result["images"] = (np.stack(images) if images else
                          np.zeros((0, views.cameras.height,
                                    views.cameras.width, 3), np.float32))
  return result


def mask_iou(alpha, mask, threshold: float = MASK_ALPHA_THRESHOLD
             ) -> float | None:
  """IoU of (alpha > threshold) against a ground-truth mask.

  Args:
    alpha: float [H, W], rendered opacity in [0, 1].
    mask: bool [H, W], True = transient pixel.
    threshold: float, alpha above which a pixel counts as predicted.

  Returns:
    float in [0, 1], or None when both are empty (the IoU is undefined).
  """
  alpha, mask = np.asarray(alpha), np.asarray(mask, bool)
  if alpha.shape != mask.shape:
    raise ValueError(f"mask_iou: alpha is {alpha.shape}, mask {mask.shape}.")
  pred = alpha > threshold
  union = np.count_nonzero(pred | mask)
  if union == 0:
    return None
  return np.count_nonzero(pred & mask) / union


def iou_summary(names, alphas, masks) -> dict:
  """Per-view and mean IoU over the views where it is defined.

  Args:
    names: V view names.
    alphas: V float [H, W], rendered alpha of the flagged Gaussians.
    masks: V bool [H, W], ground-truth transient masks (each the shape of
      its alpha).

  Returns:
    {"mean": float, or None if no view is scored, "per_view": {name: IoU
    or None}, "num_views_scored": int, "alpha_threshold": float}.
  """
  per_view = {n: mask_iou(a, m) for n, a, m in zip(names, alphas, masks)}
  scored = [v for v in per_view.values() if v is not None]
  return {"mean": float(np.mean(scored)) if scored else None,
          "per_view": per_view, "num_views_scored": len(scored),
          "alpha_threshold": MASK_ALPHA_THRESHOLD}


def transient_mask_iou(params: gaussians.GaussianParams, views,
                       cfg: config_lib.Config) -> dict | None:
  """IoU of a Gaussian subset's rendered alpha against the views' masks.

  Used for the Gaussians a run's semantic prune removed (loop.FitResult.
  pruned): rendered alone into every training view, how well do they cover
  the ground-truth transients?

  Args:
    params: numpy GaussianParams of the subset (every row is rendered).
    views: data.scene.Views with masks.
    cfg: the run's config (render settings, background).
  Returns:
    iou_summary's dict plus "num_gaussians", or None when the views have
    no masks.
  """
  if views.masks is None:
    return None
  num = int(np.shape(params.means)[0])
  masks = [canvas.crop(views, i, m) for i, m in enumerate(views.masks)]
  if num == 0:
    alphas = [np.zeros(np.shape(m), np.float32) for m in masks]
  else:
    # Pad to a power of two so runs with similar counts share one compile.
    capacity = 1 << max(8, (num - 1).bit_length())
    padded = jax.tree.map(
        lambda x: np.concatenate(
            [x, np.zeros((capacity - num,) + x.shape[1:], x.dtype)]), params)
    alive = np.arange(capacity) < num
    alphas = [np.asarray(a) for _, a, _ in
              renders(padded, alive, views, cfg)]
  return iou_summary(views.names, alphas, masks) | {
      "num_gaussians": num}


# A map pixel counts as transient above this (maps are probabilities).
MAP_THRESHOLD = 0.5


@functools.lru_cache(maxsize=None)
def _view_map_fn(cfg: config_lib.Config, stages: bool = False):
  """Jitted (params, alive, stats, scorer, view, cam, photo, degree, valid)
  -> the map the loss would use for that training view now, or with
  `stages` the residual map after each of its steps
  (sources.residual_stages); `valid` as sources.residual_map's."""
  from clipgs_jax.maps import sources  # pylint: disable=g-import-not-at-top
  map_fn = sources.residual_stages if stages else sources.view_map

  def fn(params, alive, stats, scorer, view, cam, photo, degree, valid):
    bg = jnp.asarray(cfg.train.background, jnp.float32)
    out = rasterize.render(params, alive, cam, bg, cfg.render, degree)
    return map_fn(scorer, stats, view, out.image, out.alpha, photo,
                  cfg.residual, valid)
  return jax.jit(fn)


def view_map(params: gaussians.GaussianParams, alive, stats, scorer, views,
             index: int, cfg: config_lib.Config, degree,
             stages: bool = False):
  """float32 [H, W] in [0, 1], the transient map m a training step on view
  `index` of `views` would use now (mask_quality's arguments); with
  `stages` (a sources.ResidualSource only), {step name: the residual
  map after that step}, the last being m."""
  # The one camera, not every view's, moves to the device per call.
  cam = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32),
                     camera_lib.camera_at(views.cameras, index))
  photo = jnp.asarray(views.images[index], jnp.float32)
  # A photo on a larger canvas: the step's map sees its pixels only.
  valid = None
  if getattr(views, "sizes", None) is not None:
    valid = sharding.valid_mask(jnp.asarray(views.sizes[index]),
                                photo.shape[0], photo.shape[1])
  out = _view_map_fn(compiled.compiled_part(cfg), stages)(
      params, alive, stats, scorer, jnp.int32(index), cam, photo, degree,
      valid)
  return jax.tree.map(np.asarray, out)


def mask_quality(params: gaussians.GaussianParams, alive, stats, scorer,
                 views, cfg: config_lib.Config, degree) -> dict | None:
  """How well the transient maps the loss uses match the ground truth.

  For every training view: the map m that a training step on it would use
  now (for the residual map, from the current model's render of the view;
  static maps as they are), thresholded at MAP_THRESHOLD, against the
  view's ground-truth mask.

  Args:
    params, alive: the current model.
    stats: TrainState.maps (the residual statistics, or None).
    scorer: the run's pixel scorer (guidance.PixelMapScorer or
      sources.ResidualSource).
    views: the training Views, with masks.
    cfg: the run's config.
    degree: int32 [], the SH degree the steps use now.
  Returns:
    {"precision", "recall", "iou" (pixels pooled over all views; None where
    undefined), "per_view": {name: {"precision", "recall", "iou"}}}, or
    None when the views have no masks.
  """
  if views.masks is None:
    return None
  totals = np.zeros(3, np.int64)
  per_view = {}
  for name, m, truth in training_maps(params, alive, stats, scorer, views,
                                      cfg, degree):
    counts = confusion(m > MAP_THRESHOLD, truth)
    totals += counts
    per_view[name] = confusion_scores(counts)
  return confusion_scores(totals) | {"per_view": per_view,
                            "map_threshold": MAP_THRESHOLD}


def training_maps(params: gaussians.GaussianParams, alive, stats, scorer,
                  views, cfg: config_lib.Config, degree,
                  stages: bool = False):
  """Yields (name, map, truth) for every training view in order: view_map
  cropped to the view's photo (with `stages`, its dict of step maps, each
  cropped), and its ground-truth mask (bool, cropped), or None when the
  views have no masks (mask_quality's arguments)."""
  for i, name in enumerate(views.names):
    m = jax.tree.map(lambda x, i=i: canvas.crop(views, i, x), view_map(
        params, alive, stats, scorer, views, i, cfg, degree, stages))
    truth = (None if views.masks is None else
             canvas.crop(views, i, np.asarray(views.masks[i], bool)))
    yield name, m, truth


def confusion(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
  """int64 [3]: true positives, false positives, false negatives."""
  return np.array([np.count_nonzero(pred & truth),
                   np.count_nonzero(pred & ~truth),
                   np.count_nonzero(~pred & truth)], np.int64)


def confusion_scores(counts) -> dict[str, float | None]:
  """precision, recall and IoU of confusion counts (None where undefined)."""
  tp, fp, fn = (int(c) for c in counts)
  ratio = lambda a, b: a / b if b else None
  return {"precision": ratio(tp, tp + fp), "recall": ratio(tp, tp + fn),
          "iou": ratio(tp, tp + fp + fn)}
