"""Pose-driven deformable radiance field (AniDress §3.3; DESIGN.md §9).

- :mod:`.encoding`: multiresolution hash encoding (instant-ngp) in torch
- :mod:`.mlp`: canonical field F_c (colour, density)
- :mod:`.weights`: motion-weight volume (3D CNN from a fixed latent + body / garment priors)
- :mod:`.deform`: backward warp over the unified pose, exact inverse LBS
- :mod:`.sampler`: mask-box rays, occupancy grid from posed meshes, joint candidates, marching
- :mod:`.render`: volume rendering of packed samples (alpha, depth kept)
- :mod:`.subject`: unified pose, priors and posed surfaces of the `full` / `body_only` variants
- :mod:`.model`, :mod:`.train`: the field, its training loop (checkpoints) and image rendering
"""
