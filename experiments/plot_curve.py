"""Plots test error against training time from one or more curve.json files.

  python experiments/plot_curve.py --curves=RUN1/curve.json,RUN2/curve.json \
      --out=curve.png [--labels=a,b] [--x=seconds|step]

Each curve.json is a list of {step, seconds, test_psnr} (written by
experiments/train.py); the y axis is the test MSE on a log scale,
10^(-PSNR / 10), so lower is better and equal dB steps are equal distances.
"""

import json
import os
import sys

from absl import app
from absl import flags

import matplotlib
matplotlib.use("Agg")   # files only; no display on the training machines
import matplotlib.pyplot as plt  # pylint: disable=g-import-not-at-top,wrong-import-position

from clipgs_jax import checkpoint  # pylint: disable=g-import-not-at-top,wrong-import-position
from clipgs_jax import cli  # pylint: disable=g-import-not-at-top,wrong-import-position

FLAGS = flags.FLAGS


def _define_flags() -> None:
  # Defined only when run as a script: experiments/train.py imports `plot`,
  # and these flags must not show up in its --help.
  flags.DEFINE_list("curves", None, "curve.json files to plot.")
  flags.DEFINE_string("out", None, "Output PNG path.")
  flags.DEFINE_list("labels", None, "Legend labels (default: run folders).")
  flags.DEFINE_enum("x", "seconds", ["seconds", "step"], "x axis.")


def _read(path: str) -> list[dict]:
  with open(path) as f:
    curve = json.load(f)
  if not isinstance(curve, list) or not all(
      {"step", "seconds", "test_psnr"} <= set(p) for p in curve):
    raise ValueError(f"plot_curve: {path} is not a list of {{step, seconds, "
                     "test_psnr}} points; pass a curve.json from train.py.")
  return curve


def save_figure(fig, out_path: str) -> None:
  """Lays out `fig`, writes it as a PNG atomically and closes it."""
  fig.tight_layout()
  try:
    checkpoint.atomic_write(out_path, fig.savefig, ".png")
  finally:
    plt.close(fig)


def plot(curve_paths: list[str], out_path: str,
         labels: list[str] | None = None, x: str = "seconds") -> None:
  """Writes the error-against-time plot of the given curves, atomically."""
  if labels is not None and len(labels) != len(curve_paths):
    raise ValueError(f"plot_curve: {len(labels)} labels for "
                     f"{len(curve_paths)} curves.")
  fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
  for i, path in enumerate(curve_paths):
    curve = _read(path)
    label = (labels[i] if labels else
             os.path.basename(os.path.dirname(os.path.abspath(path))))
    xs = [p[x] for p in curve]
    mse = [10 ** (-p["test_psnr"] / 10) for p in curve]
    ax.plot(xs, mse, marker="o", markersize=3, label=label)
    if curve:
      ax.annotate(f"{curve[-1]['test_psnr']:.2f} dB", (xs[-1], mse[-1]),
                  textcoords="offset points", xytext=(4, 4), fontsize=8)
  ax.set_yscale("log")
  ax.set_xlabel("training time (s, evaluation excluded)" if x == "seconds"
                else "step")
  ax.set_ylabel("test MSE = 10^(-PSNR/10)")
  ax.grid(True, which="both", alpha=0.3)
  ax.legend(fontsize=8)
  save_figure(fig, out_path)


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments {argv[1:]}")
  if not FLAGS.curves or not FLAGS.out:
    sys.exit("plot_curve: pass --curves=a/curve.json[,b/curve.json] and "
             "--out=plot.png")
  plot(FLAGS.curves, FLAGS.out, FLAGS.labels, FLAGS.x)


if __name__ == "__main__":
  _define_flags()
  cli.run(main)
