"""FLAME-structured head model in PyTorch (seed 002, section 2.2).

M(beta, theta, psi) = W(T_P(beta, theta, psi), J(beta), theta, weights), with
T_P = T_bar + B_S(beta) + B_P(theta) + B_E(psi) and J = J_regressor (T_bar + B_S(beta)).
The same code drives the real FLAME 2020 model and the procedural default: both are a `HeadModelData`.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from torch import nn

from avatarlab.headmodel.joints import COEFFICIENT_RANGE, POSE_DIM, POSE_JOINTS  # noqa: F401 (re-exported)
from avatarlab.headmodel.sources import HeadModelData


def rodrigues(axis_angle: torch.Tensor) -> torch.Tensor:
    """axis_angle: (..., 3) -> rotation matrices (..., 3, 3)."""
    shape = axis_angle.shape[:-1]
    return axis_angle_to_rotation_matrix(axis_angle.reshape(-1, 3)).reshape(*shape, 3, 3)


def blend_shapes(coefficients: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """coefficients: (B, K), directions: (V, 3, K) -> offsets (B, V, 3). One matrix product over the (V*3, K) view
    of the directions (no copy of the large basis)."""
    v, c, k = directions.shape
    flat = directions.reshape(v * c, k)[:, : coefficients.shape[1]]
    return torch.nn.functional.linear(coefficients, flat).reshape(-1, v, c)


def rigid_transforms(rotations: torch.Tensor, joints: torch.Tensor, parents: list[int] | torch.Tensor):
    """Forward kinematics.

    rotations: (B, J, 3, 3) local rotations, joints: (B, J, 3) rest joint locations, parents: (J,) with -1 for the root
    (a list: walking the chain then reads no device memory).
    Returns posed joints (B, J, 3) and the relative transforms (B, J, 4, 4) that map rest-pose points to posed ones.
    """
    batch, n_joints = joints.shape[:2]
    parents = parents.tolist() if isinstance(parents, torch.Tensor) else list(parents)
    rel_joints = joints.clone()
    rel_joints[:, 1:] = joints[:, 1:] - joints[:, parents[1:]]
    local = torch.zeros(batch, n_joints, 4, 4, dtype=joints.dtype, device=joints.device)
    local[..., :3, :3] = rotations
    local[..., :3, 3] = rel_joints
    local[..., 3, 3] = 1.0
    chain = [local[:, 0]]
    for j in range(1, n_joints):
        chain.append(chain[parents[j]] @ local[:, j])
    world = torch.stack(chain, dim=1)
    posed_joints = world[..., :3, 3]
    # Remove the rest-pose joint location so the transform applies to rest-pose vertices.
    correction = torch.einsum("bjik,bjk->bji", world[..., :3, :3], joints)
    relative = world.clone()
    relative[..., :3, 3] = world[..., :3, 3] - correction
    return posed_joints, relative


def linear_blend_skinning(
    shape: torch.Tensor,
    expression: torch.Tensor,
    pose: torch.Tensor,
    data: "HeadModelBuffers",
):
    """LBS of FLAME. shape (B,S), expression (B,E), pose (B,15) -> vertices (B,V,3), joints (B,J,3)."""
    batch = pose.shape[0]
    v_shaped = data.v_template.unsqueeze(0) + blend_shapes(shape, data.shapedirs)
    joints = torch.einsum("jv,bvc->bjc", data.J_regressor, v_shaped)
    v_expr = v_shaped + blend_shapes(expression, data.exprdirs)
    rotations = rodrigues(pose.reshape(batch, -1, 3))
    eye = torch.eye(3, dtype=pose.dtype, device=pose.device)
    pose_feature = (rotations[:, 1:] - eye).reshape(batch, -1)
    v_posed = v_expr + blend_shapes(pose_feature, data.posedirs)
    posed_joints, transforms = rigid_transforms(rotations, joints, data.parent_list)
    n_joints = transforms.shape[1]  # per vertex: the skinning-weighted sum of the joints' 3x4 transforms
    per_vertex = (data.lbs_weights @ transforms[..., :3, :].permute(1, 0, 2, 3).reshape(n_joints, -1)).reshape(
        -1, batch, 3, 4).transpose(0, 1)  # (B, V, 3, 4)
    vertices = (per_vertex[..., :3] @ v_posed[..., None]).squeeze(-1) + per_vertex[..., 3]
    return vertices, posed_joints


def vertices_to_landmarks(vertices: torch.Tensor, faces: torch.Tensor, face_idx: torch.Tensor, bary: torch.Tensor):
    """Barycentric landmark embedding. vertices (B,V,3), face_idx (L,), bary (L,3) -> (B,L,3)."""
    corners = vertices[:, faces[face_idx]]  # (B, L, 3, 3)
    return torch.einsum("blkc,lk->blc", corners, bary)


@dataclass
class HeadOutput:
    vertices: torch.Tensor  # (B, V, 3) world coordinates, metres, y up, face towards +z
    landmarks3d: torch.Tensor  # (B, 68, 3)
    joints: torch.Tensor  # (B, 5, 3)


class HeadModelBuffers(nn.Module):
    """The model's fixed arrays as buffers, so `.to(device)` moves them."""

    def __init__(self, data: HeadModelData, dtype=torch.float32):
        super().__init__()
        as_t = lambda a: torch.as_tensor(a, dtype=dtype)  # noqa: E731
        self.register_buffer("v_template", as_t(data.v_template))
        self.register_buffer("faces", torch.as_tensor(data.faces, dtype=torch.long))
        self.register_buffer("shapedirs", as_t(data.shapedirs))
        self.register_buffer("exprdirs", as_t(data.exprdirs))
        self.register_buffer("posedirs", as_t(data.posedirs))
        self.register_buffer("J_regressor", as_t(data.J_regressor))
        self.register_buffer("parents", torch.as_tensor(data.parents, dtype=torch.long))
        self.parent_list = [int(p) for p in data.parents]
        self.register_buffer("lbs_weights", as_t(data.lbs_weights))
        self.register_buffer("lmk_faces_idx", torch.as_tensor(data.lmk_faces_idx, dtype=torch.long))
        self.register_buffer("lmk_bary", as_t(data.lmk_bary_coords))


