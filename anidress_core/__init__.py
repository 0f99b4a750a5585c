"""AniDress pipeline core: the math of every stage, importable without Snakemake.

Conventions (shared by every module):

* Dimension letters: T frames, V vertices, F faces, J body joints (24, SMPL tree),
  B garment bones, C cameras, H, W image size, N samples / rays / points.
* Units: metres, radians, seconds. World frame of the synthetic scenes: z up,
  ground plane z = 0. Body canonical frame (SMPL): y up, facing +z, T-pose; the
  EasyMocap global rotation ``Rh`` and translation ``Th`` map it to the world.
* Cameras follow OpenCV: x right, y down, z forward; ``X_cam = R X_world + T``;
  pixel centres at integer pixel coordinates; images are (H, W, 3) float in [0, 1].
* Optical flow is (H, W, 2) in pixels, (dx, dy), forward from frame t-1 to t.
* Masks: 0 background, 1 body, 2 garment.
"""

__version__ = "0.1.0"
