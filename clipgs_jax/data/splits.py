"""Which views of a scene train and which test: RobustNeRF names, the
capture's own test file, or every 8th view."""

import os

from clipgs_jax import config as config_lib

# RobustNeRF file-name tokens: `extra` views are clean held-out test views,
# `clutter` views have distractors, `clean` views are their clean twins.
ROBUSTNERF_TOKENS = ("clutter", "extra", "clean")
TRAIN_SPLITS = config_lib.TRAIN_SPLITS
# Without RobustNeRF names, every 8th image by name is a test view (the
# convention of Mip-NeRF 360 and 3DGS), in colmap.natural_key order: the
# plain sorted order for zero-padded numbers, capture order for 1..N.
TEST_EVERY = 8


def _name_tokens(names) -> list[list[str]]:
  """The RobustNeRF split words in each image's file name."""
  return [[t for t in ROBUSTNERF_TOKENS if t in os.path.basename(n)]
          for n in names]


def split(names, train_split: str, where: str, test_views=None
          ) -> tuple[list[int], list[int]]:
  """(train indices, test indices) into `names` (colmap.Model order).

  Args:
    names: the views' image names.
    train_split: "clutter" or "clean" (RobustNeRF names only).
    where: the model's folder or file, for errors.
    test_views: colmap.Model.test_views, the capture's own split (a
      transforms scene's transforms_test.json), or None.
  """
  if test_views is not None:
    test = sorted(test_views)
    train = [i for i in range(len(names)) if i not in set(test)]
    if not train or not test:
      raise ValueError(f"{where} and its test file give {len(train)} "
                       f"training and {len(test)} test views; both splits "
                       "need views.")
    return train, test
  tokens = _name_tokens(names)
  if any(tokens):
    # RobustNeRF naming: every image must say which split it belongs to.
    for name, found in zip(names, tokens):
      if len(found) != 1:
        raise ValueError(
            f"image {name} in {where} has {found or 'none'} of the "
            f"RobustNeRF split words {ROBUSTNERF_TOKENS} in its name, "
            "expected exactly one; rename it.")
    test = [i for i, t in enumerate(tokens) if t[0] == "extra"]
    train = [i for i, t in enumerate(tokens) if t[0] == train_split]
    if not test:
      raise ValueError(f"no test views in {where}: RobustNeRF names "
                       "found but no image name contains 'extra'; add clean "
                       "held-out 'extra' views.")
    if not train:
      raise ValueError(f"no training views in {where}: no image name "
                       f"contains {train_split!r}; pick another train_split.")
    return train, test
  test = list(range(0, len(names), TEST_EVERY))
  train = [i for i in range(len(names)) if i % TEST_EVERY]
  if not train:
    raise ValueError(f"no training views in {where}: only {len(names)} "
                     f"registered image(s), every {TEST_EVERY}th is held out "
                     "for testing; register more images.")
  return train, test


def train_splits(names) -> tuple[str, ...]:
  """The train splits of a folder scene: those named in a RobustNeRF one,
  () for other scenes (their train_split is ignored)."""
  tokens = _name_tokens(names)
  return tuple(t for t in TRAIN_SPLITS if any(t in found for found in tokens))
