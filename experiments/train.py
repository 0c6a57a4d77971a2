"""Trains 3D Gaussian Splatting on one scene; writes the run into --workdir.

  python experiments/train.py --workdir=DIR [--scene=DIR] [--downscale=K]
      [--steps=N] [--seed=S] [--preset=default|smoke] [--resume]
      [--random_background] [--lpips_net=alex|vgg] [--curve_points=20]
      [--tile_budget=K] [--checkpoint_every=N]
      [--semantic=off|clip|oracle] [--evidence=image|pixel] [--tau_p=P]
      [--loss_masking] [--noagreement] [--max_prune_fraction=F]
      [--distractor_prompts=P1,P2,...]
      [--static_prompts=...] [--tau=T] [--clip_weights=PATH]
      [--score_every=K] [--semantic_weighting=visibility|contribution]
      [--lambda_c=L] [--nosemantic_prune] [--scale_semantic_schedule]

Without --scene, the embedded default scene
(data.default_scene.ensure_default_scene()) is used, with
default_scene.TRAIN_STEPS steps unless --steps is given.

Writes into --workdir (every file atomically: temp file + rename):
  run.json          the command-line choices (scene, downscale, ...)
  config.json       the resolved config (config.Config as JSON)
  checkpoint.npz    the final TrainState (--resume continues from it)
  metrics.json      {"test": {"psnr", "ssim", "lpips", "lpips_net",
                    "num_views", "seconds", "per_image"}, "train_seconds",
                    "steps", "num_gaussians", "peak_memory_bytes", ...};
                    train_seconds is the training loop's wall time with
                    compilation, without evaluation and checkpoint writes;
                    peak_memory_bytes is this process's peak resident set
                    size (resource.getrusage ru_maxrss, KiB x 1024), which
                    on a CPU backend includes the device arrays
  curve.json        [{"step", "seconds", "test_psnr"}], test PSNR at
                    regular steps; seconds as train_seconds
  curve.png         test error against training time (plot_curve.py)
  point_cloud.ply   the alive Gaussians (3DGS PLY layout)
  renders/test/     one PNG per test view

With semantic guidance (--semantic=clip|oracle and distractor prompts),
also (the oracle scorer reads ground-truth masks; every output names the
scorer):
  scores.jsonl      one {"step", "view", "s_hat_d", "s_hat_s"} per scored
                    step (s_hat_s null for the oracle)
  prune_events.json {"scorer", "histogram_edges", "events": [{"step",
                    "num_alive_before", "num_pruned_semantic",
                    "num_pruned_visibility", "histogram"}]}, the histogram
                    of s_j over the alive Gaussians before each prune
  metrics.json      gains "semantic": {"scorer", "label",
                    "num_pruned_semantic", "num_pruned_visibility",
                    "fraction_pruned", "semantic_bytes", ...}
  metrics.json      with pixel evidence, also "pruned_mask_iou": the
                    IoU of the semantically pruned Gaussians' rendered
                    alpha against the training views' transient masks
With --semantic=off, CLIP is never imported and the train step is the
vanilla 3DGS step; --semantic=clip with no distractor prompts is an error.
"""

import dataclasses
import json
import os
import sys

from absl import app
from absl import flags
from absl import logging

from clipgs_jax import checkpoint
from clipgs_jax import cli
from clipgs_jax import config as config_lib
from clipgs_jax import guidance
from clipgs_jax import run as run_lib
from clipgs_jax import train
from clipgs_jax.data import default_scene
from clipgs_jax.data import scene as scene_lib



_SCENE = flags.DEFINE_string(
    "scene", None, "Scene folder (images/ + sparse/0/); default: the "
    "embedded procedural scene.")
_WORKDIR = flags.DEFINE_string("workdir", None, "Output folder.")
_DOWNSCALE = flags.DEFINE_integer("downscale", 1, "Image downscale factor.")
_STEPS = flags.DEFINE_integer("steps", None, "Training steps (default: the "
                              "preset's, or default_scene.TRAIN_STEPS).")
_SEED = flags.DEFINE_integer("seed", None, "PRNG seed (default: preset's).")
_PRESET = flags.DEFINE_enum("preset", "default", list(config_lib.PRESETS),
                            "default: 3DGS paper values; smoke: tiny CI run.")
_RESUME = flags.DEFINE_bool("resume", False,
                            "Continue from workdir/checkpoint.npz.")
_RANDOM_BACKGROUND = flags.DEFINE_bool(
    "random_background", False, "Random background colour per step.")
_LPIPS_NET = flags.DEFINE_enum("lpips_net", "alex", ["alex", "vgg"],
                               "LPIPS backbone for the test metrics.")
_CURVE_POINTS = flags.DEFINE_integer(
    "curve_points", 20, "Test-PSNR evaluations along the run for curve.json "
    "(0: the preset's eval_every).")
_TILE_BUDGET = flags.DEFINE_integer(
    "tile_budget", None, "RenderConfig.tile_budget (default: the preset's); "
    "raise it when the log warns that tile-list entries were dropped.")
