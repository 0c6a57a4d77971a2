"""Prune-threshold sweep: quality and fraction pruned per tau, s_j histogram.

  python experiments/train.py --config=configs/tau_sweep.py --scene=BENCH
      --workdir=ROOT [--config.sweep.taus=0.3,0.02] [--clip_weights=PATH
      --config.sweep.scorer=clip] ...

One guided run per tau into ROOT/<benchmark>/<scorer>_tau<T>/, next to the
table's vanilla row (ROOT/<benchmark>/vanilla, run here too when missing),
with the settings of configs/table.py. Writes into ROOT/<benchmark>:
calibrate_tau.md / .json (tau, PSNR, ΔPSNR, SSIM, LPIPS, Gaussians,
fraction pruned by score and by the n_min/alpha_min rule, and Otsu's
threshold of the first-prune histogram, computed, not run) and
s_j_histogram.png.
"""

import os

from clipgs_jax import config_file

PAPER_TAUS = "0.3,0.02,0.015,0.01"   # the paper's Table 5 sweep


def get_config():
  cd = config_file.load_file(os.path.join(os.path.dirname(__file__),
                                         "table.py"))
  cd.sweep.kind = "tau_sweep"
  cd.sweep.taus = PAPER_TAUS
  cd.sweep.scorer = "oracle"       # or clip (needs --clip_weights)
  cd.sweep.rows = "vanilla"        # run first; then one row per tau
  return cd
