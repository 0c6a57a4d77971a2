"""Gaussians to and from the 3DGS PLY layout, through plyfile."""

import os
import re

import jax
import jax.numpy as jnp
import numpy as np
import plyfile

from clipgs_jax import fileio
from clipgs_jax import gaussians

# PLY format line -> (plyfile text flag, byte order).
FORMATS = {"binary_little_endian": (False, "<"),
           "binary_big_endian": (False, ">"), "ascii": (True, "=")}


def _field_names(num_rest: int) -> list[str]:
  """3DGS vertex properties, in the order 3DGS writes them."""
  return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] +
          [f"f_rest_{i}" for i in range(3 * num_rest)] +
          ["opacity", "scale_0", "scale_1", "scale_2",
           "rot_0", "rot_1", "rot_2", "rot_3"])


def write_ply(path: str, params: gaussians.GaussianParams, alive,
              fmt: str = "binary_little_endian") -> None:
  """Writes the alive Gaussians as a 3DGS-compatible PLY, atomically.

  Values are stored unconstrained, as 3DGS does: opacity as a logit, scales
  as logs, rotations as raw (w, x, y, z) quaternions, normals as zeros.
  f_rest is channel-major: every rest coefficient of R, then G, then B.

  Args:
    path: str, output file.
    params: GaussianParams with capacity C.
    alive: bool [C], which slots to write.
    fmt: a key of FORMATS; 3DGS writes binary_little_endian.
  """
  if fmt not in FORMATS:
    raise ValueError(f"write_ply: fmt={fmt!r} is not one of "
                     f"{', '.join(FORMATS)}.")
  gaussians.validate(params, jnp.asarray(alive))
  alive = np.asarray(alive)
  get = lambda x: np.asarray(x, np.float32)[alive]
  means, rest = get(params.means), get(params.sh_rest)     # rest [N, K, 3]
  n, k = means.shape[0], rest.shape[1]
  names = _field_names(k)
  columns = np.concatenate([
      means, np.zeros((n, 3), np.float32), get(params.sh_dc),
      rest.transpose(0, 2, 1).reshape(n, 3 * k),            # [N, 3 K]
      get(params.opacity_logits)[:, None], get(params.log_scales),
      get(params.quats)], axis=1)
  text, order = FORMATS[fmt]
  records = np.empty(n, np.dtype([(name, order + "f4") for name in names]))
  for i, name in enumerate(names):
    records[name] = columns[:, i]
  data = plyfile.PlyData([plyfile.PlyElement.describe(records, "vertex")],
                         text=text, byte_order=order)
  fileio.atomic_write(path, data.write, ".ply")


def _check_finite(records: np.ndarray, path: str) -> None:
  """Raises ValueError naming the fields and rows with NaN or Inf values.

  Such a file is rejected, not loaded with those rows dead: a trainer never
  writes them (train.fit stops on non-finite values), so they mark a broken
  producer or a damaged file, and a loader that quietly drops rows would
  return a different model than the file claims to hold.
  """
  bad_rows = np.zeros(len(records), bool)
  counts = {}
  for name in records.dtype.names:
    if records.dtype[name].kind != "f":
      continue
    bad = ~np.isfinite(records[name])
    if bad.any():
      counts[name] = int(bad.sum())
      bad_rows |= bad
  if counts:
    fields = ", ".join(f"{n} in {c} rows" for n, c in counts.items())
    first = int(np.argmax(bad_rows))
    raise ValueError(
        f"{path}: {int(bad_rows.sum())} of {len(records)} vertices hold NaN "
        f"or Inf ({fields}; first row {first}); re-export the file or drop "
        "those rows.")


def _vertex_records(path: str) -> np.ndarray:
  """The vertex element's structured array; PLY errors name the file."""
  if not os.path.isfile(path):
    raise FileNotFoundError(f"PLY file not found: {path}")
  try:
    data = plyfile.PlyData.read(path)
  except plyfile.PlyHeaderParseError as e:
    raise ValueError(f"{path} is not a readable PLY file ({e}).") from e
  except plyfile.PlyElementParseError as e:
    raise ValueError(f"{path}: truncated or malformed vertex data ({e})."
                     ) from e
  if "vertex" not in data:
    raise ValueError(f"{path}: PLY file has no vertex element.")
  vertex = data["vertex"]
  lists = [p.name for p in vertex.properties
           if isinstance(p, plyfile.PlyListProperty)]
  if lists:
    raise ValueError(f"{path}: unsupported vertex list properties {lists}; "
                     "3DGS vertex properties are scalars.")
  return vertex.data


def read_ply(path: str, capacity: int | None = None
             ) -> tuple[gaussians.GaussianParams, jax.Array]:
  """Reads a 3DGS PLY (as written by `write_ply` or by 3DGS itself).

  Any property order, extra properties and elements, and any PLY format
  (binary little- or big-endian, ASCII) are read.

  Args:
    path: str, input file.
    capacity: int or None, number of slots C; default: the file's count N.
      Slots past N are dead (alive False, zero parameters, identity quats).

  Returns:
    (GaussianParams of float32 jax arrays with capacity C, alive bool [C]).
  """
  records = _vertex_records(path)
  count = len(records)
  names = set(records.dtype.names or ())
  required = set(_field_names(0)) - {"nx", "ny", "nz"}
  missing = sorted(required - names)
  if missing:
    raise ValueError(f"{path} is not a 3DGS PLY: vertex properties "
                     f"{missing} are missing (3DGS writes x, y, z, f_dc_*, "
                     "opacity, scale_*, rot_* as binary_little_endian "
                     "floats).")
  _check_finite(records, path)
  rest_ids = sorted(int(m.group(1)) for name in names
                    if (m := re.fullmatch(r"f_rest_(\d+)", name)))
  k3 = len(rest_ids)
  if rest_ids != list(range(k3)) or k3 // 3 not in (0, 3, 8, 15) or k3 % 3:
    raise ValueError(f"{path}: expected f_rest_0 .. f_rest_{{3K-1}} with "
                     f"K in (0, 3, 8, 15) (SH degree 0-3), got {k3} f_rest "
                     "properties.")
  k = k3 // 3
  capacity = count if capacity is None else int(capacity)
  if capacity < count:
    raise ValueError(f"capacity={capacity} is smaller than the {count} "
                     f"Gaussians in {path}; pass a larger capacity.")

  def cols(*fields):
    out = np.zeros((capacity, len(fields)), np.float32)
    for i, f in enumerate(fields):
      out[:count, i] = records[f]
    return out

  rest = cols(*[f"f_rest_{i}" for i in range(k3)])
  quats = cols("rot_0", "rot_1", "rot_2", "rot_3")
  quats[count:, 0] = 1.0       # dead slots hold the identity rotation
  params = gaussians.GaussianParams(
      means=jnp.asarray(cols("x", "y", "z")),
      log_scales=jnp.asarray(cols("scale_0", "scale_1", "scale_2")),
      quats=jnp.asarray(quats),
      opacity_logits=jnp.asarray(cols("opacity")[:, 0]),
      sh_dc=jnp.asarray(cols("f_dc_0", "f_dc_1", "f_dc_2")),
      sh_rest=jnp.asarray(rest.reshape(capacity, 3, k).transpose(0, 2, 1)))
  alive = np.arange(capacity) < count
  return params, jnp.asarray(alive)