_CHECKPOINT_EVERY = flags.DEFINE_integer(
    "checkpoint_every", None, "Checkpoint cadence in steps (default: the "
    "preset's); long runs that may be interrupted want a short one.")
_TRAIN_SPLIT = flags.DEFINE_enum(
    "train_split", "clutter", list(scene_lib.TRAIN_SPLITS),
    "RobustNeRF scenes: train on clutter views or on the clean twins.")
_SEMANTIC = flags.DEFINE_enum(
    "semantic", "off", list(config_lib.SCORERS),
    "Semantic guidance scorer: off (vanilla 3DGS), clip (the paper: needs "
    "--clip_weights), oracle (benchmarks only: ground-truth masks).")
_EVIDENCE = flags.DEFINE_enum(
    "evidence", "image", list(config_lib.EVIDENCES),
    "image: the paper's one score per rendered view (threshold --tau); "
    "pixel: localized, a per-pixel transient map per training view "
    "(oracle: the ground-truth mask, labelled ORACLE-PIXEL; clip: dense "
    "CLIP), s_j a probability, threshold --tau_p.")
_TAU_P = flags.DEFINE_float(
    "tau_p", None, "Pixel evidence: prune where the probability s_j "
    "exceeds this (default 0.5, the same for every scene).")
_AGREEMENT = flags.DEFINE_bool(
    "agreement", True, "Pixel evidence: a transient pixel counts only as far "
    "as the render reproduces the photo there (--noagreement: the raw map, "
    "measured in BUILD_NOTES).")
_LOSS_MASKING = flags.DEFINE_bool(
    "loss_masking", False, "Pixel evidence: weight the photometric loss "
    "per pixel by 1 - m.")
_MAX_PRUNE_FRACTION = flags.DEFINE_float(
    "max_prune_fraction", None, "A semantic prune that would remove more "
    "than this share of the alive Gaussians removes none (default 0.5; 1.0 "
    "lifts the guard, as the paper-exact reproduction needs).")
_DISTRACTOR_PROMPTS = flags.DEFINE_list(
    "distractor_prompts", list(config_lib.PAPER_DISTRACTOR_PROMPTS),
    "Distractor prompt set D, comma-separated (--semantic=clip needs one).")
_STATIC_PROMPTS = flags.DEFINE_list(
    "static_prompts", list(config_lib.PAPER_STATIC_PROMPTS),
    "Static prompt set S (s_hat_s is logged only), comma-separated.")
_TAU = flags.DEFINE_float("tau", None, "Prune threshold on s_j (paper: "
                          "0.015).")
_CLIP_WEIGHTS = flags.DEFINE_string(
    "clip_weights", None, "CLIP weights for --semantic=clip (OpenAI .pt, HF "
    "safetensors or directory, or .npz); default $CLIPGS_CLIP_WEIGHTS.")
_SCORE_EVERY = flags.DEFINE_integer(
    "score_every", None, "Score every k-th step (paper: 1).")
_SEMANTIC_WEIGHTING = flags.DEFINE_enum(
    "semantic_weighting", "visibility", list(config_lib.WEIGHTINGS),
    "visibility: the paper's accumulation (each visible Gaussian gains the "
    "view's score once); contribution: weighted by the Gaussian's blending "
    "weight in the view (a measured variant, see BUILD_NOTES.md).")
_LAMBDA_C = flags.DEFINE_float(
    "lambda_c", None, "CLIP opacity loss weight (paper: 0.01; 0 turns the "
    "loss off: the prune-only ablation).")
_SEMANTIC_PRUNE = flags.DEFINE_bool(
    "semantic_prune", True, "Eq. 13 pruning; --nosemantic_prune is the "
    "opacity-loss-only ablation.")
_SCALE_SEMANTIC_SCHEDULE = flags.DEFINE_bool(
    "scale_semantic_schedule", False, "Scale the paper's semantic schedule "
    "(500/2000/5000/1000 of 20k steps) to --steps, for short runs.")
flags.mark_flag_as_required("workdir")