class HeadModel(nn.Module):
    """FLAME-structured head: geometry from (shape, expression, pose), albedo from texture coefficients."""

    def __init__(self, data: HeadModelData, n_shape: int | None = None, n_expression: int | None = None,
                 n_texture: int | None = None):
        super().__init__()
        from avatarlab.headmodel.texture import AlbedoModel

        self.source = data.source
        self.buffers_ = HeadModelBuffers(data)
        self.n_shape = min(n_shape or data.shapedirs.shape[-1], data.shapedirs.shape[-1])
        self.n_expression = min(n_expression or data.exprdirs.shape[-1], data.exprdirs.shape[-1])
        self.albedo_model = AlbedoModel(data.albedo, n_texture)
        self.n_texture = self.albedo_model.n_components
        self.regions = {k: torch.as_tensor(v) for k, v in data.regions.items()}

    @property
    def faces(self) -> torch.Tensor:
        return self.buffers_.faces

    @property
    def num_vertices(self) -> int:
        return self.buffers_.v_template.shape[0]

    def zeros(self, batch: int = 1, device=None) -> dict[str, torch.Tensor]:
        """Neutral parameters for a batch (the initialisation of every fit)."""
        device = device or self.buffers_.v_template.device
        z = lambda n: torch.zeros(batch, n, device=device)  # noqa: E731
        return {"shape": z(self.n_shape), "expression": z(self.n_expression), "pose": z(POSE_DIM),
                "texture": z(self.n_texture)}

    def forward(self, shape: torch.Tensor, expression: torch.Tensor, pose: torch.Tensor) -> HeadOutput:
        b = self.buffers_
        vertices, joints = linear_blend_skinning(shape[:, : self.n_shape], expression[:, : self.n_expression],
                                                 pose, b)
        landmarks = vertices_to_landmarks(vertices, b.faces, b.lmk_faces_idx, b.lmk_bary)
        return HeadOutput(vertices=vertices, landmarks3d=landmarks, joints=joints)

    def albedo(self, texture: torch.Tensor):
        return self.albedo_model(texture)


def clip_coefficients(values: torch.Tensor) -> torch.Tensor:
    """Clip shape/expression/texture coefficients to the range where the model is meaningful."""
    return values.clamp(*COEFFICIENT_RANGE)
