"""Tests for summary.py: TensorBoard event files written and read back."""

import os

import numpy as np

from clipgs_jax import summary


def test_written_values_read_back(tmp_path):
  writer = summary.Writer(str(tmp_path))
  writer.scalars(3, {"train/loss": 0.25, "test/psnr": 21.5})
  writer.image(3, "view/render", np.full((5, 7, 3), 0.5, np.float32))
  writer.image(4, "view/mask", np.ones((5, 7), bool))
  writer.histogram(4, "semantic/s_j", np.linspace(0, 1, 11),
                   bins=np.linspace(0, 1, 5))
  writer.histogram(4, "semantic/empty", np.zeros(0))    # writes nothing
  writer.close()
  rows = summary.read(str(tmp_path))
  assert [(r["step"], r["tag"], r["kind"], r["value"]) for r in rows] == [
      (3, "train/loss", "scalar", 0.25), (3, "test/psnr", "scalar", 21.5),
      (3, "view/render", "image", (5, 7)), (4, "view/mask", "image", (5, 7)),
      (4, "semantic/s_j", "histogram", 11.0)]


def test_a_resumed_writer_adds_a_file(tmp_path):
  for start in (0, 10):
    writer = summary.Writer(str(tmp_path), start_step=start)
    writer.scalars(start + 1, {"a": 1.0})
    writer.close()
  assert len(os.listdir(tmp_path)) == 2
  assert [r["step"] for r in summary.read(str(tmp_path))] == [1, 11]