def config_from_flags(embedded: bool) -> config_lib.Config:
  """The preset with the command-line overrides applied."""
  cfg = config_lib.preset(_PRESET.value)
  t = cfg.train
  steps = _STEPS.value
  if steps is None and embedded and _PRESET.value == "default":
    steps = default_scene.TRAIN_STEPS
  if steps is not None:
    if steps <= 0:
      raise app.UsageError(f"--steps must be positive, got {steps}.")
    t = dataclasses.replace(t, steps=steps)
  if _SEED.value is not None:
    t = dataclasses.replace(t, seed=_SEED.value)
  if _RANDOM_BACKGROUND.value:
    t = dataclasses.replace(t, random_background=True)
  if _CHECKPOINT_EVERY.value is not None:
    if _CHECKPOINT_EVERY.value <= 0:
      raise app.UsageError(f"--checkpoint_every must be positive, got "
                           f"{_CHECKPOINT_EVERY.value}.")
    t = dataclasses.replace(t, checkpoint_every=_CHECKPOINT_EVERY.value)
  if _CURVE_POINTS.value > 0:
    t = dataclasses.replace(t, eval_every=max(1, t.steps // _CURVE_POINTS.value))
  cfg = dataclasses.replace(cfg, train=t)
  if _TILE_BUDGET.value is not None:
    if _TILE_BUDGET.value <= 0:
      raise app.UsageError(f"--tile_budget must be positive, got "
                           f"{_TILE_BUDGET.value}.")
    cfg = dataclasses.replace(cfg, render=dataclasses.replace(
        cfg.render, tile_budget=_TILE_BUDGET.value))
  sem = dataclasses.replace(
      cfg.semantic, scorer=_SEMANTIC.value,
      distractor_prompts=tuple(_DISTRACTOR_PROMPTS.value),
      static_prompts=tuple(_STATIC_PROMPTS.value),
      weighting=_SEMANTIC_WEIGHTING.value, prune=_SEMANTIC_PRUNE.value,
      evidence=_EVIDENCE.value, loss_masking=_LOSS_MASKING.value,
      agreement=_AGREEMENT.value)
  if _TAU_P.value is not None:
    sem = dataclasses.replace(sem, tau_p=_TAU_P.value)
  if _MAX_PRUNE_FRACTION.value is not None:
    sem = dataclasses.replace(sem, max_prune_fraction=_MAX_PRUNE_FRACTION.value)
  if _LAMBDA_C.value is not None:
    sem = dataclasses.replace(sem, lambda_c=_LAMBDA_C.value)
  if _TAU.value is not None:
    sem = dataclasses.replace(sem, tau=_TAU.value)
  if _SCORE_EVERY.value is not None:
    sem = dataclasses.replace(sem, score_every=_SCORE_EVERY.value)
  if _SCALE_SEMANTIC_SCHEDULE.value:
    sem = sem.scaled_to(t.steps)
  try:
    guidance.validate(sem)
  except ValueError as e:
    raise app.UsageError(f"semantic flags: {e}") from e
  return dataclasses.replace(cfg, semantic=sem)


def main(argv):
  cli.no_arguments(argv)
  # Every flag is checked before the scene or the weights are read.
  cli.require(_DOWNSCALE.value >= 1, "downscale", _DOWNSCALE.value,
              "must be a positive integer (1: full size)")
  cli.require_folder("scene", _SCENE.value)
  embedded = _SCENE.value is None
  flag_cfg = config_from_flags(embedded)
  workdir = os.path.abspath(_WORKDIR.value)
  ckpt_path = os.path.join(workdir, train.CHECKPOINT_NAME)
  if _RESUME.value and os.path.exists(ckpt_path):
    checkpoint.read_meta(ckpt_path)      # a corrupt file fails here, early
  scene_path = default_scene.ensure_default_scene() if embedded else (
      _SCENE.value)
  scene = scene_lib.load_scene(scene_path, downscale=_DOWNSCALE.value,
                               train_split=_TRAIN_SPLIT.value)
  cfg = train.resolve(flag_cfg, scene)
  if _RESUME.value and os.path.exists(ckpt_path):
    checkpoint.check_resumable(ckpt_path, cfg)
  height, width = scene.train.images.shape[1:3]
  logging.info("scene %s: %d train / %d test views, %dx%d, %d points, "
               "extent %.3f", scene_path, len(scene.train.names),
               len(scene.test.names), width, height, len(scene.points),
               scene.extent)
  try:
    scorer = guidance.make_scorer(cfg.semantic, scene,
                                  clip_weights=_CLIP_WEIGHTS.value)
  except (ValueError, FileNotFoundError) as e:
    raise app.UsageError(f"--semantic={cfg.semantic.scorer}: {e}") from e
  run_info = {"scene": os.path.abspath(scene_path), "embedded_scene": embedded,
              "downscale": _DOWNSCALE.value, "train_split": _TRAIN_SPLIT.value,
              "preset": _PRESET.value, "argv": sys.argv}
  # Nothing is written before this point; a run that fails before its
  # first checkpoint removes what it wrote.
  with cli.output_dir(workdir, keep=train.CHECKPOINT_NAME):
    metrics = run_lib.train_and_evaluate(
        cfg, scene, workdir, scorer=scorer, lpips_net=_LPIPS_NET.value,
        resume=_RESUME.value, run_info=run_info)
  test = metrics["test"]
  logging.info("test PSNR %.3f  SSIM %.4f  LPIPS(%s) %.4f  train %.1f s  "
               "%d Gaussians", test["psnr"], test["ssim"], test["lpips_net"],
               test["lpips"], metrics["train_seconds"],
               metrics["num_gaussians"])
  print(json.dumps({k: metrics[k] for k in
                    ("train_seconds", "steps", "num_gaussians")} |
                   {f"test.{k}": test[k] for k in
                    ("psnr", "ssim", "lpips", "lpips_net")}))


if __name__ == "__main__":
  cli.run(main)
