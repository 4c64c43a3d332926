"""Writes the by-hand check of `osrt import-checkpoint` against stelzner/osrt's own code.

Builds the peer's CLEVR-3D model with its own classes from its own config
(`runs/clevr3d/osrt/config.yaml`), takes 3 `torch.optim.Adam` steps at lr 1e-5 on a random
batch, saves the checkpoint with its own `Checkpoint.save`, and writes the same files as
tests/fixtures/stelzner/write.py (model.pt, config.yaml, inputs.npz, expected.npz,
after_step.npz), which the ignored tests of tests/stelzner.rs read:

    git clone https://github.com/stelzner/osrt PEER      # no code of it enters this repo
    python3 bench/stelzner_fixture.py PEER OUT            # torch, numpy, pyyaml, einops
    OSRT_PEER_FIXTURE=OUT cargo test --release --test stelzner -- --ignored --nocapture

The batch: one scene, 2 input views of 32 × 32 (any size divisible by 8 suits the
peer's CNN) and 64 target rays; the model is the paper's size (83,110,767 parameters).
"""

import math
import os
import shutil
import sys

import numpy as np
import torch
import yaml

# Adam's rate for every step: the peer's schedule reaches 1e-5 in its first 500 iterations
# (larger rates wreck a fresh 83 M model in 3 steps: saturated colours, huge logits).
LR = 1e-5


def main(peer, out):
    sys.path.insert(0, peer)
    from osrt.checkpoint import Checkpoint
    from osrt.model import OSRT

    os.makedirs(out, exist_ok=True)
    config = os.path.join(peer, "runs", "clevr3d", "osrt", "config.yaml")
    with open(config) as f:
        cfg = yaml.safe_load(f)
    shutil.copy(config, os.path.join(out, "config.yaml"))
    torch.manual_seed(0)
    model = OSRT(cfg["model"])
    print("parameters:", sum(p.numel() for p in model.parameters()))
    gen = torch.Generator().manual_seed(1)
    b, v, h, w, r = 1, 2, 32, 32, 64
    unit = lambda x: x / x.norm(dim=-1, keepdim=True)
    d = {
        "images": torch.rand(b, v, 3, h, w, generator=gen),
        "camera_pos": (torch.rand(b, v, 3, generator=gen) - 0.5) * 16,
        "rays": unit(torch.randn(b, v, h, w, 3, generator=gen)),
        "target_pos": (torch.rand(b, r, 3, generator=gen) - 0.5) * 16,
        "target_rays": unit(torch.randn(b, r, 3, generator=gen)),
        "target_rgb": torch.rand(b, r, 3, generator=gen),
    }

    def run():
        z = model.encoder(d["images"], d["camera_pos"], d["rays"])
        rgb, extras = model.decoder(z, d["target_pos"], d["target_rays"])
        loss = ((rgb - d["target_rgb"]) ** 2).mean((1, 2)).mean(0)
        return loss, rgb, extras["segmentation"], z

    opt = torch.optim.Adam(model.parameters(), lr=LR)
    for _ in range(3):
        opt.zero_grad()
        run()[0].backward()
        opt.step()
    ckpt = Checkpoint(out, encoder=model.encoder, decoder=model.decoder, optimizer=opt)
    ckpt.save("model.pt", epoch_it=0, it=3, t=1.0, loss_val_best=-math.inf, run_id=None)
    with torch.no_grad():
        _, rgb, seg, slots = run()
    f32 = lambda t: t.detach().numpy().astype(np.float32)
    np.savez(os.path.join(out, "inputs.npz"),
             input_images=f32(d["images"].permute(0, 1, 3, 4, 2)),
             input_origins=f32(d["camera_pos"][:, :, None, None].expand(-1, -1, h, w, -1)),
             input_directions=f32(d["rays"]),
             target_origins=f32(d["target_pos"]),
             target_directions=f32(d["target_rays"]),
             target_rgb=f32(d["target_rgb"]), lr=np.array([LR], np.float32))
    np.savez(os.path.join(out, "expected.npz"), rgb=f32(rgb), slot_weights=f32(seg),
             slots=f32(slots))
    opt.zero_grad()
    run()[0].backward()
    opt.step()
    np.savez(os.path.join(out, "after_step.npz"),
             **{k: f32(p) for k, p in model.named_parameters()})


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
