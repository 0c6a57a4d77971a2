"""Tests for ply.py: the 3DGS PLY layout and exact round trips."""

import os

import jax.numpy as jnp
import numpy as np
import plyfile
import pytest

from clipgs_jax import gaussians
from clipgs_jax import ply


def _random_params(capacity, k, seed=0):
  rng = np.random.default_rng(seed)
  f = lambda *s: jnp.asarray(rng.normal(size=s).astype(np.float32))
  return gaussians.GaussianParams(
      means=f(capacity, 3), log_scales=f(capacity, 3), quats=f(capacity, 4),
      opacity_logits=f(capacity), sh_dc=f(capacity, 3),
      sh_rest=f(capacity, k, 3))


def _header(path):
  with open(path, "rb") as fh:
    data = fh.read()
  end = data.index(b"end_header\n") + len(b"end_header\n")
  return data[:end].decode().splitlines(), data[end:]


@pytest.mark.parametrize("k", [0, 3, 15])
def test_round_trip_is_exact(tmp_path, k):
  params = _random_params(10, k)
  alive = jnp.array([True, False, True, True, False, True, True, True, False,
                     True])
  path = str(tmp_path / "g.ply")
  ply.write_ply(path, params, alive)
  back, back_alive = ply.read_ply(path)
  assert back.capacity == 7 and bool(back_alive.all())
  keep = np.asarray(alive)
  for field in ("means", "log_scales", "quats", "opacity_logits", "sh_dc",
                "sh_rest"):
    np.testing.assert_array_equal(np.asarray(getattr(back, field)),
                                  np.asarray(getattr(params, field))[keep])
  gaussians.validate(back, back_alive)
  assert os.listdir(tmp_path) == ["g.ply"]           # no temp file left


def test_3dgs_field_layout(tmp_path):
  params = _random_params(4, 3)
  path = str(tmp_path / "g.ply")
  ply.write_ply(path, params, jnp.ones(4, bool))
  lines, body = _header(path)
  assert lines[:3] == ["ply", "format binary_little_endian 1.0",
                       "element vertex 4"]
  props = [line.split()[2] for line in lines if line.startswith("property")]
  assert all(line.split()[1] == "float" for line in lines
             if line.startswith("property"))
  assert props == (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1",
                    "f_dc_2"] + [f"f_rest_{i}" for i in range(9)] +
                   ["opacity", "scale_0", "scale_1", "scale_2", "rot_0",
                    "rot_1", "rot_2", "rot_3"])
  rows = np.frombuffer(body, "<f4").reshape(4, len(props))
  col = {name: rows[:, i] for i, name in enumerate(props)}
  rest = np.asarray(params.sh_rest)                   # [C, K, 3]
  # Channel-major: f_rest_{c * K + k} = coefficient k of channel c.
  np.testing.assert_array_equal(col["f_rest_1"], rest[:, 1, 0])
  np.testing.assert_array_equal(col["f_rest_3"], rest[:, 0, 1])
  np.testing.assert_array_equal(col["f_rest_8"], rest[:, 2, 2])
  np.testing.assert_array_equal(col["nx"], 0)
  np.testing.assert_array_equal(col["opacity"], params.opacity_logits)
  np.testing.assert_array_equal(col["rot_0"], params.quats[:, 0])   # w
  np.testing.assert_array_equal(col["scale_2"], params.log_scales[:, 2])


def test_capacity_padding(tmp_path):
  params = _random_params(3, 8)
  path = str(tmp_path / "g.ply")
  ply.write_ply(path, params, jnp.ones(3, bool))
  back, alive = ply.read_ply(path, capacity=5)
  assert back.capacity == 5 and back.sh_degree == 2
  np.testing.assert_array_equal(alive, [True] * 3 + [False] * 2)
  np.testing.assert_array_equal(back.means[:3], params.means)
  np.testing.assert_array_equal(back.means[3:], 0)
  np.testing.assert_array_equal(back.quats[3:], [[1, 0, 0, 0]] * 2)
  with pytest.raises(ValueError, match="capacity"):
    ply.read_ply(path, capacity=2)


