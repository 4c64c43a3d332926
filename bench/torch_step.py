#!/usr/bin/env python3
"""PyTorch mirror of osrt's `clevr-lite-cpu` model and train step, for side-by-side timing
with `osrt bench model` (same architecture and parameter count, same batch shape, same
thread counts). Run by hand; CI does not install PyTorch.

    python3 bench/torch_step.py [--steps 10] [--threads 1,2] [--out target/bench/torch.json]
                                [--worker-allocator]

Mirrors crates/model (ray_encoding, encoder, nn, slot_attention, decoder/slot_mixer) with
`Config::cpu()` sizes, and crates/trainer/src/bench.rs: the median of `--steps` full
optimiser steps (forward, MSE on the target rays, backward, AdamW step, zero_grad) after
one warm-up, batch building excluded; and render speed (decoding one whole 32x32 view,
1024 rays, from 7 slots, no gradients; median of 5 after one warm-up). Each thread count
runs in a fresh child process (thread pools are sized once per process), as in Rust.
"""

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time

# The clevr-lite-cpu preset (`osrt config --preset clevr-lite-cpu`; model = Config::cpu()).
CFG = dict(
    origin_octaves=8, origin_start=-3, direction_octaves=8, direction_start=0,
    conv_channels=[32, 64], dim=128, enc_layers=2, enc_heads=4, enc_head_dim=32, enc_mlp=256,
    ray_input="add",
    num_slots=7, slot_dim=128, slot_mlp=256, iterations=3, eps=1e-8,
    query_hidden=192, alloc_layers=1, alloc_heads=4, alloc_head_dim=32, alloc_mlp=192,
    render_hidden=[128, 128],
    batch_size=16, rays_per_scene=512, input_views=1, image_size=32,
    lr=3e-4, beta1=0.9, beta2=0.999, adam_eps=1e-8, weight_decay=0.0,
)

# The Rust model's parameter count (`osrt bench model --json` → "parameters"). By module:
#   ray encoding: 6·(8+8) = 96 dims, no parameters
#   encoder  607,072 = convs 3→32→64→64→128 (3×3, no bias) 864+18,432+36,864+73,728
#                      + 1×1 projection 16,384
#                      + ray-patch embedding 96→128 (4×4, stride 4, no bias) 196,608
#                      + 2 blocks × 132,096 (2 LN 512, q/k/v 3×16,384, out 16,512,
#                        MLP 128→256→128 65,920)
#   slots    215,808 = 3 LN 768, q/k/v 49,152, GRU 2×49,536, MLP 65,920, init 7×128 = 896
#   decoder  206,499 = query MLP 96→192→96 37,152
#                      + 1 block 94,976 (2 LN 384, q 12,288, k/v 2×16,384, out 12,384,
#                        MLP 96→192→96 37,152)
#                      + mix_q 12,288 + mix_k 16,384
#                      + render MLP 224→128→128→3 28,800+16,512+387
RUST_PARAMETERS = 1_029_379

# What `osrt bench model` re-executes itself with (src/cluster.rs, WORKER_MALLOC_ENV).
WORKER_MALLOC_ENV = {
    "MALLOC_MMAP_THRESHOLD_": "33554432",
    "MALLOC_TRIM_THRESHOLD_": "4294967296",
    "MALLOC_TOP_PAD_": "268435456",
}


