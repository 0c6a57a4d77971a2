"""One run: load its scene, train, evaluate and write its run folder.

experiments/train.py, the sweeps of clipgs_jax/lab and the notebook call
`train_and_evaluate(cfg, workdir)`; this module is the one place that knows
the artefacts' names. Every file is written atomically (temp file +
rename).
"""

import datetime
import json
import os
import platform
import resource
import time
from typing import Any

from absl import app
from absl import logging
import jax
import numpy as np

from clipgs_jax import checkpoint
from clipgs_jax import cli
from clipgs_jax import config as config_lib
from clipgs_jax import config_file
from clipgs_jax import evaluation
from clipgs_jax import fileio
from clipgs_jax import gaussians
from clipgs_jax import guidance
from clipgs_jax import guidance_config
from clipgs_jax import loop
from clipgs_jax import plots
from clipgs_jax import ply
from clipgs_jax import sharding
from clipgs_jax import train
from clipgs_jax.data import default_scene
from clipgs_jax.data import images as images_lib
from clipgs_jax.data import scene as scene_lib

RUN_JSON = "run.json"            # the command-line choices (scene, ...)
CONFIG_JSON = "config.json"      # the resolved config.Config
METRICS_JSON = "metrics.json"    # test metrics, run time, semantic block
CURVE_JSON = "curve.json"        # [{step, seconds, test_psnr}]
CURVE_PNG = "curve.png"          # test error against training time
SCORES_JSONL = "scores.jsonl"    # guided runs: one line per scored step
PRUNE_EVENTS_JSON = "prune_events.json"  # guided runs: every prune event
POINT_CLOUD_PLY = "point_cloud.ply"  # the alive Gaussians (3DGS layout)
PRUNED_PLY = "pruned.ply"        # guided runs: the rows semantic prunes
#   removed, as they were when removed (3DGS layout; none: 0 vertices)
TENSORBOARD_DIR = "tensorboard"  # TensorBoard event files (summary.py)
TEST_RENDERS = os.path.join("renders", "test")   # one PNG per test view


def test_metrics(params, alive, views, cfg: config_lib.Config,
                 lpips_net: str, renders_dir: str | None = None) -> dict:
  """Test-set PSNR / SSIM / LPIPS, averaged per image, and optional renders.

  Returns:
    {"psnr", "ssim", "lpips": means over the views, "lpips_net",
     "num_views", "seconds" (this evaluation's wall time), "per_image":
     {view name: {"psnr", "ssim", "lpips"}}}.
  """
  tic = time.perf_counter()
  result = evaluation.evaluate(params, alive, views, cfg, lpips_net=lpips_net,
                               keep_images=renders_dir is not None)
  if renders_dir is not None:
    for name, image in zip(views.names, result["images"]):
      stem = os.path.splitext(os.path.basename(name))[0]
      images_lib.write_png(os.path.join(renders_dir, stem + ".png"), image)
  return {
      "psnr": result["mean/psnr"], "ssim": result["mean/ssim"],
      "lpips": result["mean/lpips"], "lpips_net": lpips_net,
      "num_views": len(views.names),
      "seconds": time.perf_counter() - tic,
      "per_image": {
          name: {k: result[k][i] for k in ("psnr", "ssim", "lpips")}
          for i, name in enumerate(views.names)},
  }


def read_json(path: str, what: str) -> dict:
  """A run folder's JSON file; `what` says what it holds in the error when
  it is missing."""
  if not os.path.exists(path):
    raise FileNotFoundError(f"{path} is missing ({what}); pass a run folder "
                            "written by experiments/train.py.")
  with open(path) as f:
    return json.load(f)


def load_config(workdir: str) -> config_lib.Config:
  """The resolved config a run folder was trained with."""
  return config_file.from_dict(read_json(os.path.join(workdir, CONFIG_JSON),
                                         "the resolved config"))


def load_run(workdir: str):
  """(run.json dict, resolved config, scene) of a run folder.

  A run.json without "train_split" (older runs) means "clutter".
  """
  run = read_json(os.path.join(workdir, RUN_JSON), "scene and downscale")
  cfg = load_config(workdir)
  scene = scene_lib.load_scene(run["scene"], downscale=run["downscale"],
                               train_split=run.get("train_split", "clutter"),
                               background=cfg.data.background)
  return run, cfg, scene


