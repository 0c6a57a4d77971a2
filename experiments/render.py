"""Renders a finished run along a smooth camera path into a video.

  python experiments/render.py --run=DIR [--compare=DIR2]
      [--path=orbit|train|test] [--seconds=10] [--fps=30] [--scores]
      --out=FILE.mp4|FILE.gif

--path=orbit flies an ellipse fitted to the training cameras, looking where
their optical axes meet; train and test pass through those cameras in name
order. --compare puts a second run of the same scene on the right, each
under its label (folder name, test PSNR); --scores lays s_j over a guided
run's render as colour (clipgs_jax/lab/video.py). MP4 is H.264 through the
ffmpeg that imageio-ffmpeg ships; GIF through Pillow.
"""

import json

from absl import flags

from clipgs_jax import cli
from clipgs_jax.lab import video

_RUN = flags.DEFINE_string("run", None, "Run folder (experiments/train.py "
                           "--workdir).")
_COMPARE = flags.DEFINE_string("compare", None, "A second run folder of the "
                               "same scene, shown on the right.")
_PATH = flags.DEFINE_string("path", "orbit", "Camera path: "
                            + ", ".join(video.PATHS) + ".")
_SECONDS = flags.DEFINE_float("seconds", 10.0, "Length of the video.")
_FPS = flags.DEFINE_float("fps", 30.0, "Frames per second.")
_OUT = flags.DEFINE_string("out", None, "Output file, .mp4 (H.264) or "
                           ".gif; its folder must exist.")
_SCORES = flags.DEFINE_bool("scores", False, "Lay each guided run's "
                            "transient score s_j over its render as colour.")
flags.mark_flags_as_required(["run", "out"])


def main(argv):
  cli.no_arguments(argv)
  plan = video.plan(_RUN.value, _COMPARE.value, _PATH.value, _SECONDS.value,
                    _FPS.value, _OUT.value, scores=_SCORES.value)
  print(json.dumps(video.write(plan)))


if __name__ == "__main__":
  cli.run(main)
