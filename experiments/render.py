"""Renders a finished run's training views: colour, or its transient masks.

  python experiments/render.py --workdir=DIR [--masks [--tau=T]]

Reads DIR/run.json, DIR/config.json and DIR/checkpoint.npz (the PLY lacks
the semantic statistics, so a checkpoint is required) and renders every
training view (clutter views for RobustNeRF scenes) with all SH bands.

Default: the full model's colour, DIR/renders/train/<stem>.png, to look at
what it made of the transients.

--masks: the alpha of only the Gaussians the run flags as transient, alive
and s_j > tau (DESIGN.md step 5; tau is config.json's semantic.tau unless
--tau), as 8-bit grey DIR/renders/masks/<stem>.png. When the scene has
ground-truth masks (masks/<stem>.png), each view's IoU of (alpha > 0.5)
against its mask is computed, and DIR/metrics.json (created if absent) gets
"mask_iou": {"mean", "per_view" (name: IoU, null where the prediction and
the mask are both empty), "num_views_scored", "alpha_threshold", "tau",
"num_gaussians_above_tau"}. Views with an empty union have no IoU and are
left out of the mean. Every file is written atomically.
"""

import json
import os

from absl import app
from absl import flags
from absl import logging
import jax.numpy as jnp
import numpy as np

from clipgs_jax import checkpoint
from clipgs_jax import cli
from clipgs_jax import config as config_lib
from clipgs_jax import evaluation
from clipgs_jax import fileio
from clipgs_jax import run as run_lib
from clipgs_jax import semantic
from clipgs_jax import train
from clipgs_jax.data import images as images_lib


FLAGS = flags.FLAGS

def _define_flags() -> None:
  # Defined only when run as a script, as in evaluate.py: tests import this
  # module next to experiments/train.py, which defines --workdir too.
  flags.DEFINE_string("workdir", None, "Run folder written by train.py.")
  flags.DEFINE_bool("masks", False, "Render the alpha of the Gaussians with "
                    "s_j > tau instead of the colour, and score it against "
                    "the scene's masks when it has them.")
  flags.DEFINE_float("tau", None, "Score threshold for --masks (default: "
                     "the run's semantic.tau).")
  flags.mark_flag_as_required("workdir")


def select_transient(stats: semantic.SemanticStats, alive, tau: float
                     ) -> np.ndarray:
  """bool [C], alive Gaussians whose normalized score s_j exceeds tau.

  Never-scored Gaussians (n_j = 0) have s_j = 0, so a tau >= 0 leaves them
  out.
  """
  scores = np.asarray(semantic.normalized_scores(stats))
  return np.asarray(alive, bool) & (scores > tau)


def _require(path: str, what: str) -> None:
  if not os.path.exists(path):
    raise app.UsageError(
        f"{path} is missing ({what}); pass as --workdir a run folder "
        "written by experiments/train.py.")


def load(workdir: str):
  """(resolved config, scene, TrainState) of a run folder.

  Raises:
    app.UsageError: the folder, run.json, config.json or checkpoint.npz is
      missing.
  """
  if not os.path.isdir(workdir):
    raise app.UsageError(f"--workdir={workdir} is not a folder; pass a run "
                         "folder written by experiments/train.py.")
  _require(os.path.join(workdir, "run.json"), "scene and downscale")
  _require(os.path.join(workdir, "config.json"), "the resolved config")
  ckpt = os.path.join(workdir, train.CHECKPOINT_NAME)
  if not os.path.exists(ckpt):
    raise app.UsageError(
        f"{ckpt} is missing; render needs the trained state (the PLY lacks "
        "the semantic scores): rerun experiments/train.py into this folder, "
        "or with --resume if it was interrupted.")
  _, cfg, scene = run_lib.load_run(workdir)
  state, _ = checkpoint.restore(ckpt, train.initial_state(cfg, scene))
  return cfg, scene, state


def render_views(params, alive, views, cfg: config_lib.Config):
  """Colour and alpha of every view, all SH bands, cfg.train.background.

  Returns:
    (float32 [V, H, W, 3] colour in [0, 1], float32 [V, H, W] alpha).
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
  return np.stack(colours), np.stack(alphas)


def _stem(name: str) -> str:
  return os.path.splitext(os.path.basename(name))[0]


def render_rgb(workdir: str) -> str:
  """Writes the training views' colour renders; returns their folder."""
  cfg, scene, state = load(workdir)
  colours, _ = render_views(state.params, state.alive, scene.train, cfg)
  out_dir = os.path.join(workdir, "renders", "train")
  for name, image in zip(scene.train.names, colours):
    images_lib.write_png(os.path.join(out_dir, _stem(name) + ".png"), image)
  print(f"wrote {len(colours)} training-view renders to {out_dir}")
  return out_dir


def render_masks(workdir: str, tau: float | None = None) -> dict | None:
  """Writes the transient-mask PNGs and, with ground truth, their IoU.

  Args:
    workdir: str, run folder written by experiments/train.py.
    tau: float or None, score threshold; None = the run's semantic.tau.

  Returns:
    The "mask_iou" block written to metrics.json, or None when the scene
    has no masks (then only the PNGs are written).
  """
  cfg, scene, state = load(workdir)
  tau = cfg.semantic.tau if tau is None else float(tau)
  chosen = select_transient(state.semantic, state.alive, tau)
  num_chosen = int(chosen.sum())
  if num_chosen == 0:
    logging.warning("no alive Gaussian has s_j > tau = %g (semantic.scorer "
                    "= %r); the masks are empty.", tau, cfg.semantic.scorer)
  _, alphas = render_views(state.params, jnp.asarray(chosen), scene.train,
                           cfg)
  out_dir = os.path.join(workdir, "renders", "masks")
  for name, alpha in zip(scene.train.names, alphas):
    images_lib.write_png(os.path.join(out_dir, _stem(name) + ".png"), alpha)
  print(f"wrote {len(alphas)} mask renders of {num_chosen} Gaussians with "
        f"s_j > tau = {tau:g} to {out_dir}")
  if scene.train.masks is None:
    logging.info("scene %s has no masks/: no IoU computed.", scene.path)
    print("the scene has no ground-truth masks: no IoU computed")
    return None
  block = evaluation.iou_summary(scene.train.names, alphas, scene.train.masks)
  block |= {"tau": tau, "num_gaussians_above_tau": num_chosen}
  metrics_path = os.path.join(workdir, "metrics.json")
  metrics = {}
  if os.path.exists(metrics_path):
    with open(metrics_path) as f:
      metrics = json.load(f)
  metrics["mask_iou"] = block
  fileio.write_json(metrics_path, metrics)
  skipped = len(alphas) - block["num_views_scored"]
  mean = "n/a" if block["mean"] is None else f"{block['mean']:.4f}"
  print(f"mask IoU (alpha > {evaluation.MASK_ALPHA_THRESHOLD}): mean {mean} "
        "over "
        f"{block['num_views_scored']} views; {skipped} views left out (no "
        f"transient in the mask or the render); updated {metrics_path}")
  return block


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments {argv[1:]}")
  if FLAGS.tau is not None and not FLAGS.masks:
    raise app.UsageError("--tau applies to --masks only.")
  if FLAGS.masks:
    render_masks(FLAGS.workdir, FLAGS.tau)
  else:
    render_rgb(FLAGS.workdir)


if __name__ == "__main__":
  _define_flags()
  cli.run(main)
