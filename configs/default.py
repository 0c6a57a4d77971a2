"""One run with the 3DGS paper values (config.Config's defaults).

  python experiments/train.py --workdir=OUT [--scene=DIR]
      [--config.train.steps=N] [--config.data.downscale=K] ...

train.steps is None: 30k steps (3DGS) on a --scene, and
default_scene.TRAIN_STEPS on the embedded scene (no --scene).
"""

from ml_collections import config_dict

from clipgs_jax import config as config_lib
from clipgs_jax import config_file


def get_config():
  cd = config_file.to_config_dict(config_lib.Config())
  cd.train.steps = config_dict.placeholder(int)   # None: auto, see above
  return cd
