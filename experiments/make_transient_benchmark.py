"""Builds a RobustNeRF-layout transient benchmark from a static COLMAP scene.

  PYTHONPATH=. python experiments/make_transient_benchmark.py \
      --scene=COLMAP_DIR --distractors=PHOTO_DIR --out=DIR --seed=S \
      [--mode=independent|persistent] [--persist_views=5] \
      [--fraction=0.5] [--per_view=1..3] [--overwrite] [--cache_dir=DIR]

Layout, modes and determinism: `clipgs_jax/data/transients.py`. Photo
categories (person / clutter) come from `PHOTO_DIR/person/` and
`PHOTO_DIR/clutter/` subfolders, or a `PHOTO_DIR/categories.txt` manifest
with one `CATEGORY NAME` per line (`person me at the door.jpg`), or the
file names of ../shared/data/distractors (see
`clipgs_jax/data/distractors.py`). A bad input ends in one line on stderr
and exit status 1; nothing is left in --out.
"""

import time

from absl import flags

from clipgs_jax import cli
from clipgs_jax.data import transients

FLAGS = flags.FLAGS


def _define_flags() -> None:
  # Defined only when run as a script, so tests can import this module.
  flags.DEFINE_string("scene", None, "COLMAP scene folder (images/, "
                      "sparse/0/) without transients.")
  flags.DEFINE_string("distractors", None, "Folder of photos to paste "
                      "(person/ and clutter/ subfolders, or categories.txt).")
  flags.DEFINE_string("out", None, "Output scene folder (must not exist or "
                      "be empty, unless --overwrite).")
  flags.DEFINE_integer("seed", None, "Random seed (>= 0).")
  flags.DEFINE_enum("mode", "independent", list(transients.MODES),
                    "independent: 2D pastes, new in every view; persistent: "
                    "3D billboards seen by runs of --persist_views views.")
  flags.DEFINE_integer("persist_views", transients.DEFAULT_PERSIST_VIEWS,
                       "Consecutive training views per billboard "
                       "(--mode=persistent), e.g. 3-8.")
  flags.DEFINE_float("fraction", 0.5, "Fraction of training views (runs, "
                     "when persistent) that get transients, in [0, 1].")
  flags.DEFINE_string("per_view", "1..3", "Photos per cluttered view "
                      "(billboards per run): an integer or a range A..B.")
  flags.DEFINE_bool("overwrite", False, "Replace a non-empty --out.")
  flags.DEFINE_string("cache_dir", None, "Undistortion cache of --scene "
                      "(default: the one load_scene uses).")
  flags.mark_flags_as_required(["scene", "distractors", "out", "seed"])


def main(argv):
  cli.no_arguments(argv)
  tic = time.perf_counter()
  manifest = transients.build(
      FLAGS.scene, FLAGS.distractors, FLAGS.out, FLAGS.seed,
      fraction=FLAGS.fraction, per_view=FLAGS.per_view,
      overwrite=FLAGS.overwrite, cache_dir=FLAGS.cache_dir,
      mode=FLAGS.mode, persist_views=FLAGS.persist_views)
  counts = ", ".join(f"{n} {c}" for c, n in
                     sorted(manifest["transients_by_category"].items()))
  boards = (f", {len(manifest['billboards'])} billboards of "
            f"{manifest['persist_views']} views" if "billboards" in manifest
            else "")
  print(f"wrote {FLAGS.out} ({manifest['mode']}): {manifest['num_train']} "
        f"training views ({manifest['num_cluttered']} cluttered; "
        f"transients: {counts or 'none'}{boards}), {manifest['num_test']} "
        f"test views, in {time.perf_counter() - tic:.1f} s")


if __name__ == "__main__":
  _define_flags()
  cli.run(main)
