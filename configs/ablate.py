"""Ablations of guidance: which part helps, and do the prompts matter.

  python experiments/train.py --config=configs/ablate.py --scene=BENCH
      --workdir=ROOT [--clip_weights=PATH] [--config.semantic.tau=T] ...

Rows, each one run into ROOT/<benchmark>/<row>/ with the settings of
configs/table.py (whose vanilla, oracle, clip and clean rows are the same
folders, so runs are shared and resumable):
  vanilla            3DGS on the clutter views (reference)
  oracle             ORACLE scorer, opacity loss and pruning (the table's)
  oracle_reg_only    ... opacity loss only (semantic.prune False)
  oracle_prune_only  ... pruning only (semantic.lambda_c 0)
  oracle_pixel       localized: the ground-truth mask per pixel (the table's)
  uniform_pixel      ... the masks' mean fraction at every pixel instead: a
                     uniform opacity penalty of the same total evidence (the
                     control for what the location buys)
  clip               CLIP scorer, the paper's distractor prompts
  clip_generic       CLIP scorer, generic prompts
  clean              3DGS on the clean views (upper bound)
The oracle ignores prompts, so the clip rows need --clip_weights; without
it they are listed as not run. Writes ROOT/<benchmark>/ablate.md and
ablate.json.
"""

import os

from clipgs_jax import config_file

GENERIC_PROMPTS = ("a photo of an object", "a photo of a thing")
DESCRIPTIONS = {
    "vanilla": "vanilla 3DGS (clutter)",
    "oracle": "ORACLE: opacity loss + pruning",
    "oracle_reg_only": "ORACLE: opacity loss only",
    "oracle_prune_only": "ORACLE: pruning only",
    "oracle_pixel": "ORACLE-PIXEL: localized evidence",
    "uniform_pixel": "UNIFORM control: the masks' mean at every pixel",
    "clip": "CLIP: paper prompts",
    "clip_generic": "CLIP: generic prompts",
    "clean": "3DGS on clean views (upper bound)",
}


def get_config():
  cd = config_file.load_file(os.path.join(os.path.dirname(__file__),
                                         "table.py"))
  rows = cd.sweep.row_overrides
  oracle = {"scorer": "oracle"}
  rows.oracle_reg_only = {"semantic": dict(oracle, prune=False)}
  rows.oracle_prune_only = {"semantic": dict(oracle, lambda_c=0.0)}
  rows.uniform_pixel = {"semantic": {"scorer": "uniform",
                                     "evidence": "pixel"}}
  rows.clip_generic = {"semantic": {
      "scorer": "clip", "distractor_prompts": GENERIC_PROMPTS}}
  cd.sweep.kind = "ablate"
  cd.sweep.rows = ",".join(DESCRIPTIONS)
  cd.sweep.descriptions = DESCRIPTIONS
  return cd