def load_state(workdir: str):
  """(run.json dict, resolved config, scene, TrainState) of a run folder.

  Raises:
    FileNotFoundError: the folder, run.json, config.json or the checkpoint
      is missing (the PLY lacks the semantic statistics).
  """
  if not os.path.isdir(workdir):
    raise FileNotFoundError(f"{workdir} is not a folder; pass a run folder "
                            "written by experiments/train.py.")
  for name in (RUN_JSON, CONFIG_JSON):
    if not os.path.exists(os.path.join(workdir, name)):
      raise FileNotFoundError(f"{os.path.join(workdir, name)} is missing; "
                              "pass a run folder written by "
                              "experiments/train.py.")
  ckpt = os.path.join(workdir, train.CHECKPOINT_NAME)
  if not os.path.exists(ckpt):   # checked before the scene is loaded
    raise FileNotFoundError(
        f"{ckpt} is missing; rendering needs the trained state (the PLY "
        "lacks the semantic scores): rerun experiments/train.py into this "
        "folder, or with --resume if it was interrupted.")
  run, cfg, scene = load_run(workdir)
  state, _ = checkpoint.restore(ckpt, train.initial_state(cfg, scene))
  return run, cfg, scene, state


def semantic_label(cfg: config_lib.Config) -> str:
  """How tables and logs name a run's guidance; oracles say so."""
  sem, pixel, rc = cfg.semantic, cfg.pixel, cfg.residual
  if not sem.enabled:
    return "vanilla 3DGS"
  variant = ""
  if not sem.localized and sem.weighting != "visibility":
    variant += f", {sem.weighting}-weighted accumulation"
  if sem.localized and not pixel.agreement:
    variant += ", raw map (no agreement)"
  if pixel.loss_masking:
    variant += ", loss masking"
  if sem.lambda_c == 0:
    variant += ", no opacity loss"
  if not sem.prune:
    variant += ", no pruning"
  if sem.localized:
    # The residual test's rule, and the regions that vote it if any.
    rule = rc.rule + (f", {rc.features} feature regions"
                      if rc.features else "")
    if rc.features and rc.vote != 0.5:
      rule += f" masked at {rc.vote:g} failing"
    default_gate = guidance_config.ResidualConfig.uniformity
    if rc.features and rc.uniformity != default_gate:
      rule += (f", early only where even (std / mean < "
               f"{rc.uniformity:g})" if rc.uniformity
               else ", no early uniformity gate")
    if rc.remember:
      rule += ", remembered per view"
    if sem.scorer == "residual":
      return f"residual map ({rule}, no weights, no oracle)" + variant
    if sem.scorer == "learned":
      return (f"learned map ({cfg.learned.net} features, trained on the "
              f"residual test: {rule}, no oracle)" + variant)
    if rc.with_semantic:
      variant += f", gating the residual map ({rule})"
    if sem.scorer == "oracle_patch":
      return ("localized CLIP-GS machinery, ORACLE-PATCH scorer "
              "(ground-truth masks at dense CLIP's patch grid, not CLIP)"
              + variant)
    if sem.scorer == "uniform":
      return ("localized CLIP-GS machinery, UNIFORM control map (the "
              "ground-truth masks' mean everywhere: no location)" + variant)
    if sem.scorer == "oracle":
      return ("localized CLIP-GS machinery, ORACLE-PIXEL scorer "
              "(ground-truth masks, not CLIP)" + variant)
    return f"localized CLIP-GS (dense {sem.clip_variant}{variant})"
  if sem.scorer == "oracle":
    return ("CLIP-GS machinery, ORACLE scorer (ground-truth masks, not CLIP)"
            + variant)
  return f"CLIP-GS ({sem.clip_variant}{variant})"


