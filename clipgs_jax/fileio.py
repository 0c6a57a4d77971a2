"""Atomic file writes: a reader never sees a partial artefact."""

import json
import os
import tempfile


def atomic_write(path: str, write_fn, suffix: str = "") -> None:
  """Calls write_fn(tmp_path) and renames the result onto `path`.

  The temporary file lives in the same directory (so os.replace is an
  atomic rename) and keeps `suffix`, for writers that pick a format from
  the extension. A reader never sees a partial file.
  """
  directory = os.path.dirname(os.path.abspath(path))
  os.makedirs(directory, exist_ok=True)
  fd, tmp = tempfile.mkstemp(dir=directory, suffix=".tmp" + suffix,
                             prefix="." + os.path.basename(path) + ".")
  os.close(fd)
  try:
    try:
      write_fn(tmp)
    except OSError as e:
      if e.filename is not None or not e.errno:
        raise
      # The disk filled up (or the like) under a writer that does not name
      # its file; name the destination.
      raise OSError(e.errno, e.strerror, path) from e
    # mkstemp creates the file 0600; give it the usual umask-based mode.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    os.replace(tmp, path)
  except BaseException:
    if os.path.exists(tmp):
      os.remove(tmp)
    raise


def write_json(path: str, obj) -> None:
  """Atomic JSON write (indented, sorted keys, trailing newline)."""
  def write(tmp):
    with open(tmp, "w") as f:
      json.dump(obj, f, indent=2, sort_keys=True)
      f.write("\n")
  atomic_write(path, write, ".json")
