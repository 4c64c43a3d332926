#!/usr/bin/env python3
"""PyTorch mirror of osrt's `clevr-lite-cpu` model and train step, for side-by-side timing
with `osrt bench model` (same architecture and parameter count, same batch shape, same
thread counts). Run by hand; CI does not install PyTorch.

    python3 bench/torch_step.py [--steps 10] [--threads 1,2] [--out target/bench/torch.json]

Mirrors crates/model (ray_encoding, encoder, nn, slot_attention, decoder/slot_mixer) and
crates/trainer/src/bench.rs: the median of `--steps` full optimiser steps (forward, MSE,
backward, AdamW step) after one warm-up, batch building excluded; and render speed
(decoding one whole 32×32 view from 7 slots, no gradients). Each thread count runs in a
fresh child process (thread pools are sized once per process), like the Rust benchmark.
"""

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time

# The clevr-lite-cpu preset (osrt config --preset clevr-lite-cpu).
CFG = dict(
    origin_octaves=8, origin_start=-3, direction_octaves=8, direction_start=0,
    conv_channels=[32, 64], dim=128, enc_layers=2, enc_heads=4, enc_head_dim=32, enc_mlp=256,
    num_slots=7, slot_dim=128, slot_mlp=256, iterations=3, eps=1e-8,
    query_hidden=192, alloc_layers=1, alloc_heads=4, alloc_head_dim=32, alloc_mlp=192,
    render_hidden=[128, 128],
    batch_size=16, rays_per_scene=512, input_views=1, image_size=32, lr=3e-4,
)


