"""Shows a finished run in the browser (viser), until Ctrl-C.

  python experiments/view.py --run=DIR [--compare=DIR2] [--port=8080]
      [--host=127.0.0.1]

Open the printed address: the run's Gaussians as splats, its cameras as
frustums (click one: the view moves there and the panel shows its photo,
our render, its transient map and ground-truth mask), and for guided runs
s_j as colour, a tau slider that highlights what a prune would remove, and
the rows the run pruned. --compare switches between two runs of the same
scene from the same camera (clipgs_jax/lab/viewer.py).
"""

from absl import flags

from clipgs_jax import cli
from clipgs_jax.lab import viewer

_RUN = flags.DEFINE_string("run", None, "Run folder (experiments/train.py "
                           "--workdir).")
_COMPARE = flags.DEFINE_string("compare", None, "A second run folder of the "
                               "same scene, switched to in the panel.")
_PORT = flags.DEFINE_integer("port", 8080, "Port to serve on.")
_HOST = flags.DEFINE_string("host", "127.0.0.1", "Address to serve on; "
                            "0.0.0.0 serves every network.")
flags.mark_flag_as_required("run")


def main(argv):
  cli.no_arguments(argv)
  cli.require(0 < _PORT.value < 65536, "port", _PORT.value,
              "is not a port number (1-65535)")
  viewer.serve(_RUN.value, _COMPARE.value, host=_HOST.value,
               port=_PORT.value)


if __name__ == "__main__":
  cli.run(main)
