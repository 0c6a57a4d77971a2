"""Recomputes a finished run's test metrics from what it saved.

  python experiments/evaluate.py --workdir=DIR [--source=auto|checkpoint|ply]
      [--lpips_net=alex|vgg] [--dry_run]

Reads DIR/run.json (scene and downscale), DIR/config.json and the trained
Gaussians (DIR/checkpoint.npz, or DIR/point_cloud.ply when there is no
checkpoint or --source=ply), renders every test view, and replaces the
"test" block of DIR/metrics.json (atomically) unless --dry_run. Prints the
new and the stored numbers side by side.
"""

import json
import os
import sys
import time

from absl import app
from absl import flags
from absl import logging

from clipgs_jax import checkpoint
from clipgs_jax import cli
from clipgs_jax import config as config_lib
from clipgs_jax import evaluation
from clipgs_jax import ply
from clipgs_jax import train
from clipgs_jax.data import images as images_lib
from clipgs_jax.data import scene as scene_lib

FLAGS = flags.FLAGS


def _define_flags() -> None:
  # Defined only when run as a script: experiments/train.py imports
  # `test_metrics`, and its --help must not list these.
  flags.DEFINE_string("workdir", None, "Run folder written by train.py.")
  flags.DEFINE_enum("source", "auto", ["auto", "checkpoint", "ply"],
                    "Where the Gaussians come from (auto: the checkpoint "
                    "if present, else the PLY).")
  flags.DEFINE_enum("lpips_net", None, ["alex", "vgg"],
                    "LPIPS backbone (default: the one the run used).")
  flags.DEFINE_bool("dry_run", False, "Print only; leave metrics.json.")
  flags.mark_flag_as_required("workdir")


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


def _read_json(path: str, what: str) -> dict:
  if not os.path.exists(path):
    raise FileNotFoundError(f"evaluate: {path} is missing; --workdir must be "
                            f"a run folder written by train.py ({what}).")
  with open(path) as f:
    return json.load(f)


def load_run(workdir: str):
  """(run.json dict, resolved config, scene) of a run folder of train.py.

  A run.json without "train_split" (older runs) means "clutter".
  """
  run = _read_json(os.path.join(workdir, "run.json"), "scene and downscale")
  cfg = config_lib.from_dict(_read_json(os.path.join(workdir, "config.json"),
                                        "the resolved config"))
  scene = scene_lib.load_scene(run["scene"], downscale=run["downscale"],
                               train_split=run.get("train_split", "clutter"))
  return run, cfg, scene


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments {argv[1:]}")
  workdir = FLAGS.workdir
  run, cfg, scene = load_run(workdir)
  ckpt = os.path.join(workdir, train.CHECKPOINT_NAME)
  ply_path = os.path.join(workdir, "point_cloud.ply")
  source = FLAGS.source
  if source == "auto":
    source = "checkpoint" if os.path.exists(ckpt) else "ply"
  if source == "checkpoint":
    state, _ = checkpoint.restore(ckpt, train.initial_state(cfg, scene))
    params, alive = state.params, state.alive
  else:
    if not os.path.exists(ply_path):
      sys.exit(f"evaluate: {ply_path} is missing; pass --source=checkpoint.")
    params, alive = ply.read_ply(ply_path)
  lpips_net = FLAGS.lpips_net or run.get("lpips_net", "alex")
  new = test_metrics(params, alive, scene.test, cfg, lpips_net)
  metrics_path = os.path.join(workdir, "metrics.json")
  stored = {}
  if os.path.exists(metrics_path):
    with open(metrics_path) as f:
      stored = json.load(f)
  old = stored.get("test", {})
  print(f"source: {source}; {new['num_views']} test views; LPIPS "
        f"backbone: {lpips_net}")
  for key in ("psnr", "ssim", "lpips"):
    before = old.get(key)
    before = "-" if before is None else f"{before:.4f}"
    print(f"  {key:6s} now {new[key]:.4f}   stored {before}")
  if not FLAGS.dry_run:
    stored["test"] = new
    stored["test_source"] = source
    checkpoint.write_json(metrics_path, stored)
    logging.info("updated %s", metrics_path)


if __name__ == "__main__":
  _define_flags()
  cli.run(main)
