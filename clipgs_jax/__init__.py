"""clipgs_jax: 3D Gaussian Splatting in JAX with CLIP-guided transient removal."""
