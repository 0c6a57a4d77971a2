"""Where a training step's per-pixel transient map m comes from.

Static sources give one map per training view before training (the
ground-truth mask, ORACLE-PATCH, dense CLIP: guidance.PixelMapScorer); the
step hands the view's map to the rasterizer, which sums it per Gaussian in
the render's own pass. The residual source (`ResidualSource`) computes m
inside the step from the step's own render and photo (residual.py), with
running statistics in TrainState.maps; the render cannot read a map that
depends on it, so the per-Gaussian sums come from the backward pass through
the rasterizer's evidence probe (rasterize.rasterize). The combination of
the residual map with a semantic map (the residual test, kept only where
the semantic map calls the pixel transient) is the residual source with a
static map to intersect.
"""

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import guidance_config
from clipgs_jax.maps import features
from clipgs_jax.maps import learned
from clipgs_jax.maps import residual

# The combination rule: a pixel the residual test calls transient stays
# transient only where the semantic map's p(transient) exceeds this.
SEMANTIC_GATE = 0.5
# The learned map calls a pixel transient where p(inlier) is under this.
# The map is this verdict, 0 or 1, as the residual map: the evidence and
# the opacity loss read it. Read soft, 1 - p (0.02-0.05 on every static
# pixel of bird persistent at step 500) gave every Gaussian a small s_j,
# and Adam's normalised opacity steps took the whole model down (test
# PSNR 16.4 -> 9.5 from reg_start); the loss keeps SLS-mlp's soft weight.
LEARNED_CUT = 0.5

# The residual map's steps in the order they apply (_test's, then _gates');
# a map skips the steps its source and config do not have.
STAGES = ("threshold", "rule", "learned", "vote", "semantic", "alpha",
          "valid", "share", "memory")


@flax.struct.dataclass
class ResidualSource:
  """The residual map's scorer: what it reads besides the step's render.

  Attributes:
    semantic: float32 [V, H, W] in [0, 1] or None: per-view semantic maps
      (dense CLIP, ORACLE-PATCH) that gate the residual test.
    labels: int32 [V, H, W] or None: each training photo's feature regions
      (features.regions), which take the majority verdict of the residual
      test inside them.
    num_regions: the regions' label count (static).
    pixel_features: float32 [V, H, W, F] or None: each training photo's
      per-pixel features (features.pixel_features); given, the map is the
      learned map, transient where the classifier's p(inlier) <
      LEARNED_CUT (the classifier is TrainState.maps.classifier), voted
      over the regions if any.
  """
  semantic: jax.Array | None = None
  labels: jax.Array | None = None
  num_regions: int = flax.struct.field(pytree_node=False, default=0)
  pixel_features: jax.Array | None = None
  # One entry per view (sharding.py).
  per_view = ("semantic", "labels", "pixel_features")


@flax.struct.dataclass
class ResidualMap:
  """One step's residual map.

  Attributes:
    transient: float32 [H, W] in {0, 1}, the map m (1 = transient).
    loss_weight: float32 [H, W] in [0, 1], the per-pixel weight of the
      photometric loss: 1 - m (the learned map: p(inlier) where m is 0),
      with the warm-up's sampled pixels kept.
    residual: float32 [H, W], mean_c |render - photo|.
  """
  transient: jax.Array
  loss_weight: jax.Array
  residual: jax.Array


def _test(source: ResidualSource, stats: residual.ResidualState,
          view: jax.Array, res: jax.Array, rc: guidance_config.ResidualConfig,
          valid: jax.Array | None) -> dict[str, jax.Array]:
  """The residual test's steps, each float32 [H, W] in {0, 1} (1 =
  transient so far), in order: "threshold" (the residual at or above the
  threshold), "rule" (the 3x3 or patch rule: residual.inliers), with pixel
  features "learned" (the classifier's p(inlier) < LEARNED_CUT, which
  replaces the rule's verdict) and, with feature regions, "vote" (each
  region's majority); the last is the test's verdict."""
  steps = {"threshold": (res >= stats.threshold).astype(jnp.float32)}
  inlier = residual.inliers(res, stats.threshold, rc.rule, valid)
  steps["rule"] = 1.0 - inlier
  if source.pixel_features is not None:
    p = _inlier_probability(source, stats, view, valid)
    inlier = (p >= LEARNED_CUT).astype(jnp.float32)
    steps["learned"] = 1.0 - inlier
    if valid is not None:
      # Outside the photo: neither inlier nor transient, as the rule's.
      inlier, steps["learned"] = inlier * valid, steps["learned"] * valid
  if source.labels is not None:
    steps["vote"] = features.vote(inlier, source.labels[view],
                                  source.num_regions, rc.vote)
  return steps