def build(torch):
    nn = torch.nn

    class RayEncoding(nn.Module):
        """[.., 3] origins and directions → [.., 96]: sin block then cos block of
        (origin·f for each octave and axis, direction·f …), octave-major, f = 2^o·π."""

        def __init__(self, c):
            super().__init__()

            def freqs(octaves, start):
                return torch.tensor([2.0 ** (start + o) * math.pi
                                     for o in range(octaves) for _ in range(3)])

            self.register_buffer("of", freqs(c["origin_octaves"], c["origin_start"]))
            self.register_buffer("df", freqs(c["direction_octaves"], c["direction_start"]))
            self.no, self.nd = c["origin_octaves"], c["direction_octaves"]
            self.dim = 6 * (self.no + self.nd)

        def forward(self, o, d):
            rep = lambda x, n: x.repeat(*([1] * (x.dim() - 1)), n)  # cat of n copies
            a = torch.cat([rep(o, self.no) * self.of, rep(d, self.nd) * self.df], -1)
            return torch.cat([a.sin(), a.cos()], -1)

    class Attention(nn.Module):
        """Bias-free q/k/v, output projection with bias; q and kv widths may differ."""

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
        """Pre-LN: x + Attn(LN(x), ctx or LN(x)), then x + MLP(LN(x)); erf GELU."""

        def __init__(self, dim, ctx_dim, heads, head_dim, mlp):
            super().__init__()
            self.norm_attn = nn.LayerNorm(dim)  # eps 1e-5, as nn.rs
            self.attn = Attention(dim, ctx_dim, heads, head_dim)
            self.norm_mlp = nn.LayerNorm(dim)
            self.mlp = nn.Sequential(nn.Linear(dim, mlp), nn.GELU(), nn.Linear(mlp, dim))

        def forward(self, x, ctx=None):
            h = self.norm_attn(x)
            x = x + self.attn(h, h if ctx is None else ctx)
            return x + self.mlp(self.norm_mlp(x))

    class Transformer(nn.Module):
        """A stack of blocks, no final LayerNorm (as nn.rs)."""

        def __init__(self, dim, ctx_dim, layers, heads, head_dim, mlp):
            super().__init__()
            self.blocks = nn.ModuleList(Block(dim, ctx_dim, heads, head_dim, mlp)
                                        for _ in range(layers))

        def forward(self, x, ctx=None):
            for b in self.blocks:
                x = b(x, ctx)
            return x

    class Encoder(nn.Module):
        """[conv3×3 s1 → ReLU → conv3×3 s2 → ReLU] per block, no biases, 1×1 projection,
        tokens in (view, row, column) order, self-attention transformer. `ray_input`:
        "concat" (paper: the CNN reads RGB ⊕ rays) or "add" (the CNN reads RGB; a
        stride×stride patch embedding of the rays is added to the tokens)."""

        def __init__(self, c, ray_dim):
            super().__init__()
            self.add_rays = c["ray_input"] == "add"
            convs, c_in = [], 3 if self.add_rays else 3 + ray_dim
            for ch in c["conv_channels"]:
                convs += [nn.Conv2d(c_in, ch, 3, padding=1, bias=False), nn.ReLU(),
                          nn.Conv2d(ch, 2 * ch, 3, stride=2, padding=1, bias=False), nn.ReLU()]
                c_in = 2 * ch
            self.convs = nn.Sequential(*convs)
            self.project = nn.Conv2d(c_in, c["dim"], 1, bias=False)
            stride = 2 ** len(c["conv_channels"])
            self.ray_embed = (nn.Conv2d(ray_dim, c["dim"], stride, stride=stride, bias=False)
                              if self.add_rays else None)
            # candle_nn::conv2d_no_bias initialises with Kaiming normal (fan in, ReLU gain).
            for m in [*self.convs, self.project, self.ray_embed]:
                if isinstance(m, nn.Conv2d):
                    nn.init.kaiming_normal_(m.weight, mode="fan_in", nonlinearity="relu")
            self.transformer = Transformer(c["dim"], c["dim"], c["enc_layers"], c["enc_heads"],
                                           c["enc_head_dim"], c["enc_mlp"])

        def forward(self, rays, images, origins, directions):
            b, v, h, w, _ = images.shape
            enc = rays(origins, directions).reshape(b * v, h, w, -1)
            if self.add_rays:
                x = images.reshape(b * v, h, w, 3)
            else:
                x = torch.cat([images.reshape(b * v, h, w, 3), enc], -1)
            x = self.project(self.convs(x.permute(0, 3, 1, 2)))  # [b·v, d, h', w']
            if self.add_rays:
                x = x + self.ray_embed(enc.permute(0, 3, 1, 2))
            d = x.shape[1]
            tokens = x.reshape(b, v, d, -1).permute(0, 1, 3, 2).reshape(b, -1, d)
            return self.transformer(tokens)

    class Gru(nn.Module):
        """r, z, n gate order; h' = n + z·(h − n)."""

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
        """Learned init, softmax over slots, +ε then weighted mean over inputs, GRU, then
        pre-LN residual ReLU MLP; keys/values computed once."""

        def __init__(self, c, in_dim):
            super().__init__()
            ds = c["slot_dim"]
            self.c = c
            self.norm_inputs = nn.LayerNorm(in_dim)
            self.norm_slots = nn.LayerNorm(ds)
            self.norm_mlp = nn.LayerNorm(ds)
            self.to_q = nn.Linear(ds, ds, bias=False)
            self.to_k = nn.Linear(in_dim, ds, bias=False)
            self.to_v = nn.Linear(in_dim, ds, bias=False)
            self.gru = Gru(ds)
            self.mlp = nn.Sequential(nn.Linear(ds, c["slot_mlp"]), nn.ReLU(),
                                     nn.Linear(c["slot_mlp"], ds))
            self.init_slots = nn.Parameter(torch.randn(c["num_slots"], ds))

        def forward(self, inputs):
            x = self.norm_inputs(inputs)
            k, v = self.to_k(x), self.to_v(x)
            kt = k.transpose(-1, -2)
            slots = self.init_slots.unsqueeze(0).expand(x.shape[0], -1, -1)
            for _ in range(max(self.c["iterations"], 1)):
                prev = slots
                q = self.to_q(self.norm_slots(slots))
                attn = torch.softmax(q @ kt / math.sqrt(self.c["slot_dim"]), 1)  # over slots
                w = attn + self.c["eps"]
                w = w / w.sum(-1, keepdim=True)
                slots = self.gru(w @ v, prev)
                slots = slots + self.mlp(self.norm_mlp(slots))
            return slots

    class Mlp(nn.Module):
        """Linear → act → … → Linear (no activation after the last layer)."""

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
        """Query MLP → allocation transformer (cross-attention into slots) → single-head
        mixing weights over slots → render MLP on (mixed slot ⊕ query) → sigmoid."""

        def __init__(self, c, ray_dim):
            super().__init__()
            ds = c["slot_dim"]
            self.query_mlp = Mlp([ray_dim, c["query_hidden"], ray_dim], nn.ReLU)
            self.allocation = Transformer(ray_dim, ds, c["alloc_layers"], c["alloc_heads"],
                                          c["alloc_head_dim"], c["alloc_mlp"])
            self.mix_q = nn.Linear(ray_dim, ds, bias=False)
            self.mix_k = nn.Linear(ds, ds, bias=False)
            # max(x, 0.01·x) in Rust = LeakyReLU(0.01).
            self.render = Mlp([ds + ray_dim, *c["render_hidden"], 3], lambda: nn.LeakyReLU(0.01))
            self.ds = ds

        def forward(self, slots, rays):
            query = self.query_mlp(rays)
            allocated = self.allocation(query, slots)
            logits = self.mix_q(allocated) @ self.mix_k(slots).transpose(-1, -2)
            w = torch.softmax(logits / math.sqrt(self.ds), -1)
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
    count = lambda m: sum(p.numel() for p in m.parameters())
    params = count(model)
    opt = torch.optim.AdamW(model.parameters(), lr=c["lr"], betas=(c["beta1"], c["beta2"]),
                            eps=c["adam_eps"], weight_decay=c["weight_decay"])
    b, s, r, v = c["batch_size"], c["image_size"], c["rays_per_scene"], c["input_views"]
    # Random inputs of the benchmark's shapes: one camera per view (origin of norm 10, the
    # same for all its pixels), unit ray directions; 512 target rays per scene.
    images = torch.rand(b, v, s, s, 3)
    origins = 10.0 * unit(torch, b, v, 1, 1, 3).expand(-1, -1, s, s, -1).contiguous()
    directions = unit(torch, b, v, s, s, 3)
    t_orig = (10.0 * unit(torch, b, 1, 3)).expand(-1, r, -1).contiguous()
    t_dir = unit(torch, b, r, 3)
    target = torch.rand(b, r, 3)
    step_s, fb_s, losses = [], [], []
    for i in range(steps + 1):
        t0 = time.perf_counter()
        rgb, _ = model.decode(model.encode(images, origins, directions), t_orig, t_dir)
        loss = ((rgb - target) ** 2).mean()
        loss.backward()
        t1 = time.perf_counter()
        opt.step()
        opt.zero_grad(set_to_none=True)
        t2 = time.perf_counter()
        losses.append(loss.item())
        if i > 0:
            step_s.append(t2 - t0)
            fb_s.append(t1 - t0)
    # Render: one whole view (s·s rays) from the model's 7 slots, no gradients; the slots
    # are encoded once (excluded), as in bench_render.
    with torch.no_grad():
        slots = model.encode(images[:1], origins[:1], directions[:1])
        ro = origins[:1, 0].reshape(1, -1, 3)
        rd = directions[:1, 0].reshape(1, -1, 3)
        render_s = []
        for i in range(6):
            t0 = time.perf_counter()
            rgb, _ = model.decode(slots, ro, rd)
            rgb.flatten().tolist()  # as the Rust bench reads the pixels back
            if i > 0:
                render_s.append(time.perf_counter() - t0)
    m = statistics.median(step_s)
    frame = statistics.median(render_s)
    return dict(
        preset="clevr-lite-cpu", framework=f"torch {torch.__version__}", threads=threads,
        torch_threads=torch.get_num_threads(),
        parameters=params,
        parameters_by_module={k: count(getattr(model, k))
                              for k in ("encoder", "slot_attention", "decoder")},
        batch_size=b, rays_per_scene=r, image_size=s, steps=steps,
        median_step_s=m, median_forward_backward_s=statistics.median(fb_s),
        scenes_per_s=b / m,
        render={"decoder": "slot_mixer", "slots": int(slots.shape[1]), "image_size": s,
                "median_frame_s": frame, "fps": 1.0 / frame},
        render_fps=1.0 / frame,
        losses=losses,
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=10, help="timed steps after one warm-up")
    ap.add_argument("--threads", default="1,2", help="thread counts, one child process each")
    ap.add_argument("--out", default="target/bench/torch.json")
    ap.add_argument("--worker-allocator", action="store_true",
                    help="give the children the glibc malloc settings `osrt bench model` uses")
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.steps < 1:
        ap.error("--steps must be at least 1")
    if a.child:
        print(json.dumps(child(a.child, a.steps)))
        return
    results = {}
    for t in [int(x) for x in a.threads.split(",")]:
        print(f"benchmarking with {t} thread(s)…", file=sys.stderr)
        env = dict(os.environ, OMP_NUM_THREADS=str(t), MKL_NUM_THREADS=str(t))
        if a.worker_allocator:
            env.update(WORKER_MALLOC_ENV)
        out = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", str(t),
                              "--steps", str(a.steps)], env=env, capture_output=True, text=True)
        if out.returncode != 0:
            sys.exit(f"benchmark child ({t} threads) failed:\n{out.stderr}")
        r = json.loads(out.stdout.strip().splitlines()[-1])
        r["worker_allocator"] = a.worker_allocator
        results[str(t)] = r

    first = next(iter(results.values()))
    p = first["parameters"]
    check = "= Rust" if p == RUST_PARAMETERS else f"!= Rust {RUST_PARAMETERS:,} — MISMATCH"
    print(f"{first['preset']} mirror, {first['framework']}: {p:,} parameters ({check}; "
          + ", ".join(f"{k} {n:,}" for k, n in first["parameters_by_module"].items())
          + f"), batch {first['batch_size']} × {first['rays_per_scene']} rays, "
          f"{first['image_size']}px, median of {a.steps} step(s) after 1 warm-up"
          + (", workers' allocator" if a.worker_allocator else ""))
    head = ("threads", "step ms", "fwd+bwd ms", "scenes/s", "render ms", "render fps")
    print("  ".join(f"{h:>10}" for h in head))
    for t, r in results.items():
        row = (t, f"{r['median_step_s'] * 1e3:.1f}", f"{r['median_forward_backward_s'] * 1e3:.1f}",
               f"{r['scenes_per_s']:.1f}", f"{r['render']['median_frame_s'] * 1e3:.2f}",
               f"{r['render']['fps']:.1f}")
        print("  ".join(f"{x:>10}" for x in row))
    os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
    with open(a.out, "w") as f:
        json.dump(results, f, indent=2)
    print(f"saved to {a.out}")
    if p != RUST_PARAMETERS:
        sys.exit(1)


if __name__ == "__main__":
    main()
