"""Where the real captures live, and the skip marker for tests that need them."""

import pathlib

import pytest

DATA = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "data"


def needs_data(*scenes: str):
  """Skips a test unless every named scene folder exists under DATA."""
  return pytest.mark.skipif(
      not all((DATA / s).is_dir() for s in scenes),
      reason=f"real data not found at {DATA} (a fresh clone has no ../shared)")