def build(torch):
    nn = torch.nn
    F = torch.nn.functional

    class RayEncoding(nn.Module):
        def __init__(self, c):
            super().__init__()
            def freqs(octaves, start):
                return torch.tensor([2.0 ** (start + o) * math.pi for o in range(octaves) for _ in range(3)])
            self.register_buffer("of", freqs(c["origin_octaves"], c["origin_start"]))
            self.register_buffer("df", freqs(c["direction_octaves"], c["direction_start"]))
            self.no, self.nd = c["origin_octaves"], c["direction_octaves"]
            self.dim = 6 * (self.no + self.nd)

        def forward(self, o, d):
            a = torch.cat([o.repeat(*([1] * (o.dim() - 1)), self.no) * self.of,
                           d.repeat(*([1] * (d.dim() - 1)), self.nd) * self.df], -1)
            return torch.cat([a.sin(), a.cos()], -1)

    class Attention(nn.Module):
        def __init__(self, q_dim, kv_dim, heads, head_dim):
            super().__init__()
            inner = heads * head_dim
            self.q = nn.Linear(q_dim, inner, bias=False)
            self.k = nn.Linear(kv_dim, inner, bias=False)
            self.v = nn.Linear(kv_dim, inner, bias=False)
            self.out = nn.Linear(inner, q_dim)
            self.h, self.dh = heads, head_dim

        def forward(self, x, ctx):
            b, n, _ = x.shape
            m = ctx.shape[1]
            q = self.q(x).view(b, n, self.h, self.dh).transpose(1, 2)
            k = self.k(ctx).view(b, m, self.h, self.dh).transpose(1, 2)
            v = self.v(ctx).view(b, m, self.h, self.dh).transpose(1, 2)
            attn = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(self.dh), -1)
            return self.out((attn @ v).transpose(1, 2).reshape(b, n, self.h * self.dh))

    class Block(nn.Module):
        def __init__(self, dim, ctx_dim, heads, head_dim, mlp):
            super().__init__()
            self.norm_attn = nn.LayerNorm(dim)
            self.attn = Attention(dim, ctx_dim, heads, head_dim)
            self.norm_mlp = nn.LayerNorm(dim)
            self.mlp = nn.Sequential(nn.Linear(dim, mlp), nn.GELU(), nn.Linear(mlp, dim))

        def forward(self, x, ctx=None):
            h = self.norm_attn(x)
            x = x + self.attn(h, h if ctx is None else ctx)
            return x + self.mlp(self.norm_mlp(x))

    class Transformer(nn.Module):
        def __init__(self, dim, ctx_dim, layers, heads, head_dim, mlp):
            super().__init__()
            self.blocks = nn.ModuleList(Block(dim, ctx_dim, heads, head_dim, mlp) for _ in range(layers))

        def forward(self, x, ctx=None):
            for b in self.blocks:
                x = b(x, ctx)
            return x

    class Encoder(nn.Module):
        def __init__(self, c, ray_dim):
            super().__init__()
            convs, c_in = [], 3 + ray_dim
            for ch in c["conv_channels"]:
                convs += [nn.Conv2d(c_in, ch, 3, padding=1, bias=False), nn.ReLU(),
                          nn.Conv2d(ch, 2 * ch, 3, stride=2, padding=1, bias=False), nn.ReLU()]
                c_in = 2 * ch
            self.convs = nn.Sequential(*convs)
            self.project = nn.Conv2d(c_in, c["dim"], 1, bias=False)
            self.transformer = Transformer(c["dim"], c["dim"], c["enc_layers"], c["enc_heads"],
                                           c["enc_head_dim"], c["enc_mlp"])

        def forward(self, rays, images, origins, directions):
            b, v, h, w, _ = images.shape
            x = torch.cat([images, rays(origins, directions)], -1).reshape(b * v, h, w, -1)
            x = self.project(self.convs(x.permute(0, 3, 1, 2)))
            d = x.shape[1]
            tokens = x.reshape(b, v, d, -1).permute(0, 1, 3, 2).reshape(b, -1, d)
            return self.transformer(tokens)

    class Gru(nn.Module):
        def __init__(self, d):
            super().__init__()
            self.input = nn.Linear(d, 3 * d)
            self.hidden = nn.Linear(d, 3 * d)

        def forward(self, x, h):
            gi, gh = self.input(x).chunk(3, -1), self.hidden(h).chunk(3, -1)
            r = torch.sigmoid(gi[0] + gh[0])
            z = torch.sigmoid(gi[1] + gh[1])
            n = torch.tanh(gi[2] + r * gh[2])
            return n + z * (h - n)

    class SlotAttention(nn.Module):
        def __init__(self, c, in_dim):
            super().__init__()
            ds = c["slot_dim"]
            self.c = c
            self.norm_inputs, self.norm_slots, self.norm_mlp = nn.LayerNorm(in_dim), nn.LayerNorm(ds), nn.LayerNorm(ds)
            self.to_q = nn.Linear(ds, ds, bias=False)
            self.to_k = nn.Linear(in_dim, ds, bias=False)
            self.to_v = nn.Linear(in_dim, ds, bias=False)
            self.gru = Gru(ds)
            self.mlp = nn.Sequential(nn.Linear(ds, c["slot_mlp"]), nn.ReLU(), nn.Linear(c["slot_mlp"], ds))
            self.init_slots = nn.Parameter(torch.randn(c["num_slots"], ds))

        def forward(self, inputs):
            x = self.norm_inputs(inputs)
            k, v = self.to_k(x), self.to_v(x)
            slots = self.init_slots.unsqueeze(0).expand(x.shape[0], -1, -1)
            for _ in range(self.c["iterations"]):
                prev = slots
                q = self.to_q(self.norm_slots(slots))
                attn = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(self.c["slot_dim"]), 1)
                w = attn + self.c["eps"]
                w = w / w.sum(-1, keepdim=True)
                slots = self.gru(w @ v, prev)
                slots = slots + self.mlp(self.norm_mlp(slots))
            return slots

    class Mlp(nn.Module):
        def __init__(self, dims, act):
            super().__init__()
            layers = []
            for i, (a, b) in enumerate(zip(dims, dims[1:])):
                layers.append(nn.Linear(a, b))
                if i + 2 < len(dims):
                    layers.append(act())
            self.net = nn.Sequential(*layers)

        def forward(self, x):
            return self.net(x)

    class SlotMixer(nn.Module):
        def __init__(self, c, ray_dim):
            super().__init__()
            ds = c["slot_dim"]
            self.query_mlp = Mlp([ray_dim, c["query_hidden"], ray_dim], nn.ReLU)
            self.allocation = Transformer(ray_dim, ds, c["alloc_layers"], c["alloc_heads"],
                                          c["alloc_head_dim"], c["alloc_mlp"])
            self.mix_q = nn.Linear(ray_dim, ds, bias=False)
            self.mix_k = nn.Linear(ds, ds, bias=False)
            self.render = Mlp([ds + ray_dim, *c["render_hidden"], 3], lambda: nn.LeakyReLU(0.01))
            self.ds = ds

        def forward(self, slots, rays):
            query = self.query_mlp(rays)
            allocated = self.allocation(query, slots)
            w = torch.softmax(self.mix_q(allocated) @ self.mix_k(slots).transpose(-1, -2) / math.sqrt(self.ds), -1)
            return torch.sigmoid(self.render(torch.cat([w @ slots, query], -1))), w

    class Osrt(nn.Module):
        def __init__(self, c):
            super().__init__()
            self.rays = RayEncoding(c)
            self.encoder = Encoder(c, self.rays.dim)
            self.slot_attention = SlotAttention(c, c["dim"])
            self.decoder = SlotMixer(c, self.rays.dim)

        def encode(self, images, origins, directions):
            return self.slot_attention(self.encoder(self.rays, images, origins, directions))

        def decode(self, slots, origins, directions):
            return self.decoder(slots, self.rays(origins, directions))

    return Osrt(CFG)


