"""Checks of COLMAP model files before pycolmap reads them.

pycolmap trusts what it reads (a truncated points3D.bin made it allocate
memory without bound), so colmap.read_reconstruction runs these first: the
binary records are walked byte by byte, and text camera models are named.
"""

import os
import struct


class _Reader:
  """Bounds-checked little-endian reads from one binary model file."""

  def __init__(self, path: str):
    self.path = path
    with open(path, "rb") as f:
      self.data = f.read()
    self.pos = 0

  def fail(self, what: str):
    name = os.path.basename(self.path)
    raise ValueError(f"corrupt COLMAP file {self.path}: {what} at byte "
                     f"{self.pos} of {len(self.data)}; re-export {name} "
                     "with COLMAP.")

  def read(self, fmt: str):
    size = struct.calcsize("<" + fmt)
    if self.pos + size > len(self.data):
      self.fail("file ends early (truncated or empty)")
    values = struct.unpack_from("<" + fmt, self.data, self.pos)
    self.pos += size
    return values

  def skip(self, size: int):
    if self.pos + size > len(self.data):
      self.fail("file ends early (truncated or empty)")
    self.pos += size

  def count(self, min_record: int) -> int:
    (n,) = self.read("Q")
    if n * min_record > len(self.data) - self.pos:
      self.fail(f"record count {n} does not fit the file")
    return n

  def finish(self):
    if self.pos != len(self.data):
      self.fail("unexpected trailing bytes")


def _num_params() -> dict[int, tuple[str, int]]:
  """Camera model id -> (name, number of parameters), from pycolmap itself."""
  import pycolmap  # pylint: disable=import-outside-toplevel  # see colmap.py
  table = {}
  for name, model_id in pycolmap.CameraModelId.__members__.items():
    if name == "INVALID":
      continue
    cam = pycolmap.Camera.create_from_model_id(0, model_id, 1.0, 2, 2)
    table[int(model_id)] = (name, len(cam.params))
  return table


def check_binary(folder: str) -> None:
  """Walks every record of the .bin files before pycolmap reads them.

  pycolmap trusts the record counts it reads: a truncated points3D.bin made
  it allocate memory without bound here, instead of raising. So the layout
  (COLMAP's documented little-endian records) is verified first.
  """
  models = _num_params()
  path = os.path.join(folder, "cameras.bin")
  r = _Reader(path)
  for _ in range(r.count(24)):
    cam_id, model_id, _, _ = r.read("iiQQ")
    if model_id not in models:
      raise ValueError(
          f"{path}: camera {cam_id} has unknown camera model id {model_id}; "
          f"supported: {', '.join(n for n, _ in models.values())}.")
    r.skip(8 * models[model_id][1])
  r.finish()
  path = os.path.join(folder, "rigs.bin")
  if os.path.isfile(path):
    r = _Reader(path)
    for _ in range(r.count(8)):
      _, num_sensors = r.read("II")
      if num_sensors > 0:
        r.skip(8)
      for _ in range(max(0, num_sensors - 1)):
        _, _, has_pose = r.read("iIB")
        r.skip(56 if has_pose else 0)
    r.finish()
  path = os.path.join(folder, "frames.bin")
  if os.path.isfile(path):
    r = _Reader(path)
    for _ in range(r.count(68)):
      r.skip(64)
      (num_data,) = r.read("I")
      r.skip(16 * num_data)
    r.finish()
  path = os.path.join(folder, "images.bin")
  r = _Reader(path)
  for _ in range(r.count(73)):
    r.skip(64)
    end = r.data.find(b"\0", r.pos)
    if end < 0:
      r.fail("image name is not terminated")
    r.pos = end + 1
    (num_points2d,) = r.read("Q")
    r.skip(24 * num_points2d)
  r.finish()
  path = os.path.join(folder, "points3D.bin")
  r = _Reader(path)
  for _ in range(r.count(51)):
    r.skip(43)
    (track_len,) = r.read("Q")
    r.skip(8 * track_len)
  r.finish()


def check_text(folder: str) -> None:
  """Checks camera model names in cameras.txt (clearer than pycolmap's)."""
  import pycolmap  # pylint: disable=import-outside-toplevel  # see colmap.py
  names = {n for n in pycolmap.CameraModelId.__members__ if n != "INVALID"}
  path = os.path.join(folder, "cameras.txt")
  with open(path, encoding="utf-8", errors="replace") as f:
    for line_no, line in enumerate(f, 1):
      fields = line.split()
      if not fields or fields[0].startswith("#"):
        continue
      if len(fields) < 2 or fields[1] not in names:
        model = fields[1] if len(fields) > 1 else "(none)"
        raise ValueError(
            f"{path}:{line_no}: unknown camera model {model}; supported: "
            f"{', '.join(sorted(names))}.")