def _write_semantic_logs(workdir: str, cfg: config_lib.Config,
                         result: loop.FitResult, scene) -> dict:
  """scores.jsonl, prune_events.json and pruned.ply; returns
  metrics.json's block."""
  def write_lines(tmp):
    with open(tmp, "w") as f:
      for row in result.scores:
        f.write(json.dumps(row) + "\n")
  fileio.atomic_write(os.path.join(workdir, SCORES_JSONL), write_lines,
                      ".jsonl")
  fileio.write_json(os.path.join(workdir, PRUNE_EVENTS_JSON), {
      "scorer": cfg.semantic.scorer, "evidence": cfg.semantic.evidence,
      "histogram_edges": guidance.histogram_edges(cfg.semantic),
      "events": result.prune_events})
  state = result.state
  pruned = result.pruned
  if pruned is None:
    pruned = gaussians.empty(0, state.params.sh_degree)[0]
  ply.write_ply(os.path.join(workdir, PRUNED_PLY), pruned,
                np.ones(pruned.means.shape[0], bool))
  block = guidance.summarize(result.prune_events,
                             int(jax.device_get(state.alive.sum())),
                             state.semantic)
  block = {"scorer": cfg.semantic.scorer, "evidence": cfg.semantic.evidence,
           "label": semantic_label(cfg),
           "num_scored_steps": len(result.scores), **block}
  if result.pruned is not None:
    block["pruned_mask_iou"] = evaluation.transient_mask_iou(
        result.pruned, scene.train, cfg)
  if result.mask_quality is not None:
    block["mask_quality"] = result.mask_quality
  return block


def train_and_evaluate(cfg: config_lib.Config, workdir: str, *,
                       resume: bool = False, clip_weights: str | None = None,
                       progress: bool = True,
                       run_info: dict[str, Any] | None = None) -> dict:
  """Trains the run `cfg` describes, evaluates it, writes its run folder.

  Loads the scene (cfg.data: a folder, a pack, or None for the embedded
  scene), fills in its extent (train.resolve, once), builds the scorer
  (guidance.make_scorer), trains (train.fit), evaluates on the test views
  and writes every artefact into `workdir`. The checkpoint's metadata
  (resume), the scene and the CLIP weights are read before anything is
  written; a run that fails before its first checkpoint leaves no folder
  behind (cli.output_dir).

  Args:
    cfg: the checked config (config_file.check).
    workdir: the run folder (created).
    resume: continue from the folder's checkpoint.
    clip_weights: CLIP weights for clip scorers (else
      $CLIPGS_CLIP_WEIGHTS).
    progress: a tqdm bar.
    run_info: extra run.json fields (the config file, argv, ...).
  Returns:
    The metrics.json dict.
  Raises:
    app.UsageError: the scorer cannot be built (no masks, no weights).
  """
  check_inputs(cfg, clip_weights)
  workdir = os.path.abspath(workdir)
  ckpt_path = os.path.join(workdir, train.CHECKPOINT_NAME)
  resuming = resume and os.path.exists(ckpt_path)
  if resuming:
    checkpoint.read_meta(ckpt_path)      # a corrupt file fails here, early
  held = _held_views(cfg)
  embedded = cfg.data.scene is None
  scene_path = (default_scene.ensure_default_scene() if embedded
                else cfg.data.scene)
  scene = scene_lib.load_scene(scene_path, downscale=cfg.data.downscale,
                               train_split=cfg.data.train_split,
                               train_views=held,
                               background=cfg.data.background)
  cfg = train.resolve(cfg, scene)
  if resuming:
    checkpoint.check_resumable(ckpt_path, cfg)
  height, width = scene.train.images.shape[1:3]
  logging.info("scene %s: %d train / %d test views, %dx%d%s, %d points, "
               "extent %.3f", scene_path, len(scene.train.names),
               len(scene.test.names), width, height,
               "" if scene.train.sizes is None else " (canvas)",
               len(scene.points), scene.extent)
  try:
    scorer = guidance.make_scorer(cfg, scene,
                                  clip_weights=clip_weights)
  except (ValueError, FileNotFoundError) as e:
    raise app.UsageError(f"--config.semantic.scorer={cfg.semantic.scorer}: "
                         f"{e}") from e
  info = {"scene": os.path.abspath(scene_path), "embedded_scene": embedded,
          "downscale": cfg.data.downscale,
          "train_split": cfg.data.train_split, **(run_info or {})}
  if not sharding.is_writer():
    # Another process of a multi-host run writes the folder.
    result = train.fit(cfg, scene, workdir, scorer=scorer, resume=resume,
                       progress=False)
    return {"steps": int(result.state.step)}
  with cli.output_dir(workdir, keep=train.CHECKPOINT_NAME):
    return _train_into(cfg, scene, workdir, scorer=scorer, resume=resume,
                       progress=progress, run_info=info)