def unit(torch, *shape):
    d = torch.randn(*shape)
    return d / d.norm(dim=-1, keepdim=True)


def child(threads, steps):
    import torch
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    c = CFG
    model = build(torch)
    params = sum(p.numel() for p in model.parameters())
    opt = torch.optim.AdamW(model.parameters(), lr=c["lr"], weight_decay=0.0)
    b, s, r = c["batch_size"], c["image_size"], c["rays_per_scene"]
    images = torch.rand(b, c["input_views"], s, s, 3)
    origins = 10.0 * unit(torch, b, c["input_views"], 1, 1, 3).expand(-1, -1, s, s, -1).contiguous()
    directions = unit(torch, b, c["input_views"], s, s, 3)
    t_orig = origins[:, 0].reshape(b, -1, 3)[:, :r].contiguous()
    t_dir = unit(torch, b, r, 3)
    target = torch.rand(b, r, 3)
    step_s, fb_s = [], []
    for i in range(steps + 1):
        t0 = time.perf_counter()
        rgb, _ = model.decode(model.encode(images, origins, directions), t_orig, t_dir)
        loss = ((rgb - target) ** 2).mean()
        loss.backward()
        t1 = time.perf_counter()
        opt.step()
        opt.zero_grad(set_to_none=True)
        if i > 0:
            step_s.append(time.perf_counter() - t0)
            fb_s.append(t1 - t0)
    # Render: one whole view (s·s rays) from 7 slots, no gradients.
    with torch.no_grad():
        slots = model.encode(images[:1], origins[:1], directions[:1])
        ro = origins[:1, 0].reshape(1, -1, 3)
        rd = directions[:1, 0].reshape(1, -1, 3)
        render_s = []
        for i in range(6):
            t0 = time.perf_counter()
            model.decode(slots, ro, rd)
            if i > 0:
                render_s.append(time.perf_counter() - t0)
    m = statistics.median(step_s)
    return dict(
        preset="clevr-lite-cpu", framework=f"torch {torch.__version__}", threads=threads,
        parameters=params, batch_size=b, rays_per_scene=r, image_size=s,
        median_step_s=m, median_forward_backward_s=statistics.median(fb_s),
        scenes_per_s=b / m, render_fps=1.0 / statistics.median(render_s),
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--out", default="target/bench/torch.json")
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        print(json.dumps(child(a.child, a.steps)))
        return
    results = {}
    for t in [int(x) for x in a.threads.split(",")]:
        env = dict(os.environ, OMP_NUM_THREADS=str(t), MKL_NUM_THREADS=str(t))
        out = subprocess.run([sys.executable, __file__, "--child", str(t), "--steps", str(a.steps)],
                             env=env, capture_output=True, text=True, check=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        results[str(t)] = r
        print(f"{t} thread(s): train step {r['median_step_s'] * 1e3:8.1f} ms median "
              f"({r['scenes_per_s']:.1f} scenes/s; fwd+bwd {r['median_forward_backward_s'] * 1e3:.1f} ms; "
              f"{r['parameters']} params, batch {r['batch_size']}, {r['rays_per_scene']} rays, "
              f"{r['image_size']}px); render {r['render_fps']:.1f} fps  [{r['framework']}]")
    os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
    with open(a.out, "w") as f:
        json.dump(results, f, indent=2)
    print(f"saved to {a.out}")


if __name__ == "__main__":
    main()