def _inlier_probability(source: ResidualSource,
                        stats: residual.ResidualState, view: jax.Array,
                        valid: jax.Array | None) -> jax.Array:
  """float32 [H, W], the learned map's p(inlier), 1 outside the photo."""
  p = learned.predict(stats.classifier.params, source.pixel_features[view])
  return p if valid is None else 1.0 - (1.0 - p) * valid


def _gates(source: ResidualSource, view: jax.Array,
           rc: guidance_config.ResidualConfig, valid: jax.Array | None,
           alpha: jax.Array | None) -> dict[str, jax.Array]:
  """The gates a transient pixel must pass, float [H, W] in {0, 1} each
  (1 = it may be transient), in the order they apply: "semantic" (p >
  SEMANTIC_GATE), "alpha" (the render covers it, by pixel or by region),
  "valid" (inside the photo)."""
  gates = {}
  if source.semantic is not None:
    gates["semantic"] = (source.semantic[view] > SEMANTIC_GATE).astype(
        jnp.float32)
  if rc.min_alpha > 0:
    if alpha is None:
      raise ValueError("residual_map: residual.min_alpha = "
                       f"{rc.min_alpha} needs the render's alpha.")
    covered = (alpha > rc.min_alpha).astype(jnp.float32)
    if source.labels is not None:
      covered = 1.0 - features.vote(covered, source.labels[view],
                                    source.num_regions)
    gates["alpha"] = covered
  if valid is not None:
    gates["valid"] = valid
  return gates


def _marks_enough(transient: jax.Array, valid: jax.Array | None,
                  rc: guidance_config.ResidualConfig) -> jax.Array:
  """float32 [], 1 where `transient` marks at least
  rc.min_share of the photo's pixels, else 0 (the view is taken
  as clean)."""
  area = jnp.size(transient) if valid is None else jnp.sum(valid)
  return (jnp.sum(transient) >= rc.min_share * area).astype(
      jnp.float32)


def residual_map(source: ResidualSource,
                 stats: residual.ResidualState,
                 view: jax.Array,
                 render: jax.Array,
                 photo: jax.Array,
                 step: jax.Array,
                 key: jax.Array,
                 rc: guidance_config.ResidualConfig,
                 valid: jax.Array | None = None,
                 alpha: jax.Array | None = None) -> ResidualMap:
  """The transient map of training view `view` at `step`.

  Args:
    source: the scorer (ResidualSource).
    stats: the running residual statistics (TrainState.maps).
    view: int32 [], the view's index.
    render: float [H, W, 3], the step's render (no gradient flows).
    photo: float [H, W, 3], the view's photo.
    step: int32 [], finished steps.
    key: the step's PRNG key for the warm-up's sampling.
    rc: the residual map's settings.
    valid: None, or float [H, W] in {0, 1}, the photo's pixels on a larger
      canvas: the pixels outside are neither transient nor static (0 in
      both maps' masks; residual.counts leaves them out).
    alpha: float [H, W], the render's alpha; needed when
      rc.min_alpha > 0: a pixel is transient only where alpha
      exceeds it, or, with feature regions, only in a region where most
      pixels' alpha does (the gate follows the region, as the vote does).
  A map that, after these gates, marks less than rc.min_share of
  the photo's pixels is empty, and the view's loss keeps every pixel.
  Raises:
    ValueError: rc.min_alpha > 0 and no alpha.
  """
  res = residual.residual(render, photo)
  transient = list(_test(source, stats, view, res, rc, valid).values())[-1]
  if source.pixel_features is None:
    kept = residual.sample_inliers(1.0 - transient, step, key,
                                   rc.warmup)
    dropped = 1.0 - kept
  else:
    # SLS-mlp weights the loss by p, a transient pixel's by 0; the warm-up
    # keeps its sampled pixels whole.
    weight = (1.0 - transient) * _inlier_probability(source, stats, view,
                                                     valid)
    kept = residual.sample_inliers(jnp.zeros_like(transient), step, key,
                                   rc.warmup)
    dropped = (1.0 - weight) * (1.0 - kept)
  for gate in _gates(source, view, rc, valid, alpha).values():
    transient, dropped = transient * gate, dropped * gate
  if rc.min_share > 0:
    big = _marks_enough(transient, valid, rc)
    transient, dropped = transient * big, dropped * big
  return ResidualMap(transient=transient, loss_weight=1.0 - dropped,
                     residual=res)