def test_reads_other_property_orders_and_extras(tmp_path):
  names = (["rot_3", "rot_2", "rot_1", "rot_0", "x", "y", "z", "opacity",
            "f_dc_2", "f_dc_1", "f_dc_0", "scale_0", "scale_1", "scale_2",
            "extra"])
  values = np.arange(2 * len(names), dtype="<f4").reshape(2, len(names))
  header = ("ply\nformat binary_little_endian 1.0\ncomment made by hand\n"
            "element vertex 2\n" +
            "".join(f"property float {n}\n" for n in names[:-1]) +
            "property double extra\nend_header\n")
  records = np.empty(2, [(n, "<f4") for n in names[:-1]] + [("extra", "<f8")])
  for i, n in enumerate(names):
    records[n] = values[:, i]
  path = tmp_path / "h.ply"
  path.write_bytes(header.encode() + records.tobytes())
  params, alive = ply.read_ply(str(path))
  np.testing.assert_array_equal(params.quats[1], values[1, [3, 2, 1, 0]])
  np.testing.assert_array_equal(params.means[0], values[0, 4:7])
  np.testing.assert_array_equal(params.sh_dc[0], values[0, [10, 9, 8]])
  assert params.sh_rest.shape == (2, 0, 3) and bool(alive.all())


def test_bad_files(tmp_path):
  with pytest.raises(FileNotFoundError, match="nope.ply"):
    ply.read_ply(str(tmp_path / "nope.ply"))
  bad = tmp_path / "bad.ply"
  bad.write_bytes(b"not a ply\n")
  with pytest.raises(ValueError, match="bad.ply"):
    ply.read_ply(str(bad))
  bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
  with pytest.raises(ValueError, match="binary_little_endian"):
    ply.read_ply(str(bad))
  good = str(tmp_path / "g.ply")
  ply.write_ply(good, _random_params(3, 3), jnp.ones(3, bool))
  with open(good, "rb") as f:
    data = f.read()
  bad.write_bytes(data[:-5])
  with pytest.raises(ValueError, match="truncated"):
    ply.read_ply(str(bad))
  bad.write_bytes(data.replace(b"property float f_rest_8\n", b""))
  with pytest.raises(ValueError, match="f_rest"):
    ply.read_ply(str(bad))
  bad.write_bytes(data.replace(b"property float opacity\n", b""))
  with pytest.raises(ValueError, match="opacity"):
    ply.read_ply(str(bad))


def test_write_validates(tmp_path):
  params = _random_params(3, 3)
  with pytest.raises(ValueError, match="alive"):
    ply.write_ply(str(tmp_path / "g.ply"), params, jnp.ones(4, bool))


@pytest.mark.parametrize("fmt", sorted(ply.FORMATS))
@pytest.mark.parametrize("k", [0, 8])
def test_round_trip_in_every_format(tmp_path, fmt, k):
  params = _random_params(6, k, seed=1)
  path = str(tmp_path / "g.ply")
  ply.write_ply(path, params, jnp.ones(6, bool), fmt=fmt)
  lines, _ = _header(path)
  assert lines[1] == f"format {fmt} 1.0"
  back, alive = ply.read_ply(path)
  assert bool(alive.all()) and back.sh_degree == (2 if k else 0)
  for field in ("means", "log_scales", "quats", "opacity_logits", "sh_dc",
                "sh_rest"):
    np.testing.assert_array_equal(np.asarray(getattr(back, field)),
                                  np.asarray(getattr(params, field)))


def test_reads_a_plyfile_file_in_another_property_order(tmp_path):
  params = _random_params(5, 3, seed=2)
  path = str(tmp_path / "g.ply")
  ply.write_ply(path, params, jnp.ones(5, bool))
  records = plyfile.PlyData.read(path)["vertex"].data
  rng = np.random.default_rng(3)
  order = list(rng.permutation(records.dtype.names))
  shuffled = np.empty(len(records), [(n, ">f8") for n in order])
  for n in order:
    shuffled[n] = records[n]
  other = str(tmp_path / "other.ply")
  plyfile.PlyData([plyfile.PlyElement.describe(shuffled, "vertex")],
                  byte_order=">").write(other)
  assert _header(other)[0][1] == "format binary_big_endian 1.0"
  back, _ = ply.read_ply(other)
  for field in ("means", "quats", "sh_rest"):
    np.testing.assert_array_equal(np.asarray(getattr(back, field)),
                                  np.asarray(getattr(params, field)))
