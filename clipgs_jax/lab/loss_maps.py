"""Where a run's transient maps fail: the maps the loss used, per view.

For a finished pixel-evidence run (residual, features, ORACLE-PATCH, dense
CLIP): the map m each training view's step would use with the final model
(evaluation.view_map), scored against the ground-truth masks, and a figure
of the worst views, photo | render | m | ground truth | errors, for the
two ways a map fails: transient views where it misses or overreaches
(lowest IoU) and views with no transient where it masks anyway (most
masked pixels). For the residual map, where its recall goes: the share of
the ground truth's pixels still transient after each of the map's steps
(sources.residual_stages), and with feature regions the most their
majority vote could keep (every region that the ground truth fills at
least half of). With the run of the scene's clean twin (the same cameras,
no transients), how far a residual test at the run's threshold could reach:
the ground truth's pixels whose photo differs by at least the threshold
from what lies behind the transient (the clean run's render), and of those
the ones the run's own render reproduces (baked into the model).
"""

import os

import jax
import numpy as np
from matplotlib import figure

from clipgs_jax import evaluation
from clipgs_jax import fileio
from clipgs_jax import guidance
from clipgs_jax import plots
from clipgs_jax import run as run_lib
from clipgs_jax import sh
from clipgs_jax.data import canvas
from clipgs_jax.data import scene as scene_lib
from clipgs_jax.maps import features
from clipgs_jax.maps import residual
from clipgs_jax.maps import sources

LOSS_MAPS_JSON = "loss_maps.json"
LOSS_MAPS_PNG = "loss_maps.png"
PANEL_INCHES = 2.0
_SHORT = {"masked_fraction": "masked", "transient_fraction": "transient",
          "precision": "P", "recall": "R", "iou": "IoU"}
COLUMNS = ("photo", "render", "map m (loss weight 1 - m)", "ground truth",
           "m > 0.5: hit green, false red, missed blue")