def held_back(rmap: ResidualMap, source: ResidualSource, view: jax.Array,
              step: jax.Array,
              rc: guidance_config.ResidualConfig) -> ResidualMap:
  """`rmap` as the step that starts at `step` uses it: empty (no pixel
  transient, every pixel in the loss) before rc.start; with
  feature regions and rc.uniformity, before
  rc.uniform_until only the regions whose residual is uniform
  (features.uniform) stay transient. The evaluation maps (view_map, mask
  quality) are the test's own map, which the step uses from then on."""
  uniform = rc.uniformity > 0 and source.labels is not None
  if not rc.start and not uniform:
    return rmap
  on = (step >= rc.start).astype(jnp.float32)
  if uniform:
    even = features.uniform(rmap.residual, source.labels[view],
                            source.num_regions, rc.uniformity)
    on = on * jnp.where(step < rc.uniform_until, even, 1.0)
  return rmap.replace(transient=rmap.transient * on,
                      loss_weight=1.0 - on * (1.0 - rmap.loss_weight))


def remember(rmap: ResidualMap, memory: jax.Array, step: jax.Array,
             rc: guidance_config.ResidualConfig
             ) -> tuple[ResidualMap, jax.Array]:
  """`rmap` with its view's memory, and the view's memory after this visit.

  A pixel the view's map has marked stays transient (out of the loss, in
  the evidence) whatever the step's own map says: the fit learns a
  transient the map misses, and the test then passes it. The memory
  records from step rc.uniform_until: before it the early render's smear
  makes false positives that it would keep.

  Args:
    rmap: the step's map (after held_back).
    memory: bool [H, W], the view's memory (ResidualState.memory[view]).
    step: int32 [], finished steps.
    rc: the residual map's settings.
  Returns:
    (the map the step uses, bool [H, W] the view's new memory).
  """
  marked = (rmap.transient > 0) & (step >= rc.uniform_until)
  return (rmap.replace(transient=_held(rmap.transient, memory),
                       loss_weight=rmap.loss_weight
                       * (1.0 - memory.astype(jnp.float32))),
          memory | marked)


def _held(transient: jax.Array, memory: jax.Array) -> jax.Array:
  """float32 [H, W], `transient` with the pixels `memory` (bool [H, W])
  holds marked too."""
  return jnp.maximum(transient, memory.astype(jnp.float32))


def residual_stages(source: ResidualSource,
                    stats: residual.ResidualState,
                    view: jax.Array,
                    render: jax.Array,
                    alpha: jax.Array,
                    photo: jax.Array,
                    rc: guidance_config.ResidualConfig,
                    valid: jax.Array | None = None) -> dict[str, jax.Array]:
  """Where the residual map's transient pixels go: {step: the map after
  it}, float32 [H, W] in {0, 1}, for the steps of STAGES the map has; the
  last of them in STAGES' order is view_map's map (the warm-up samples
  only the loss weight; "memory" holds what the view's memory does:
  remember). Arguments as residual_map's."""
  res = residual.residual(render, photo)
  stages = _test(source, stats, view, res, rc, valid)
  transient = list(stages.values())[-1]
  for name, gate in _gates(source, view, rc, valid, alpha).items():
    transient = stages[name] = transient * gate
  if rc.min_share > 0:
    transient = stages["share"] = transient * _marks_enough(transient, valid,
                                                            rc)
  if stats.memory is not None:
    stages["memory"] = _held(transient, stats.memory[view])
  return stages


def in_stage_order(stages: dict) -> dict:
  """`stages` (residual_stages' dict, or any dict keyed by its steps) in
  STAGES' order, the last being the map: jax's pytrees (jit outputs,
  jax.tree.map) sort dict keys, which loses it."""
  return {k: stages[k] for k in STAGES if k in stages}


