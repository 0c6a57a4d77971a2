"""Finished run folders: recomputed test metrics, colour and mask renders."""

import json
import os

from absl import logging
import jax.numpy as jnp
import numpy as np

from clipgs_jax import checkpoint
from clipgs_jax import config as config_lib
from clipgs_jax import evaluation
from clipgs_jax import fileio
from clipgs_jax import ply
from clipgs_jax import run as run_lib
from clipgs_jax import semantic
from clipgs_jax import train
from clipgs_jax.data import canvas
from clipgs_jax.data import images as images_lib

SOURCES = ("auto", "checkpoint", "ply")   # where the Gaussians come from
TRAIN_RENDERS = os.path.join("renders", "train")   # colour, training views
MASK_RENDERS = os.path.join("renders", "masks")    # transient alpha, grey


def _read_metrics(workdir: str) -> dict:
  path = os.path.join(workdir, run_lib.METRICS_JSON)
  if not os.path.exists(path):
    return {}
  with open(path) as f:
    return json.load(f)


def recompute_metrics(workdir: str, source: str = "auto",
                      lpips_net: str | None = None, dry_run: bool = False
                      ) -> tuple[dict, dict, str]:
  """Renders a finished run's test views again and scores them.

  Args:
    workdir: str, run folder written by experiments/train.py.
    source: one of SOURCES; "auto" is the checkpoint if present, else the
      PLY.
    lpips_net: "alex", "vgg", or None for the one the run used.
    dry_run: leave metrics.json as it is.

  Returns:
    (new "test" block, the stored one ({} if none), the source used).
    Unless dry_run, metrics.json's "test" and "test_source" are replaced
    atomically.
  """
  if source not in SOURCES:
    raise ValueError(f"source={source!r}; pass one of {SOURCES}.")
  run, cfg, scene = run_lib.load_run(workdir)
  ckpt = os.path.join(workdir, train.CHECKPOINT_NAME)
  ply_path = os.path.join(workdir, run_lib.POINT_CLOUD_PLY)
  if source == "auto":
    source = "checkpoint" if os.path.exists(ckpt) else "ply"
  if source == "checkpoint":
    state, _ = checkpoint.restore(ckpt, train.initial_state(cfg, scene))
    params, alive = state.params, state.alive
  else:
    if not os.path.exists(ply_path):
      raise FileNotFoundError(f"{ply_path} is missing; read the Gaussians "
                              "from the checkpoint instead.")
    params, alive = ply.read_ply(ply_path)
  lpips_net = lpips_net or run.get("lpips_net", "alex")
  new = run_lib.test_metrics(params, alive, scene.test, cfg, lpips_net)
  stored = _read_metrics(workdir)
  old = stored.get("test", {})
  if not dry_run:
    stored["test"] = new
    stored["test_source"] = source
    fileio.write_json(os.path.join(workdir, run_lib.METRICS_JSON),
                          stored)
    logging.info("updated %s", os.path.join(workdir, run_lib.METRICS_JSON))
  return new, old, source


def transient_selection(state, tau: float) -> np.ndarray:
  """bool [C], the Gaussians the run flags as transient at threshold tau.

  The semantic condition of eq. 13 (alive and s_j > tau) as
  semantic.prune_masks states it, without an evidence floor; never-scored
  Gaussians (s_j = 0) are left out for any tau >= 0.
  """
  flagged, _ = semantic.prune_masks(
      state.semantic, state.params.opacity_logits, state.alive, tau=tau,
      n_min=0.0, alpha_min=0.0)
  return np.asarray(flagged)


def render_views(params, alive, views, cfg: config_lib.Config):
  """Colour and alpha of every view, all SH bands, cfg.train.background.

  Returns:
    (V float32 [h, w, 3] colour in [0, 1], V float32 [h, w] alpha), each
    the size of its view's photo.
  """
  colours, alphas, overflow = [], [], 0
  for image, alpha, dropped in evaluation.renders(params, alive, views, cfg):
    colours.append(np.asarray(image))
    alphas.append(np.asarray(alpha))
    overflow += int(dropped)
  if overflow:
    logging.warning("%d tile-list entries dropped over %d views; raise "
                    "RenderConfig.tile_budget for exact renders.", overflow,
                    len(colours))
  return colours, alphas


def _write_pngs(folder: str, names, pixels) -> None:
  for name, image in zip(names, pixels):
    stem = os.path.splitext(os.path.basename(name))[0]
    images_lib.write_png(os.path.join(folder, stem + ".png"), image)


def render_colour(workdir: str) -> str:
  """Writes the training views' colour renders; returns their folder."""
  _, cfg, scene, state = run_lib.load_state(workdir)
  colours, _ = render_views(state.params, state.alive, scene.train, cfg)
  out_dir = os.path.join(workdir, TRAIN_RENDERS)
  _write_pngs(out_dir, scene.train.names, colours)
  return out_dir


def render_masks(workdir: str, tau: float | None = None) -> dict:
  """Writes the transient-mask PNGs and, with ground truth, their IoU.

  The mask of a view is the alpha of only the alive Gaussians with
  s_j > tau (the semantic condition of eq. 13), as 8-bit grey
  renders/masks/<stem>.png.
  With ground-truth masks, metrics.json gets "mask_iou": iou_summary's
  block plus "tau" and "num_gaussians_above_tau".

  Args:
    workdir: str, run folder written by experiments/train.py.
    tau: float or None, score threshold; None = the run's semantic.tau.

  Returns:
    {"folder", "num_views", "tau", "num_gaussians_above_tau", "mask_iou":
    the block written to metrics.json, or None when the scene has no
    masks (then only the PNGs are written)}.
  """
  _, cfg, scene, state = run_lib.load_state(workdir)
  tau = cfg.semantic.tau if tau is None else float(tau)
  chosen = transient_selection(state, tau)
  num_chosen = int(chosen.sum())
  if num_chosen == 0:
    logging.warning("no alive Gaussian has s_j > tau = %g (semantic.scorer "
                    "= %r); the masks are empty.", tau, cfg.semantic.scorer)
  _, alphas = render_views(state.params, jnp.asarray(chosen), scene.train,
                           cfg)
  out_dir = os.path.join(workdir, MASK_RENDERS)
  _write_pngs(out_dir, scene.train.names, alphas)
  out = {"folder": out_dir, "num_views": len(alphas), "tau": tau,
         "num_gaussians_above_tau": num_chosen, "mask_iou": None}
  if scene.train.masks is None:
    logging.info("scene %s has no masks/: no IoU computed.", scene.path)
    return out
  masks = [canvas.crop(scene.train, i, m)
           for i, m in enumerate(scene.train.masks)]
  block = evaluation.iou_summary(scene.train.names, alphas, masks)
  block |= {"tau": tau, "num_gaussians_above_tau": num_chosen}
  metrics = _read_metrics(workdir)
  metrics["mask_iou"] = block
  fileio.write_json(os.path.join(workdir, run_lib.METRICS_JSON), metrics)
  out["mask_iou"] = block
  return out