def check_inputs(cfg: config_lib.Config, clip_weights: str | None) -> None:
  """The checks of a run's inputs beyond its config's (config.check) that
  read no scene, photo or weights: run first, so that their error is the
  only line a bad command prints.

  Raises:
    app.UsageError: a CLIP scorer has no weights (flag or environment) or
      they do not exist.
  """
  if cfg.semantic.scorer != "clip":
    return
  # Only a CLIP scorer imports the clip package.
  from clipgs_jax.clip import weights  # pylint: disable=g-import-not-at-top
  try:
    weights.resolve_weights_path(clip_weights)
  except (ValueError, FileNotFoundError) as e:
    raise app.UsageError(f"--config.semantic.scorer=clip: {e}") from e


def _held_views(cfg: config_lib.Config):
  """None, or in a multi-host run which training views this process
  reads (those of its devices' lanes, sharding.holds).

  Raises:
    ValueError: train.batch_size does not divide over the devices (before
      any scene is read).
  """
  size = cfg.train.batch_size
  if size == 1 and jax.process_count() == 1:
    return None
  mesh = sharding.make_mesh(size)
  if jax.process_count() == 1:
    return None
  lanes = sharding.held_lanes(mesh, size)
  return lambda view: sharding.holds(view, size, lanes)


def _train_into(cfg: config_lib.Config, scene, workdir: str, *, scorer,
                resume: bool, progress: bool, run_info: dict[str, Any]
                ) -> dict:
  """Trains the resolved `cfg` on `scene` and writes the run folder."""
  lpips_net = cfg.eval.lpips_net
  os.makedirs(workdir, exist_ok=True)
  fileio.write_json(os.path.join(workdir, RUN_JSON), dict(
      run_info, lpips_net=lpips_net,
      guidance=semantic_label(cfg)))
  fileio.write_json(os.path.join(workdir, CONFIG_JSON),
                    config_lib.to_dict(cfg))
  result = train.fit(cfg, scene, workdir, scorer=scorer, resume=resume,
                     progress=progress,
                     summary_dir=os.path.join(workdir, TENSORBOARD_DIR))
  state = sharding.local(result.state)
  test = test_metrics(state.params, state.alive, scene.test, cfg, lpips_net,
                      renders_dir=os.path.join(workdir, TEST_RENDERS))
  ply.write_ply(os.path.join(workdir, POINT_CLOUD_PLY), state.params,
                state.alive)
  curve_path = os.path.join(workdir, CURVE_JSON)
  fileio.write_json(curve_path, result.curve)
  plots.plot([curve_path], os.path.join(workdir, CURVE_PNG),
             labels=[os.path.basename(os.path.normpath(workdir))])
  final_log = result.log[-1] if result.log else {}
  height, width = np.shape(scene.train.images)[1:3]
  metrics = {
      "test": test,
      "train_seconds": result.train_seconds,
      "steps": int(state.step),
      "num_gaussians": int(jax.device_get(state.alive.sum())),
      "capacity": state.capacity,
      "peak_memory_bytes": resource.getrusage(
          resource.RUSAGE_SELF).ru_maxrss * 1024,
      "peak_memory_note": "process peak RSS (getrusage ru_maxrss x 1024)",
      "final_train": {k: v for k, v in final_log.items()
                      if not k.startswith("grad_norm")},
      "image_size": [int(width), int(height)],
      "num_train_views": len(np.asarray(
          scene_lib.all_train_cameras(scene).fx)),
      "machine": f"{platform.node()} {platform.processor() or ''} "
                 f"{os.cpu_count()} cpus, jax {jax.__version__} "
                 f"{jax.default_backend()}",
      "finished": datetime.datetime.now().isoformat(timespec="seconds"),
  }
  if cfg.semantic.enabled:
    metrics["semantic"] = _write_semantic_logs(workdir, cfg, result, scene)
  fileio.write_json(os.path.join(workdir, METRICS_JSON), metrics)
  return metrics
