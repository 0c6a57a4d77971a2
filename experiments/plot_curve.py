"""Plots test error against training time from one or more curve.json files.

  python experiments/plot_curve.py --curves=RUN1/curve.json,RUN2/curve.json \
      --out=curve.png [--labels=a,b] [--x=seconds|step]

Each curve.json is a list of {step, seconds, test_psnr} (written by
experiments/train.py); the y axis is the test MSE on a log scale,
10^(-PSNR / 10), so lower is better and equal dB steps are equal distances.
"""


from absl import app
from absl import flags

from clipgs_jax import cli
from clipgs_jax import plots

FLAGS = flags.FLAGS


def _define_flags() -> None:
  # Defined only when run as a script: experiments/train.py imports `plot`,
  # and these flags must not show up in its --help.
  flags.DEFINE_list("curves", None, "curve.json files to plot.")
  flags.DEFINE_string("out", None, "Output PNG path.")
  flags.DEFINE_list("labels", None, "Legend labels (default: run folders).")
  flags.DEFINE_enum("x", "seconds", ["seconds", "step"], "x axis.")


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments {argv[1:]}")
  if not FLAGS.curves or not FLAGS.out:
    raise app.UsageError("pass --curves=a/curve.json[,b/curve.json] and "
                         "--out=plot.png")
  plots.plot(FLAGS.curves, FLAGS.out, FLAGS.labels, FLAGS.x)


if __name__ == "__main__":
  _define_flags()
  cli.run(main)