def learned_features(images, lc, sizes=None) -> jax.Array:
  """float32 [V, H, W, F], every training photo's per-pixel features for
  the learned map (features.pixel_features, once per photo); with `sizes`
  (int [V, 2]) each photo's alone, 0 on the canvas around it."""
  if sizes is None:
    return jnp.asarray(np.stack(
        features.pixel_features(images, lc.net, lc.dims)))
  feats = features.pixel_features(
      [im[:h, :w] for im, (w, h) in zip(images, sizes)], lc.net, lc.dims)
  out = np.zeros(np.shape(images)[:3] + (feats[0].shape[-1],), np.float32)
  for o, f in zip(out, feats):
    o[:f.shape[0], :f.shape[1]] = f
  return jnp.asarray(out)


def feature_regions(images, net: str, sizes=None) -> tuple[jax.Array, int]:
  """(int32 [V, H, W] regions of every training photo, label count), from
  the `net` backbone's features (features.regions, once per photo).

  With `sizes` (int [V, 2], photos on a larger canvas) each photo is
  clustered alone and the canvas around it is one more region, the last
  label, whose verdict no map reads (it is outside the photo).
  """
  clustering = features.Clustering(net=net)
  if sizes is None:
    labels = np.stack([features.regions(im, clustering) for im in images])
    return jnp.asarray(labels, jnp.int32), clustering.num_regions
  num = clustering.num_regions
  labels = np.full(np.shape(images)[:3], num, np.int32)
  for label, im, (w, h) in zip(labels, images, sizes):
    label[:h, :w] = features.regions(im[:h, :w], clustering)
  return jnp.asarray(labels), num + 1


def _pool_matrix(n: int, cells: int) -> np.ndarray:
  """float64 [cells, n]: row k averages the pixels of the k-th of `cells`
  equal spans of n pixels, each pixel weighted by its overlap."""
  edges = np.arange(cells + 1) * (n / cells)
  lo, hi = edges[:-1, None], edges[1:, None]
  px = np.arange(n)[None, :]
  overlap = np.clip(np.minimum(hi, px + 1) - np.maximum(lo, px), 0.0, None)
  return overlap / (n / cells)


def oracle_patch_maps(masks, grid: int) -> jax.Array:
  """ORACLE-PATCH: ground-truth masks as a perfect dense CLIP would see them.

  Each mask is averaged over a grid x grid layout of equal cells (dense
  CLIP squashes the whole view to its square input, so cell k spans the
  k-th 1/grid of each axis) and upsampled back as dense CLIP's patch map is
  (clip.dense.upsample). Benchmarks only: it reads the ground truth.

  Args:
    masks: bool [V, H, W], True = transient.
    grid: patches per side of the CLIP input (14 for B/32 at 448 px).
  Returns:
    float32 [V, H, W] in [0, 1].
  """
  from clipgs_jax.clip import dense  # pylint: disable=g-import-not-at-top
  masks = np.asarray(masks, np.float64)
  _, h, w = masks.shape
  rows, cols = _pool_matrix(h, grid), _pool_matrix(w, grid)
  pooled = np.einsum("ih,vhw,jw->vij", rows, masks, cols)
  return jnp.stack([dense.upsample(jnp.asarray(p, jnp.float32), h, w)
                    for p in pooled])



def view_map(scorer,
             stats: residual.ResidualState | None,
             view: jax.Array,
             render: jax.Array,
             alpha: jax.Array,
             photo: jax.Array,
             rc: guidance_config.ResidualConfig,
             valid: jax.Array | None = None) -> jax.Array:
  """float32 [H, W], the map m a training step on `view` would use now:
  the residual map for a ResidualSource (from `render` and `alpha`, the
  view rendered by the current model; `valid` as residual_map's; m does
  not depend on the warm-up's sampling, and before rc.start it
  is the test's map, which the step does not use yet: held_back; with a
  memory, the pixels it holds are transient too: remember), else the
  static map of a guidance.PixelMapScorer (`render` unread)."""
  if isinstance(scorer, ResidualSource):
    m = residual_map(scorer, stats, view, render, photo, jnp.int32(0),
                     jax.random.key(0), rc, valid=valid,
                     alpha=alpha).transient
    if stats.memory is not None:
      m = _held(m, stats.memory[view])
    return m
  return scorer.score_map(view)
