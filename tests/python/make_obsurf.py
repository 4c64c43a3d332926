"""Writes a small dataset in ObSuRF's release format (CLEVR-3D / MSN-Easy), independently
of osrt, for the importer's tests (tests/import.rs).

    python3 make_obsurf.py OUT [SCENES [WIDTH HEIGHT [SMALL_WIDTH SMALL_HEIGHT]]]

OUT/metadata.npz (np.savez_compressed): camera_pos [S, 3, 3], shape [S, 8] (codes > 0
where an object is, packed first), 3d_coords [S, 8, 3], color [S, 8] (int codes),
material [S, 8] (text), size [S, 8] (float), rotation [S, 8].
OUT/images/img_{s}_{v}.png: 32x24 RGB noise (RGBA for view 1 of scene 0).
OUT/masks/masks_{s}_{v}.png: 8-bit ids 0..n (scene 3 uses the mask_{s}_{v}.png spelling).
Scene 5 has 7 objects (left out by CLEVR-3D's default 6-object filter).
OUT/expected_rays.npy [S, 3, 24, 32, 3]: each pixel's unit ray direction, computed here
from the release's camera model (looking at the origin, z up, focal 0.035, sensor width
0.032, rays through pixel centres, row 0 at the top).
With SMALL_WIDTH SMALL_HEIGHT, what an import shrunk to that size must hold:
OUT/expected_small/img_{s}_{v}.png, each RGB image shrunk by Pillow's area-averaging
BOX filter, and OUT/expected_small/rays.npy [S, 3, SH, SW, 3], the camera model's rays
at that size.
"""

import os
import sys

import numpy as np
from PIL import Image

W, H, V, K = 32, 24, 3, 8
FOCAL, SENSOR_W = 0.035, 0.032


def rays_of(pos):
    """Unit ray directions [H, W, 3] of a camera at `pos` aimed at the origin."""
    return rays_at(pos, W, H)


def rays_at(pos, W, H):
    """`rays_of` for a W × H image."""
    forward = -pos / np.linalg.norm(pos)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pitch = SENSOR_W / W
    xs = (np.arange(W) + 0.5 - W / 2) * pitch
    ys = (np.arange(H) + 0.5 - H / 2) * pitch
    d = (FOCAL * forward[None, None, :]
         + xs[None, :, None] * right[None, None, :]
         + ys[:, None, None] * down[None, None, :])
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def main():
    global W, H
    out = sys.argv[1]
    scenes = int(sys.argv[2]) if len(sys.argv) > 2 else 12
    if len(sys.argv) > 4:
        W, H = int(sys.argv[3]), int(sys.argv[4])
    small = (int(sys.argv[5]), int(sys.argv[6])) if len(sys.argv) > 6 else None
    if small:
        os.makedirs(os.path.join(out, "expected_small"), exist_ok=True)
        small_rays = np.zeros((scenes, V, small[1], small[0], 3), dtype=np.float32)
    rng = np.random.default_rng(3)
    os.makedirs(os.path.join(out, "images"), exist_ok=True)
    os.makedirs(os.path.join(out, "masks"), exist_ok=True)
    camera_pos = np.zeros((scenes, V, 3))
    shape = np.zeros((scenes, K), dtype=np.int64)
    coords = np.zeros((scenes, K, 3))
    color = np.zeros((scenes, K), dtype=np.int32)
    material = np.full((scenes, K), "", dtype="<U6")
    size = np.zeros((scenes, K))
    rotation = np.zeros((scenes, K))
    rays = np.zeros((scenes, V, H, W, 3), dtype=np.float32)
    for s in range(scenes):
        n = 7 if s == 5 else 1 + s % 5
        shape[s, :n] = rng.integers(1, 4, n)
        coords[s, :n] = rng.uniform(-3, 3, (n, 3))
        color[s, :n] = rng.integers(1, 9, n)
        material[s, :n] = rng.choice(["rubber", "metal"], n)
        size[s, :n] = rng.choice([0.35, 0.7], n)
        rotation[s, :n] = rng.uniform(0, 360, n)
        for v in range(V):
            azimuth = rng.uniform(0, 2 * np.pi)
            pos = np.array([10 * np.cos(azimuth), 10 * np.sin(azimuth), rng.uniform(3, 8)])
            camera_pos[s, v] = pos
            rays[s, v] = rays_of(pos)
            pixels = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
            if small:
                shrunk = Image.fromarray(pixels, "RGB").resize(small, Image.BOX)
                shrunk.save(os.path.join(out, f"expected_small/img_{s}_{v}.png"))
                small_rays[s, v] = rays_at(pos, *small)
            if s == 0 and v == 1:
                rgba = np.concatenate([pixels, np.full((H, W, 1), 200, np.uint8)], -1)
                Image.fromarray(rgba, "RGBA").save(os.path.join(out, f"images/img_{s}_{v}.png"))
            else:
                Image.fromarray(pixels, "RGB").save(os.path.join(out, f"images/img_{s}_{v}.png"))
            mask = rng.integers(0, n + 1, (H, W), dtype=np.uint8)
            name = f"mask_{s}_{v}.png" if s == 3 else f"masks_{s}_{v}.png"
            Image.fromarray(mask, "L").save(os.path.join(out, "masks", name))
    np.savez_compressed(os.path.join(out, "metadata.npz"), camera_pos=camera_pos, shape=shape,
                        **{"3d_coords": coords}, color=color, material=material, size=size,
                        rotation=rotation)
    np.save(os.path.join(out, "expected_rays.npy"), rays)
    if small:
        np.save(os.path.join(out, "expected_small/rays.npy"), small_rays)


if __name__ == "__main__":
    main()
