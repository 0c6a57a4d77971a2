"""A tiny CI run: 60 steps that run every stage of training.

  python experiments/train.py --config=configs/smoke.py --workdir=OUT

A small capacity (2x the points, at most 16k) and 60 steps that run
densification (with capacity growth), pruning, the SH raise, evaluation and
checkpoints.
"""

from clipgs_jax import config as config_lib
from clipgs_jax import config_file


def get_config():
  cd = config_file.to_config_dict(config_lib.Config())
  cd.gaussians.update(capacity=0, min_capacity=256, max_capacity=16384,
                      sh_degree=1, random_init_points=500)
  # Densify at 20 and 30, SH degree 1 from 20. No opacity reset: it needs
  # thousands of steps to recover from (tests/test_densify.py and
  # tests/test_train.py cover it), and a CI run should show the test PSNR
  # rising.
  cd.densify.update(start=10, stop=35, every=10, opacity_reset_every=0,
                    sh_degree_every=20)
  cd.train.update(steps=60, log_every=10, eval_every=20, checkpoint_every=30)
  cd.eval.curve_points = 0       # keep eval_every = 20: three curve points
  return cd
