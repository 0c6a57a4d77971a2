"""Test setup: CPU only, fast compiles, absl flags parsed."""

import os

# Must happen before jax is imported anywhere.
os.environ["JAX_PLATFORMS"] = "cpu"

import jax  # pylint: disable=g-import-not-at-top
from absl import flags  # pylint: disable=g-import-not-at-top

jax.config.update("jax_disable_most_optimizations", True)
# absl raises UnparsedFlagAccessError under pytest otherwise.
flags.FLAGS.mark_as_parsed()
