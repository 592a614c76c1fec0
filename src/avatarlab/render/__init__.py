"""Camera, rasterizer and mesh renderer (pure PyTorch, differentiable)."""
from avatarlab.render.camera import Camera, intrinsics, orbit_camera, scale_intrinsics  # noqa: F401
from avatarlab.render.mesh_renderer import MeshRenderer, RenderOutput, vertex_normals  # noqa: F401
from avatarlab.render.rasterizer import Fragments, rasterize  # noqa: F401
