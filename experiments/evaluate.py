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

from absl import app
from absl import flags
from absl import logging

from clipgs_jax import checkpoint
from clipgs_jax import cli
from clipgs_jax import fileio
from clipgs_jax import ply
from clipgs_jax import run as run_lib
from clipgs_jax import train

FLAGS = flags.FLAGS


def _define_flags() -> None:
  flags.DEFINE_string("workdir", None, "Run folder written by train.py.")
  flags.DEFINE_enum("source", "auto", ["auto", "checkpoint", "ply"],
                    "Where the Gaussians come from (auto: the checkpoint "
                    "if present, else the PLY).")
  flags.DEFINE_enum("lpips_net", None, ["alex", "vgg"],
                    "LPIPS backbone (default: the one the run used).")
  flags.DEFINE_bool("dry_run", False, "Print only; leave metrics.json.")
  flags.mark_flag_as_required("workdir")


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments {argv[1:]}")
  workdir = FLAGS.workdir
  run, cfg, scene = run_lib.load_run(workdir)
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
      raise FileNotFoundError(f"{ply_path} is missing; pass "
                              "--source=checkpoint.")
    params, alive = ply.read_ply(ply_path)
  lpips_net = FLAGS.lpips_net or run.get("lpips_net", "alex")
  new = run_lib.test_metrics(params, alive, scene.test, cfg, lpips_net)
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
    fileio.write_json(metrics_path, stored)
    logging.info("updated %s", metrics_path)


if __name__ == "__main__":
  _define_flags()
  cli.run(main)
