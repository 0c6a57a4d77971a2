"""Test setup: CPU only, fast compiles, absl flags, two xdist workers."""

import os
import subprocess
import sys

import pytest

# Must happen before jax is imported anywhere.
os.environ["JAX_PLATFORMS"] = "cpu"

# XLA:CPU's fusion emitters take most of a test program's compile; the older
# emitters compile the tests' train step ~3x faster (BUILD_NOTES.md, "Test and
# compile time"). XLA aborts the process on a flag it does not know, and newer
# XLA may drop this one (openxla/xla#48001), so it is set only where a child
# process accepts it. Set before the xdist workers, the notebook kernel and
# the scripts' subprocesses start, so they inherit it.
FAST_COMPILE_XLA_FLAG = "--xla_cpu_use_fusion_emitters=false"


def _xla_accepts(flags: str) -> bool:
  probe = subprocess.run(
      [sys.executable, "-c", "import jax; jax.devices()"],
      env=dict(os.environ, XLA_FLAGS=flags), capture_output=True,
      check=False)
  return probe.returncode == 0


if FAST_COMPILE_XLA_FLAG not in os.environ.get("XLA_FLAGS", ""):
  _flags = f"{os.environ.get('XLA_FLAGS', '')} {FAST_COMPILE_XLA_FLAG}".strip()
  if _xla_accepts(_flags):
    os.environ["XLA_FLAGS"] = _flags

import jax  # pylint: disable=g-import-not-at-top
from absl import flags  # pylint: disable=g-import-not-at-top

jax.config.update("jax_disable_most_optimizations", True)
# absl raises UnparsedFlagAccessError under pytest otherwise.
flags.FLAGS.mark_as_parsed()

# The suite's time is mostly single-threaded XLA compiles, so two
# xdist worker processes use both cores of the 2-core box. Each file runs
# whole on one worker (--dist loadfile), so the programs its tests share are
# compiled once.
DEFAULT_WORKERS = 2


@pytest.hookimpl(tryfirst=True)
def pytest_cmdline_main(config):
  """Runs on DEFAULT_WORKERS xdist workers unless -n (or -p no:xdist) says.

  Called before xdist's own hook of the same name (conftest hooks run
  first), which turns numprocesses into worker processes.
  """
  if (config.pluginmanager.hasplugin("xdist")
      and not hasattr(config, "workerinput")      # not inside a worker
      and config.option.numprocesses is None):
    config.option.numprocesses = DEFAULT_WORKERS
    if config.option.dist == "no":
      config.option.dist = "loadfile"
    # xdist (>= 3.6) deals files by their number of tests unless told not
    # to, which dealt the one-test notebook (50 s) and the few-test end to
    # end files last: one worker ran 94 s longer than the other
    # (BUILD_NOTES.md, "Test and compile time").
    config.option.loadscopereorder = False


# The slowest files, started first, slowest first (seconds of pytest
# --durations on a quiet box, 2026-11-24): a slow file dealt last would leave
# the other worker idle at the end. Files not named follow in their order.
SLOW_FILES_FIRST = (
    "test_viewer.py",              # 191 under load 15; 55 s of CPU
    "test_table.py",               # 76
    "test_guidance.py",            # 70
    "test_notebook.py",            # 50
    "test_rasterize.py",           # 47
    "test_guidance_e2e.py",        # 43
    "test_rasterize_evidence.py",  # 33
    "test_train.py",               # 31
    "test_rasterize_extreme.py",   # 30
    "test_clip_parity.py",         # 29
    "test_clip_dense.py",          # 29
    "test_bad_inputs.py",          # 27
    "test_report.py",              # 21
    "test_clip_model.py",          # 20
    "test_rasterize_lanes.py",     # 19
    "test_resume.py",              # 18
    "test_densify.py",             # 14
    "test_metrics.py",             # 11
    "test_scripts.py")             # 11


def pytest_collection_modifyitems(items):
  """Moves the files in SLOW_FILES_FIRST to the front, in that order."""
  rank = {name: i for i, name in enumerate(SLOW_FILES_FIRST)}
  items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
