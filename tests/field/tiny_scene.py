"""A tiny rendered scene for training tests: the small mannequin in two poses, 4 cameras."""
from __future__ import annotations

import torch

from anidress_core.camera import pixel_rays, ring_cameras
from anidress_core.field.model import AnimatableField, FieldConfig
from anidress_core.field.encoding import HashGridConfig
from anidress_core.field.sampler import SurfacePart, build_occupancy, mask_boxes
from anidress_core.field.subject import BodyRest, canonical_setup
from anidress_core.field.train import TrainData
from anidress_core.raster import render_mesh

from .conftest import bent_pose

SMALL = FieldConfig(grid=HashGridConfig(levels=4, features=2, log2_size=12, base_resolution=8, max_resolution=64),
                    width=32, volume_res=16, latent=32, decoder_width=16)


def tiny_scene(body, size: int = 40, cams: int = 4):
    """TrainData of 2 frames (rest + bent) x ``cams`` cameras at size x size, and the model."""
    poses = torch.cat([torch.zeros(1, 72), bent_pose()])
    Th = torch.tensor([[0.0, 0.0, 0.95], [0.0, 0.0, 0.95]])
    Rh = torch.tensor([[1.5708, 0.0, 0.0], [1.5708, 0.0, 0.0]])  # canonical y-up -> world z-up
    posed = body.pose(poses, Rh, Th)
    cam = ring_cameras(cams, 3.0, 1.0, (0.0, 0.0, 0.9), focal_px=size * 1.2, image_height=size, image_width=size)
    # colour: a smooth function of the canonical position (the texture the field must learn)
    v = body.v_template
    col = 0.5 + 0.45 * torch.stack([torch.sin(9 * v[:, 1]), torch.cos(7 * v[:, 0] + 3 * v[:, 1]),
                                    torch.sin(5 * v[:, 2] + 11 * v[:, 1])], -1)
    imgs, masks = [], []
    for t in range(2):
        r = render_mesh(posed.vertices[t], body.faces, cam.K, cam.world_to_cam, size, size, vertex_colors=col)
        imgs.append((r.rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8))
        masks.append(r.mask)
    imgs, masks = torch.stack(imgs), torch.stack(masks)  # (2, C, H, W, 3), (2, C, H, W)
    boxes = mask_boxes(masks.reshape(-1, size, size), 2).reshape(2, cams, 4)
    br = BodyRest(body.v_template, body.faces, body.weights, body.joints_rest)
    box, prior = canonical_setup(br, None, "full", res=SMALL.volume_res)
    grid = build_occupancy([SurfacePart(posed.vertices, body.faces, body.weights, 0.03)], (32, 32, 32), 8)
    rays = pixel_rays(cam)
    data = TrainData(imgs, masks, boxes, rays.origins[:, 0, 0], rays.directions, posed.transforms,
                     grid)
    return data, box, prior


def new_model(box, prior, seed: int = 0) -> AnimatableField:
    return AnimatableField(box, prior, SMALL, seed=seed)
