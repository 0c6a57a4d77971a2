"""Host-side data: COLMAP models, images, scenes and the default scene."""
