"""How far a transient map could reach on a finished run, with the truth.

Three tests of each training pixel, scored against the ground-truth masks
(precision, recall, IoU over all training views), to tell a map's failure
from its inputs' limit:
  * "features": the learned map's classifier (learned.predict on
    features.pixel_features, the run's LearnedConfig) trained offline on
    the ground-truth masks of every training view, balanced as the online
    one is: the most its features can tell, with perfect labels. Also the
    precision where its ranking reaches RECALL_TARGET of the transients.
  * "multiview": photo consistency on the run's own geometry. Each pixel's
    rendered surface point (depth, alpha > 0.5) is projected into every
    other training view; a view sees it where that view's rendered depth
    there is within DEPTH_TOLERANCE (relative) of the point's; the pixel
    is transient when at least MIN_SEEN views see it and more than half of
    them hold a colour that differs from its own by over the colour
    tolerance (mean |difference| over channels; a few tolerances). Alone,
    and intersected with the residual over its median.
  * "memory" (a run with residual.remember): the pixels its memory holds,
    and those left after a multi-view release lets go of the held pixels
    that at least MIN_SEEN views see and no majority disagrees with.
  * "residual": the final model's residual over its RESIDUAL_QUANTILE
    quantile (the residual map's default quantile, without its gates).
"""

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import camera as camera_lib
from clipgs_jax import evaluation
from clipgs_jax import fileio
from clipgs_jax import run as run_lib
from clipgs_jax.maps import features
from clipgs_jax.maps import learned
from clipgs_jax.render import rasterize

MAP_LIMITS_JSON = "map_limits.json"
FIT_STEPS = 3000            # one view per Adam step, as the online fit
RECALL_TARGET = 0.75        # the recall a photos-only map is asked for
#   (BUILD_NOTES.md, "Transient masks without an oracle")
DEPTH_TOLERANCE = 0.05      # |z_j - depth_j| < this x z_j: view j sees it
COLOUR_TOLERANCES = (0.05, 0.1, 0.2)
MIN_SEEN = 3
RESIDUAL_QUANTILE = 0.7


def scores(pred: np.ndarray, truth: np.ndarray) -> dict:
  """precision, recall and IoU of bool maps against bool truth."""
  return evaluation.confusion_scores(evaluation.confusion(pred, truth))


def precision_at_recall(score: np.ndarray, truth: np.ndarray,
                        recall: float) -> float:
  """The precision of the fewest top-scored pixels that hold `recall` of
  the true ones (ties broken by order)."""
  ranked = truth.reshape(-1)[np.argsort(-score.reshape(-1), kind="stable")]
  hits = np.cumsum(ranked)
  k = int(np.searchsorted(hits, recall * hits[-1]))
  return float(hits[k] / (k + 1))


def fit_classifier(feats: np.ndarray, truth: np.ndarray, lc,
                   steps: int = FIT_STEPS, seed: int = 0) -> np.ndarray:
  """float32 [V, H, W], the transient probability 1 - p of the learned
  map's classifier (learned.init, learned.loss, learned.apply) fitted to
  the true masks: one random view a step, every pixel labelled (inlier or
  outlier, none between), the classes weighed as the online fit weighs
  them (lc.balance)."""
  f = jnp.asarray(feats)
  inlier = 1.0 - jnp.asarray(truth, jnp.float32)

  @jax.jit
  def step(clf, i):
    grads = jax.grad(learned.loss)(clf.params, f[i], inlier[i], inlier[i],
                                   lc)
    return learned.apply(clf, grads, lc, 1)

  clf = learned.init(lc, jax.random.PRNGKey(seed))
  for i in np.random.default_rng(seed).integers(0, len(feats), steps):
    clf = step(clf, i)
  predict = jax.jit(jax.vmap(lambda x: learned.predict(clf.params, x)))
  return 1.0 - np.asarray(predict(f))