def error_picture(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
  """float32 [h, w, 3]: true positives green, false positives red, false
  negatives blue, the rest black."""
  out = np.zeros(pred.shape + (3,), np.float32)
  out[pred & truth, 1] = 1.0
  out[pred & ~truth, 0] = 1.0
  out[~pred & truth, 2] = 1.0
  return out


def view_scores(pred: np.ndarray, truth: np.ndarray | None) -> dict:
  """The masked fraction of one view's thresholded map and, with a ground
  truth, its precision, recall and IoU (None where undefined)."""
  out = {"masked_fraction": float(pred.mean())}
  if truth is None:
    return out
  return out | {"transient_fraction": float(truth.mean())} | (
      evaluation.confusion_scores(evaluation.confusion(pred, truth)))


def worst_views(scores: dict[str, dict], count: int) -> dict[str, list[str]]:
  """The `count` transient views of lowest IoU (a missing IoU, nothing
  masked and nothing to mask, never counts) and the `count` views without
  a transient pixel that the map masks most."""
  with_gt = [n for n, s in scores.items() if s.get("transient_fraction")]
  clean = [n for n, s in scores.items()
           if "transient_fraction" in s and not s["transient_fraction"]]
  low_iou = sorted(with_gt, key=lambda n: scores[n]["iou"] or 0.0)
  masked_clean = sorted(clean, key=lambda n: -scores[n]["masked_fraction"])
  return {"lowest_iou": low_iou[:count],
          "clean_most_masked": [n for n in masked_clean[:count]
                                if scores[n]["masked_fraction"] > 0]}


def stage_counts(stages: dict[str, np.ndarray], truth: np.ndarray,
                 labels: np.ndarray | None, num_regions: int) -> dict:
  """{step: [ground-truth pixels still transient, pixels transient]} of one
  view's residual-map steps (map > MAP_THRESHOLD, in the order of
  `stages`), plus "regions_best" (the ground truth's majority vote over
  `labels`) when there are labels, and "pixels": [ground-truth pixels,
  pixels]."""
  out = {"pixels": [int(truth.sum()), truth.size]}
  if labels is not None:
    stages = stages | {"regions_best": np.asarray(features.vote(
        ~truth, labels, num_regions))}
  for name, m in stages.items():
    pred = m > evaluation.MAP_THRESHOLD
    out[name] = [int(np.count_nonzero(pred & truth)),
                 int(np.count_nonzero(pred))]
  return out


def stage_summary(counts: dict) -> dict:
  """{step: {"precision", "recall", "iou", "masked_fraction"}} of summed
  stage_counts (None where undefined)."""
  gt, pixels = counts["pixels"]
  return {name: evaluation.confusion_scores((hit, masked - hit, gt - hit))
          | {"masked_fraction": float(masked / pixels)}
          for name, (hit, masked) in counts.items() if name != "pixels"}


def contrast_counts(photo: np.ndarray, render: np.ndarray,
                    behind: np.ndarray, truth: np.ndarray,
                    threshold: float) -> np.ndarray:
  """int64 [3] of one view's ground-truth transient pixels: all of them;
  "reachable", where the photo differs from `behind` (the render of a model
  trained without the transients) by at least `threshold`, as the residual
  test measures a difference; "baked", reachable but under the threshold
  against `render` (the run's model reproduces the transient there)."""
  reachable = np.asarray(residual.residual(behind, photo)) >= threshold
  fitted = np.asarray(residual.residual(render, photo)) < threshold
  return np.array([np.count_nonzero(truth),
                   np.count_nonzero(truth & reachable),
                   np.count_nonzero(truth & reachable & fitted)], np.int64)


def same_cameras(a, b) -> bool:
  """Whether two stacked camera.Camera hold the same views (to 1e-5)."""
  la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
  return len(la) == len(lb) and all(
      np.shape(x) == np.shape(y) and np.allclose(x, y, atol=1e-5)
      for x, y in zip(la, lb))


def contrast(state, cfg, views, clean_run: str) -> dict:
  """{"threshold", "reachable", "baked"} (shares of the ground truth's
  pixels, contrast_counts) of a residual run's final model `state` on its
  training `views`, against `clean_run`, the run of the clean twin.

  Raises:
    ValueError: `clean_run`'s training cameras are not `views`'.
  """
  _, clean_cfg, clean_scene, clean_state = run_lib.load_state(clean_run)
  if not same_cameras(clean_scene.train.cameras, views.cameras):
    raise ValueError(
        f"--clean_run={clean_run} was trained on other cameras than the "
        "run's training views; pass the run of this scene's clean twin "
        "(the same photos' cameras, without transients).")
  threshold = float(state.maps.threshold)
  totals = np.zeros(3, np.int64)
  for i, ((mine, _, _), (behind, _, _)) in enumerate(zip(
      evaluation.renders(state.params, state.alive, views, cfg),
      evaluation.renders(clean_state.params, clean_state.alive, views,
                         clean_cfg))):
    totals += contrast_counts(
        canvas.crop(views, i, views.images[i]), np.asarray(mine),
        np.asarray(behind),
        canvas.crop(views, i, np.asarray(views.masks[i], bool)), threshold)
  gt, reachable, baked = (int(x) for x in totals)
  return {"threshold": threshold,
          "reachable": reachable / gt if gt else None,
          "baked": baked / gt if gt else None}


def loss_map_report(workdir: str, count: int = 3,
                    clean_run: str | None = None) -> dict:
  """Writes LOSS_MAPS_JSON and LOSS_MAPS_PNG into a finished run folder.

  Args:
    workdir: a run folder of experiments/train.py with pixel evidence.
    count: views drawn per failure kind.
    clean_run: None, or the run folder of the scene's clean twin: adds
      "contrast" (contrast()) to "pooled" for a residual map with masks.
  Returns:
    {"json", "png", "pooled" (masked fraction and, with masks, P / R /
    IoU over all training views), "worst" (worst_views)}.
  Raises:
    ValueError: the run has no per-pixel map (semantic.evidence != pixel),
      or `clean_run` is given for a run without a residual map and masks.
  """
  _, cfg, scene, state = run_lib.load_state(workdir)
  if not cfg.semantic.localized:
    raise ValueError(
        f"{workdir} was trained with semantic.scorer={cfg.semantic.scorer!r}"
        f", evidence={cfg.semantic.evidence!r}: it has no per-pixel map; "
        "pass a run with semantic.evidence=pixel.")
  views = scene.train
  scorer = guidance.make_scorer(cfg, scene)
  degree = sh.active_degree(state.step, cfg.densify.sh_degree_every,
                            cfg.gaussians.sh_degree)
  by_stage = (isinstance(scorer, sources.ResidualSource)
              and views.masks is not None)
  if clean_run is not None and not by_stage:
    raise ValueError(f"--clean_run needs a residual-map run on a scene with "
                     f"ground-truth masks; {workdir} is not one.")
  maps, truths, scores, steps = {}, {}, {}, {}
  totals = np.zeros(3, np.int64)
  for i, (name, m, truth) in enumerate(evaluation.training_maps(
      state.params, state.alive, state.maps, scorer, views, cfg, degree,
      by_stage)):
    if by_stage:
      m = sources.in_stage_order(m)
      labels = (None if scorer.labels is None else
                canvas.crop(views, i, np.asarray(scorer.labels[i])))
      for key, c in stage_counts(m, truth, labels,
                                 scorer.num_regions).items():
        steps[key] = np.add(steps.get(key, 0), c)
      m = list(m.values())[-1]
    pred = m > evaluation.MAP_THRESHOLD
    if truth is not None:
      totals += evaluation.confusion(pred, truth)
    maps[name], truths[name] = m, truth
    scores[name] = view_scores(pred, truth)
  # Pixels pooled over all views, as evaluation.mask_quality pools them.
  pooled = {"masked_fraction": float(np.mean(
      [s["masked_fraction"] for s in scores.values()]))}
  if views.masks is not None:
    pooled |= evaluation.confusion_scores(totals)
  if by_stage:
    pooled["stages"] = stage_summary(steps)
  if clean_run is not None:
    pooled["contrast"] = contrast(state, cfg, views, clean_run)
  worst = (worst_views(scores, count) if views.masks is not None else
           {"most_masked": sorted(scores, key=lambda n: -scores[n][
               "masked_fraction"])[:count]})
  picked = [(kind, n) for kind, names in worst.items() for n in names]
  png = os.path.join(workdir, LOSS_MAPS_PNG)
  if picked:
    index = {n: i for i, n in enumerate(views.names)}
    # Colour renders of the drawn views only.
    drawn = scene_lib.subset(views, [index[n] for _, n in picked])
    colours = [np.asarray(c) for c, _, _ in
               evaluation.renders(state.params, state.alive, drawn, cfg)]
    h, w = maps[picked[0][1]].shape
    fig = figure.Figure(dpi=150, figsize=(
        PANEL_INCHES * len(COLUMNS),
        (PANEL_INCHES * h / w + 0.5) * len(picked)))
    axes = fig.subplots(len(picked), len(COLUMNS), squeeze=False)
    for k, (kind, name) in enumerate(picked):
      i = index[name]
      m = maps[name]
      photo = canvas.crop(views, i, views.images[i])
      truth = (np.zeros(m.shape, bool) if truths[name] is None
               else truths[name])
      s = scores[name]
      panels = (photo, colours[k], np.repeat(m[..., None], 3, -1),
                np.repeat(truth[..., None].astype(np.float32), 3, -1),
                error_picture(m > evaluation.MAP_THRESHOLD, truth))
      for c, image in enumerate(panels):
        ax = axes[k, c]
        ax.imshow(np.clip(image, 0, 1), interpolation="nearest")
        ax.set_xticks([])
        ax.set_yticks([])
        if k == 0:
          ax.set_title(COLUMNS[c], fontsize=6)
      axes[k, 0].set_ylabel(f"{name}\n{kind}", fontsize=6)
      axes[k, 2].set_xlabel(", ".join(
          f"{_SHORT[key]} {'n/a' if v is None else f'{v:.2f}'}"
          for key, v in s.items()), fontsize=6)
    plots.save_figure(fig, png)
  out = {"run": os.path.abspath(workdir), "step": int(state.step),
         "map_threshold": evaluation.MAP_THRESHOLD, "pooled": pooled,
         "worst": worst, "per_view": scores}
  path = os.path.join(workdir, LOSS_MAPS_JSON)
  fileio.write_json(path, out)
  return {"json": path, "png": png if picked else None, "pooled": pooled,
          "worst": worst}
