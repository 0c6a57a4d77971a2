"""TensorBoard event files of a run, written through tensorboardX.

tensorboardX writes the event-file format without TensorFlow (clu's metric
writers import it); `tensorboard --logdir RUN/tensorboard` shows them
(`pip install tensorboard`, not a dependency). `read` parses them back
without either, for tests and scripts.
"""

import glob
import os
import struct
import sys
from typing import Any

import numpy as np


def _tensorboardx():
  """The tensorboardX module, imported without torch.

  Where torch is installed tensorboardX imports it, only to name a type in
  its signatures; that import took 4.4 s (against 0.5 s without it) and a
  few hundred MB of every training process on the 2-core box, where
  nothing of ours uses torch. A None in sys.modules makes `import torch`
  raise ImportError, which tensorboardX expects; it is removed at once.
  """
  if "torch" in sys.modules:
    import tensorboardX  # pylint: disable=g-import-not-at-top
    return tensorboardX
  sys.modules["torch"] = None
  try:
    import tensorboardX  # pylint: disable=g-import-not-at-top
  finally:
    del sys.modules["torch"]
  return tensorboardX


class Writer:
  """Scalars, images and histograms of one run, by training step.

  A resumed run opens a new writer with `start_step` = the checkpoint's
  step and writes to a new file in `logdir`; TensorBoard hides the earlier
  files' events after that step (a killed run may have logged steps that
  its last checkpoint does not hold, and the resumed run redoes them).
  """

  def __init__(self, logdir: str, start_step: int = 0):
    os.makedirs(logdir, exist_ok=True)
    # Files are named by the second they were opened in; the start step
    # and process keep a quick resume from overwriting the killed run's.
    self._writer = _tensorboardx().SummaryWriter(
        logdir, purge_step=start_step + 1 if start_step > 0 else None,
        filename_suffix=f".step{start_step:09d}.{os.getpid()}")

  def scalars(self, step: int, values: dict[str, float]) -> None:
    """One point per tag (e.g. "train/loss") at `step`."""
    for tag, value in values.items():
      self._writer.add_scalar(tag, float(value), step)

  def image(self, step: int, tag: str, image) -> None:
    """float [H, W, 3] or [H, W] in [0, 1] (clipped), at `step`."""
    image = np.clip(np.asarray(image, np.float32), 0.0, 1.0)
    if image.ndim == 2:
      image = np.repeat(image[..., None], 3, axis=-1)
    self._writer.add_image(tag, image, step, dataformats="HWC")

  def histogram(self, step: int, tag: str, values, bins="tensorflow"
                ) -> None:
    """The distribution of float [N] `values`; `bins` as np.histogram's
    (edges or a count) or tensorboardX's "tensorflow" default."""
    values = np.asarray(values, np.float64).ravel()
    if values.size:
      self._writer.add_histogram(tag, values, step, bins=bins)

  def flush(self) -> None:
    self._writer.flush()

  def close(self) -> None:
    self._writer.close()


def _records(path: str):
  """The payloads of a TFRecord file (length, crc, data, crc per record)."""
  with open(path, "rb") as f:
    while header := f.read(12):
      (length,) = struct.unpack("<Q", header[:8])
      data = f.read(length)
      f.read(4)                      # the payload's crc
      if len(data) < length:
        return                       # a file still being written
      yield data


def read(logdir: str) -> list[dict[str, Any]]:
  """Every summary value in `logdir`'s event files, in file order.

  Returns:
    [{"step", "tag", "kind": "scalar" | "image" | "histogram", "value":
    float | (height, width) | bucket count}].
  """
  event_pb2 = _tensorboardx().proto.event_pb2
  out = []
  for path in sorted(glob.glob(os.path.join(logdir, "events.out.tfevents*"))):
    for data in _records(path):
      event = event_pb2.Event.FromString(data)
      for v in event.summary.value:
        kind = v.WhichOneof("value")
        if kind == "simple_value":
          row = {"kind": "scalar", "value": v.simple_value}
        elif kind == "image":
          row = {"kind": "image", "value": (v.image.height, v.image.width)}
        elif kind == "histo":
          row = {"kind": "histogram", "value": v.histo.num}
        else:
          continue
        out.append({"step": event.step, "tag": v.tag} | row)
  return out