def _bilinear(image, u, v):
  """image [H, W, ...] at pixel coordinates (u, v) (centres at +0.5),
  clamped to the border."""
  h, w = image.shape[:2]
  x, y = u - 0.5, v - 0.5
  x0 = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, w - 2)
  y0 = jnp.clip(jnp.floor(y).astype(jnp.int32), 0, h - 2)
  ax, ay = jnp.clip(x - x0, 0, 1), jnp.clip(y - y0, 0, 1)
  if image.ndim == 3:
    ax, ay = ax[..., None], ay[..., None]
  return (image[y0, x0] * (1 - ax) * (1 - ay) + image[y0, x0 + 1] * ax
          * (1 - ay) + image[y0 + 1, x0] * (1 - ax) * ay
          + image[y0 + 1, x0 + 1] * ax * ay)


@functools.partial(jax.jit, static_argnums=5)
def views_seeing(photos, depths, alphas, cameras, i, colour_tolerances):
  """How many other views see each of view i's surface points, int [H, W],
  and how many of those hold a colour that differs from its own by over
  each of `colour_tolerances`, int [T, H, W] (one projection for all).

  Args:
    photos: float [V, H, W, 3]; depths, alphas: float [V, H, W], the
      renders' expected depth and alpha; cameras: camera.Camera stacked
      [V] (one canvas size); i: int [], the view; colour_tolerances: a
      tuple of T floats (static).
  """
  _, h, w = depths.shape
  rot, trans = cameras.rotation, cameras.translation
  fx, fy, cx, cy = cameras.fx, cameras.fy, cameras.cx, cameras.cy
  u, v = jnp.meshgrid(jnp.arange(w) + 0.5, jnp.arange(h) + 0.5)
  z = depths[i]
  local = jnp.stack([(u - cx[i]) / fx[i] * z, (v - cy[i]) / fy[i] * z, z],
                    -1)
  world = jnp.einsum("ji,hwj->hwi", rot[i], local - trans[i])
  surface = alphas[i] > 0.5

  def other(j):
    p = jnp.einsum("ij,hwj->hwi", rot[j], world) + trans[j]
    zj = p[..., 2]
    uj = fx[j] * p[..., 0] / zj + cx[j]
    vj = fy[j] * p[..., 1] / zj + cy[j]
    inside = ((zj > 0) & (uj > 0.5) & (uj < w - 0.5) & (vj > 0.5)
              & (vj < h - 0.5))
    seen = (inside & surface & (j != i)
            & (jnp.abs(zj - _bilinear(depths[j], uj, vj))
               < DEPTH_TOLERANCE * zj)
            & (_bilinear(alphas[j], uj, vj) > 0.5))
    differ = jnp.mean(jnp.abs(_bilinear(photos[j], uj, vj) - photos[i]), -1)
    return seen, jnp.stack([seen & (differ > t) for t in colour_tolerances])

  seen, differs = jax.lax.map(other, jnp.arange(depths.shape[0]))
  return seen.sum(0), differs.sum(0)


def disagrees(seen, differs, min_seen: int = MIN_SEEN):
  """bool [H, W]: the pixels that more than half of the (at least
  `min_seen`) other views seeing their surface point disagree with
  (views_seeing's counts)."""
  return (seen >= min_seen) & (2 * differs > seen)


def released(held, seen, differs, min_seen: int = MIN_SEEN):
  """bool [H, W], the held pixels a multi-view release lets go: at least
  `min_seen` other views see the surface point and no more than half of
  them disagree with its colour (a held pixel too few views see cannot
  be tested and stays held)."""
  return held & (seen >= min_seen) & ~disagrees(seen, differs, min_seen)


def _renders(state, cfg, views):
  """float32 [V, H, W, 3] colours, [V, H, W] depths and alphas."""
  bg = jnp.asarray(cfg.train.background, jnp.float32)
  # The model is an argument, not a constant of the trace: closed over, XLA
  # spends seconds constant-folding it.
  render = jax.jit(lambda params, alive, cam: rasterize.render(
      params, alive, cam, bg, cfg.render))
  outs = [render(state.params, state.alive,
                 camera_lib.camera_at(views.cameras, i))
          for i in range(len(views))]
  return tuple(np.stack([np.asarray(getattr(o, k)) for o in outs])
               for k in ("image", "depth", "alpha"))


