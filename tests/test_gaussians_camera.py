"""Quaternions, activation, camera construction and conventions."""

from absl.testing import parameterized
import chex
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import camera
from clipgs_jax import gaussians
from clipgs_jax import tree_util


class QuatTest(parameterized.TestCase):

  def test_known_rotation(self):
    # 90 degrees about z: x -> y.
    q = jnp.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])
    r = gaussians.quat_to_rotmat(q)
    np.testing.assert_allclose(r @ jnp.array([1.0, 0, 0]), [0, 1, 0],
                               atol=1e-6)

  def test_unnormalized_and_zero(self):
    q = jnp.array([[2.0, 0, 0, 0], [0.0, 0, 0, 0], [1.0, 2.0, 3.0, 4.0]])
    r = gaussians.quat_to_rotmat(q)
    np.testing.assert_allclose(r[0], np.eye(3), atol=1e-6)
    np.testing.assert_allclose(r[1], np.eye(3), atol=1e-6)
    np.testing.assert_allclose(r[2] @ r[2].T, np.eye(3), atol=1e-5)
    self.assertAlmostEqual(float(jnp.linalg.det(r[2])), 1.0, places=5)

  def test_finite_output_and_gradient(self):
    q = jnp.array([[0.0, 0, 0, 0], [1e-30, 0, 0, 0], [1e30, 1e30, 0, 0]])
    f = lambda q: jnp.sum(gaussians.quat_to_rotmat(q) ** 2 * jnp.arange(9.)
                          .reshape(3, 3))
    chex.assert_tree_all_finite(gaussians.quat_to_rotmat(q))
    chex.assert_tree_all_finite(jax.grad(f)(q))

  def test_check_grads(self):
    with jax.enable_x64(True):
      q = jnp.array([[0.3, -0.2, 0.9, 0.1], [1.0, 0.5, 0.2, -0.7]])
      jax.test_util.check_grads(gaussians.quat_to_rotmat, (q,), order=1)


class ActivateTest(parameterized.TestCase):

  def test_activate(self):
    params, alive = gaussians.empty(4, 2)
    params = params.replace(log_scales=jnp.log(jnp.full((4, 3), 2.0)),
                            opacity_logits=jnp.array([0.0, 60.0, -60.0, 1.0]))
    act = gaussians.activate(params)
    np.testing.assert_allclose(act.scales, 2.0, rtol=1e-6)
    np.testing.assert_allclose(act.opacities[:3], [0.5, 1.0, 0.0], atol=1e-7)
    chex.assert_shape(act.rotations, (4, 3, 3))
    self.assertEqual(params.sh_degree, 2)
    self.assertFalse(bool(jnp.any(alive)))


class CameraTest(parameterized.TestCase):

  def test_look_at_projects_target_to_principal_point(self):
    cam = camera.look_at([1.0, 2.0, -3.0], [0.5, 0.0, 1.0], [0, -1.0, 0],
                         50.0, 50.0, 64, 48)
    p = cam.rotation @ np.array([0.5, 0.0, 1.0]) + cam.translation
    self.assertGreater(p[2], 0)
    np.testing.assert_allclose(p[:2], 0.0, atol=1e-5)
    np.testing.assert_allclose(camera.camera_center(cam), [1.0, 2.0, -3.0],
                               atol=1e-5)

  def test_world_up_is_image_up(self):
    cam = camera.look_at([0, 0, -5.0], [0, 0, 0], [0, 1.0, 0], 50, 50, 64, 48)
    up_point = cam.rotation @ np.array([0, 1.0, 0]) + cam.translation
    v = cam.fy * up_point[1] / up_point[2] + cam.cy
    self.assertLess(v, cam.cy)   # +y is down in the image

  def test_rejects_parallel_up(self):
    with self.assertRaisesRegex(ValueError, "parallel"):
      camera.look_at([0, 0, -5.0], [0, 0, 0], [0, 0, 1.0], 5, 5, 8, 8)


class TreeUtilTest(parameterized.TestCase):

  def test_select_and_set(self):
    tree = {"a": jnp.arange(4.0), "b": jnp.arange(8.0).reshape(4, 2)}
    other = jax.tree.map(jnp.zeros_like, tree)
    sel = tree_util.tree_select(jnp.array([True, False, True, False]), tree,
                                other)
    np.testing.assert_array_equal(sel["b"], [[0, 1], [0, 0], [4, 5], [0, 0]])
    taken = jax.tree.map(lambda x: x[jnp.array([3, 0])], tree)
    np.testing.assert_array_equal(taken["a"], [3.0, 0.0])
    # Index 4 is out of range (the nonzero fill value): nothing is written.
    put = tree_util.tree_index_set(tree, jnp.array([1, 4]), taken)
    np.testing.assert_array_equal(put["a"], [0.0, 3.0, 2.0, 3.0])
    np.testing.assert_array_equal(put["b"][1], [6.0, 7.0])