def map_limits_report(workdir: str) -> dict:
  """Writes MAP_LIMITS_JSON into a finished run folder and returns it:
  {"features": {"scores", "precision_at_recall"}, "multiview":
  {tolerance: {"alone", "with_residual"}}, "residual": scores}, and for a
  remembered run "memory": {"alone": scores, "release": {tolerance:
  scores}} (the held pixels, and those a multi-view release keeps).

  Raises:
    ValueError: the scene has no ground-truth masks, or photos of
      different sizes (the projections assume one canvas).
  """
  _, cfg, scene, state = run_lib.load_state(workdir)
  views = scene.train
  if views.masks is None or views.sizes is not None:
    raise ValueError(
        f"{scene.path}: map limits need ground-truth masks (masks/) and "
        "photos of one size; pass a run of a benchmark scene.")
  truth = views.masks
  colours, depths, alphas = _renders(state, cfg, views)
  res = np.abs(colours - views.images).mean(-1)
  over_median = res > np.quantile(res, 0.5)
  out = {"residual": scores(res > np.quantile(res, RESIDUAL_QUANTILE),
                            truth), "multiview": {}}
  cams = jax.tree.map(jnp.asarray, views.cameras)
  photos, depths, alphas = (jnp.asarray(x) for x in
                            (views.images, depths, alphas))
  # A remembered run (residual.remember): its held pixels alone, and less
  # what a multi-view release would let go.
  held = (None if state.maps.memory is None
          else np.asarray(state.maps.memory))
  if held is not None:
    out["memory"] = {"alone": scores(held, truth), "release": {}}
  seeing = [tuple(map(np.asarray, views_seeing(photos, depths, alphas, cams,
                                               i, COLOUR_TOLERANCES)))
            for i in range(len(views))]
  for t, tol in enumerate(COLOUR_TOLERANCES):
    counts = [(seen, differs[t]) for seen, differs in seeing]
    mv = np.stack([disagrees(*c) for c in counts])
    out["multiview"][str(tol)] = {"alone": scores(mv, truth),
                                  "with_residual": scores(mv & over_median,
                                                          truth)}
    if held is not None:
      kept = np.stack([h & ~released(h, *c) for h, c in zip(held, counts)])
      out["memory"]["release"][str(tol)] = scores(kept, truth)
  lc = cfg.learned
  prob = fit_classifier(
      np.stack(features.pixel_features(views.images, lc.net, lc.dims)),
      truth, lc)
  out["features"] = {"scores": scores(prob > evaluation.MAP_THRESHOLD, truth),
                     "precision_at_recall": precision_at_recall(
                         prob, truth, RECALL_TARGET)}
  fileio.write_json(os.path.join(workdir, MAP_LIMITS_JSON), out)
  return out


def summary(out: dict) -> list[str]:
  """`map_limits_report`'s dict as lines of P / R / IoU."""
  def line(s):
    return " / ".join("-" if s[k] is None else f"{s[k]:.2f}"
                      for k in ("precision", "recall", "iou"))
  f = out["features"]
  lines = ["P / R / IoU against the ground truth, all training views:",
           f"  residual over its {RESIDUAL_QUANTILE} quantile: "
           f"{line(out['residual'])}",
           f"  learned map's classifier fitted to the truth: "
           f"{line(f['scores'])}; P {f['precision_at_recall']:.2f} at R "
           f"{RECALL_TARGET}"]
  for tol, m in out["multiview"].items():
    lines.append(f"  multi-view consistency, colour tolerance {tol}: "
                 f"{line(m['alone'])}; with the residual over its median "
                 f"{line(m['with_residual'])}")
  if "memory" in out:
    lines.append(f"  the map's memory: {line(out['memory']['alone'])}")
    for tol, m in out["memory"]["release"].items():
      lines.append(f"    less a multi-view release, colour tolerance {tol}: "
                   f"{line(m)}")
  return lines
