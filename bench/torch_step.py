#!/usr/bin/env python3
"""PyTorch mirror of osrt's model and train step, timed on the CPU or a CUDA GPU.

For side-by-side timing with `osrt bench model` (same architecture and parameter count,
same batch shapes), on the CPU (same thread counts as the Rust side) or on a CUDA GPU, in
f32 or bf16 autocast. Run by hand; CI does not install PyTorch.

    python3 bench/torch_step.py [--steps 10] [--threads 1,2] [--out target/bench/torch.json]
                                [--worker-allocator]
    python3 bench/torch_step.py --device cuda [--presets clevr-lite-cpu,paper]
                                [--batch-size 16,256] [--dtypes f32,bf16 | --bf16]
                                [--image-size N] [--input-views N] [--rays-per-scene N]
                                [--cases 1x8192,5x2304] [--warmup N] [--tf32] [--no-render]
                                [--micro-batch-size M] [--list]

Mirrors crates/model (ray_encoding, encoder, nn, slot_attention, decoder/slot_mixer) with
the sizes of `Config::cpu()` (preset `clevr-lite-cpu`) or `Config::paper()` (preset
`paper`), and crates/bench/src/model.rs: the median of `--steps` full optimiser steps
(forward, MSE on the target rays, backward, AdamW step, zero_grad) after `--warmup` steps
(1 on the CPU, 2 on CUDA), batch building excluded; and render speed (decoding one whole
input view, image_size² rays, from the model's slots, no gradients; median of 5 after one
warm-up). On the CPU each (case, thread count) runs in a fresh child process (thread pools
are sized once per process), as in Rust, and counts its heap (`bench/heap_count.c`,
preloaded: `heap GiB`, the most bytes live at once in a timed step, as `osrt bench model`'s
`peak_heap_gib`); on CUDA every case runs in this one process, with
`torch.cuda.synchronize()` before each timer is read.
"""

import argparse
import contextlib
import gc
import json
import math
import os
import statistics
import subprocess
import sys
import time

# Model sizes and benchmark shapes per job preset (`osrt config --preset NAME`).
# `shapes`: the (input views, target rays per scene) cases timed by default.
PRESETS = {
    # model = Config::cpu()
    "clevr-lite-cpu": dict(
        origin_octaves=8, origin_start=-3, direction_octaves=8, direction_start=0,
        conv_channels=[32, 64], dim=128, enc_layers=2, enc_heads=4, enc_head_dim=32,
        enc_mlp=256, ray_input="add",
        num_slots=7, slot_dim=128, slot_mlp=256, iterations=3, eps=1e-8,
        query_hidden=192, alloc_layers=1, alloc_heads=4, alloc_head_dim=32, alloc_mlp=192,
        render_hidden=[128, 128],
        batch_size=16, image_size=32, shapes=[(1, 512)],
        lr=3e-4, beta1=0.9, beta2=0.999, adam_eps=1e-8, weight_decay=0.0,
    ),
    # model = Config::paper() (ray_encoding, encoder, slot_attention, slot_mixer `paper()`);
    # optimiser = TrainConfig::reference(). The Rust preset trains batch 256 × 8192 rays;
    # here the default batch is 32 (what one GPU holds), 128 px input views, and the two
    # cases of docs/gpu.md's table: 1 view + 8192 rays, 5 views + 2304 rays.
    "paper": dict(
        origin_octaves=15, origin_start=-5, direction_octaves=15, direction_start=0,
        conv_channels=[96, 192, 384], dim=768, enc_layers=5, enc_heads=12, enc_head_dim=64,
        enc_mlp=1536, ray_input="concat",
        num_slots=6, slot_dim=1536, slot_mlp=3072, iterations=1, eps=1e-8,
        query_hidden=360, alloc_layers=2, alloc_heads=12, alloc_head_dim=128, alloc_mlp=3072,
        render_hidden=[1536, 1536, 1536, 1536],
        batch_size=32, image_size=128, shapes=[(1, 8192), (5, 2304)],
        lr=1e-4, beta1=0.9, beta2=0.999, adam_eps=1e-8, weight_decay=0.0,
    ),
}
CFG = PRESETS["clevr-lite-cpu"]

# The Rust model's parameter count per preset (`osrt bench model --json` → "parameters").
# clevr-lite-cpu, by module:
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
# paper, by module:
#   ray encoding: 6·(15+15) = 180 dims, no parameters
#   encoder  29,514,144 = convs (3+180)→96→192→192→384→384→768 (3×3, no bias) 5,300,640
#                         + 1×1 projection 589,824 (ray_input = "concat": no ray embedding)
#                         + 5 blocks × 4,724,736 (width 768, 12 heads × 64, MLP 1536)
#   slots    28,342,272 = 3 LN 7,680, q 2,359,296, k/v 2×1,179,648, GRU 2×7,082,496,
#                         MLP 1536→3072→1536 9,441,792, init 6×1536 = 9,216
#   decoder  25,253,583 = query MLP 180→360→180 130,140
#                         + 2 blocks × 6,381,624 (width 180, cross-attention into the
#                           slots with 12 heads × 128, MLP 180→3072→180)
#                         + mix_q 276,480 + mix_k 2,359,296
#                         + render MLP 1716→1536→1536→1536→1536→3 9,724,419
RUST_PARAMETERS = {"clevr-lite-cpu": 1_029_379, "paper": 83_109_999}

# What `osrt bench model` re-executes itself with (src/cluster.rs, WORKER_MALLOC_ENV).
WORKER_MALLOC_ENV = {
    "MALLOC_MMAP_THRESHOLD_": "33554432",
    "MALLOC_TRIM_THRESHOLD_": "4294967296",
    "MALLOC_TOP_PAD_": "268435456",
}


def build(torch, c):
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

    return Osrt(c)


def unit(torch, *shape, device="cpu"):
    d = torch.randn(*shape, device=device)
    return d / d.norm(dim=-1, keepdim=True)


def run_case(torch, case):
    """Times one case (a dict: preset, batch_size, input_views, rays_per_scene, image_size,
    dtype, device, steps, warmup, render) in this process; returns its figures."""
    c = PRESETS[case["preset"]]
    dev = torch.device(case["device"])
    cuda = dev.type == "cuda"
    bf16 = case["dtype"] == "bf16"
    torch.manual_seed(0)
    model = build(torch, c).to(dev)
    count = lambda m: sum(p.numel() for p in m.parameters())
    params = count(model)
    # f32 master weights and f32 AdamW state; bf16 only inside autocast (forward + loss).
    opt = torch.optim.AdamW(model.parameters(), lr=c["lr"], betas=(c["beta1"], c["beta2"]),
                            eps=c["adam_eps"], weight_decay=c["weight_decay"])
    b, s = case["batch_size"], case["image_size"]
    micro = case.get("micro_batch_size") or b
    r, v = case["rays_per_scene"], case["input_views"]
    # Random inputs of the benchmark's shapes: one camera per view (origin of norm 10, the
    # same for all its pixels), unit ray directions; r target rays per scene.
    images = torch.rand(b, v, s, s, 3, device=dev)
    origins = 10.0 * unit(torch, b, v, 1, 1, 3, device=dev).expand(-1, -1, s, s, -1).contiguous()
    directions = unit(torch, b, v, s, s, 3, device=dev)
    t_orig = (10.0 * unit(torch, b, 1, 3, device=dev)).expand(-1, r, -1).contiguous()
    t_dir = unit(torch, b, r, 3, device=dev)
    target = torch.rand(b, r, 3, device=dev)
    autocast = ((lambda: torch.autocast(dev.type, dtype=torch.bfloat16)) if bf16
                else contextlib.nullcontext)
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    if cuda:
        torch.cuda.reset_peak_memory_stats(dev)
    heap = None if cuda else HeapCounter.attach(torch)
    step_s, fb_s, opt_s, losses, peak_heap = [], [], [], [], None
    for i in range(case["warmup"] + case["steps"]):
        if i == case["warmup"]:
            # The timed steps' resident peak only, as `osrt bench model` measures it.
            reset_peak_rss()
        if heap:
            heap.reset_peak()  # each step's peak from what is live before it, as osrt's
        sync()
        t0 = time.perf_counter()
        # The batch in passes of at most `micro` scenes, each pass's mean weighted by its
        # scenes and its gradient accumulated in `.grad` (PyTorch's gradient accumulation).
        loss = 0.0
        for lo in range(0, b, micro):
            hi = min(b, lo + micro)
            with autocast():
                rgb, _ = model.decode(model.encode(images[lo:hi], origins[lo:hi],
                                                   directions[lo:hi]), t_orig[lo:hi], t_dir[lo:hi])
                # .float(): a no-op in f32
                part = ((rgb.float() - target[lo:hi]) ** 2).mean() * ((hi - lo) / b)
            part.backward()
            loss += part.detach()
        sync()
        t1 = time.perf_counter()
        opt.step()
        opt.zero_grad(set_to_none=True)
        sync()
        t2 = time.perf_counter()
        losses.append(loss.item())
        if i >= case["warmup"]:
            if heap:
                peak_heap = max(peak_heap or 0, heap.peak())
            step_s.append(t2 - t0)
            fb_s.append(t1 - t0)
            opt_s.append(t2 - t1)
    if cuda:
        peak = torch.cuda.max_memory_allocated(dev) / 2**30
        peak_kind = "torch.cuda.max_memory_allocated"
    else:
        peak = peak_rss_gib()
        peak_kind = "resident high-water mark of the timed steps"
        if peak is None:
            import resource
            peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB → GiB
            peak_kind = "process max RSS"
    m = statistics.median(step_s)
    out = dict(
        preset=case["preset"], framework=f"torch {torch.__version__}",
        device=case["device"],
        device_name=torch.cuda.get_device_name(dev) if cuda else "cpu",
        dtype=case["dtype"],
        threads=case.get("threads"), torch_threads=torch.get_num_threads(),
        parameters=params,
        parameters_by_module={k: count(getattr(model, k))
                              for k in ("encoder", "slot_attention", "decoder")},
        batch_size=b, micro_batch_size=micro, input_views=v, rays_per_scene=r, image_size=s,
        steps=case["steps"], warmup_steps=case["warmup"],
        median_step_s=m, median_forward_backward_s=statistics.median(fb_s),
        median_optimizer_s=statistics.median(opt_s),
        scenes_per_s=b / m,
        peak_memory_gib=peak, peak_memory_kind=peak_kind,
        peak_rss_gib=peak_rss_gib(),
        peak_heap_gib=None if peak_heap is None else peak_heap / 2**30,
        losses=losses,
    )
    if cuda:
        out["tf32"] = bool(torch.backends.cuda.matmul.allow_tf32)
    if case.get("profile"):
        out["profile"] = profile_step(torch, lambda: model.decode(
            model.encode(images, origins, directions), t_orig, t_dir)[0], target, autocast,
            sync, cuda)
        opt.zero_grad(set_to_none=True)
    if case.get("ledger"):
        import torch_ledger

        def step():
            with autocast():
                rgb, _ = model.decode(model.encode(images, origins, directions), t_orig, t_dir)
                part = ((rgb.float() - target) ** 2).mean()
            part.backward()
        out["ledger"] = torch_ledger.record(torch, step, opt.step)
        opt.zero_grad(set_to_none=True)
    del opt, images, origins, directions, t_orig, t_dir, target, rgb, loss
    if case["render"]:
        # Render: one whole input view (s·s rays) from the model's slots, no gradients;
        # the slots are encoded once (excluded), as in bench_render.
        with torch.no_grad(), autocast():
            x = torch.rand(1, 1, s, s, 3, device=dev)
            ro = 10.0 * unit(torch, 1, 1, 1, 1, 3, device=dev).expand(-1, -1, s, s, -1)
            rd = unit(torch, 1, 1, s, s, 3, device=dev)
            slots = model.encode(x, ro.contiguous(), rd)
            ro, rd = ro.reshape(1, -1, 3), rd.reshape(1, -1, 3)
            render_s = []
            for i in range(6):
                sync()
                t0 = time.perf_counter()
                rgb, _ = model.decode(slots, ro, rd)
                rgb.float().flatten().tolist()  # as the Rust bench reads the pixels back
                if i > 0:
                    render_s.append(time.perf_counter() - t0)
        frame = statistics.median(render_s)
        out["render"] = {"decoder": "slot_mixer", "slots": int(slots.shape[1]),
                         "image_size": s, "median_frame_s": frame, "fps": 1.0 / frame}
        out["render_fps"] = 1.0 / frame
    return out


def profile_step(torch, forward, target, autocast, sync, cuda, rows=30):
    """One more forward and backward pass under the PyTorch profiler: its table of ops by
    self time (device time on CUDA, CPU time on the CPU), the `rows` largest, with the
    bytes each op allocated and did not free itself (outputs, saved tensors; negative
    where it freed more), and the profiled pass's own forward and backward seconds."""
    from torch.profiler import ProfilerActivity, profile
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=acts, profile_memory=True) as prof:
        sync()
        t0 = time.perf_counter()
        with autocast():
            loss = ((forward().float() - target) ** 2).mean()
        sync()
        t1 = time.perf_counter()
        loss.backward()
        sync()
        t2 = time.perf_counter()
    dev = "device" if cuda else "cpu"
    self_key, total_key = f"self_{dev}_time_total", f"{dev}_time_total"
    mem_key = f"self_{dev}_memory_usage"
    avgs = sorted(prof.key_averages(), key=lambda e: getattr(e, self_key), reverse=True)
    total_self = sum(getattr(e, self_key) for e in avgs)
    return dict(
        time=f"{dev} time", forward_s=t1 - t0, backward_s=t2 - t1,
        self_total_s=total_self / 1e6,
        ops=[dict(name=e.key, calls=e.count, self_s=getattr(e, self_key) / 1e6,
                  total_s=getattr(e, total_key) / 1e6,
                  self_memory_bytes=getattr(e, mem_key, 0))
             for e in avgs[:rows] if getattr(e, self_key) > 0])


def print_profile(r):
    p = r["profile"]
    print(f"profile of {label(r, False)} ({p['time']}, one step under the PyTorch profiler: "
          f"forward {p['forward_s'] * 1e3:.1f} ms, backward {p['backward_s'] * 1e3:.1f} ms; "
          f"self times add up to {p['self_total_s'] * 1e3:.1f} ms)")
    print(f"  {'self ms':>9} {'total ms':>9} {'self MiB':>9} {'calls':>6}  op")
    for o in p["ops"]:
        print(f"  {o['self_s'] * 1e3:>9.2f} {o['total_s'] * 1e3:>9.2f} "
              f"{o.get('self_memory_bytes', 0) / 2**20:>9.1f} {o['calls']:>6}  {o['name']}")


class HeapCounter:
    """The heap bytes live at once in this process, counted by `bench/heap_count.c` when
    the parent preloaded it (CPU children): the counterpart of `osrt bench model`'s
    `peak_heap_gib`."""

    def __init__(self, lib):
        self.lib = lib

    @staticmethod
    def attach(torch):
        """The counter, or None where it is not loaded; raises if it is loaded but does not
        see a tensor's allocation (PyTorch allocating around glibc would make its figure
        meaningless)."""
        import ctypes
        try:
            lib = ctypes.CDLL(None)
            for name in ("heapcount_live", "heapcount_peak"):
                getattr(lib, name).restype = ctypes.c_int64
            lib.heapcount_reset_peak.restype = None
        except AttributeError:
            return None
        h = HeapCounter(lib)
        before = h.live()
        probe = torch.ones(64 << 20)  # 256 MiB of f32
        seen = h.live() - before
        del probe
        if seen < 256 << 20:
            raise RuntimeError(f"bench/heap_count.c saw {seen:,} bytes of a 268,435,456-byte "
                               "tensor: PyTorch allocates around glibc's malloc here")
        return h

    def live(self):
        return self.lib.heapcount_live()

    def peak(self):
        return self.lib.heapcount_peak()

    def reset_peak(self):
        self.lib.heapcount_reset_peak()


def heap_counter_library(out_dir):
    """Compiles bench/heap_count.c into out_dir (once per run); the path, or None with a
    note on stderr where no C compiler is at hand."""
    import shutil
    cc = shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc")
    if cc is None:
        print("no C compiler: PyTorch's peak heap is not counted", file=sys.stderr)
        return None
    src = os.path.join(os.path.dirname(os.path.abspath(__file__)), "heap_count.c")
    lib = os.path.abspath(os.path.join(out_dir, "libheapcount.so"))
    os.makedirs(out_dir, exist_ok=True)
    r = subprocess.run([cc, "-O2", "-shared", "-fPIC", "-o", lib, src],
                       capture_output=True, text=True)
    if r.returncode != 0:
        print(f"{cc} could not build {src}: PyTorch's peak heap is not counted\n{r.stderr}",
              file=sys.stderr)
        return None
    return lib


def reset_peak_rss():
    """Resets the process's resident high-water mark (Linux: 5 to /proc/self/clear_refs)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def peak_rss_gib():
    """The resident high-water mark since the last reset (VmHWM), or None."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 2**20
    except OSError:
        pass
    return None


def child(threads, case):
    import torch
    torch.set_num_threads(threads)
    return run_case(torch, dict(case, threads=threads))


def ints(text):
    return [int(x) for x in str(text).split(",") if x.strip()]


def plan(a, ap):
    """The cases to time: presets × batch sizes × (views, rays) shapes × dtypes."""
    presets = [p.strip() for p in a.presets.split(",") if p.strip()]
    for p in presets:
        if p not in PRESETS:
            ap.error(f"unknown preset {p!r}: expected one of {', '.join(PRESETS)}")
    if a.bf16 and a.dtypes is not None:
        ap.error("give --bf16 or --dtypes, not both")
    dtypes = ["bf16"] if a.bf16 else (a.dtypes or "f32").split(",")
    for d in dtypes:
        if d not in ("f32", "bf16"):
            ap.error(f"unknown dtype {d!r}: expected f32 or bf16")
    if a.cases and (a.input_views is not None or a.rays_per_scene is not None):
        ap.error("give --cases or --input-views/--rays-per-scene, not both")
    explicit = None
    if a.cases:
        try:
            explicit = [tuple(int(n) for n in x.lower().split("x")) for x in a.cases.split(",")]
            assert all(len(t) == 2 for t in explicit)
        except (ValueError, AssertionError):
            ap.error("--cases wants VIEWSxRAYS[,VIEWSxRAYS…], e.g. 1x8192,5x2304")
    cases = []
    for p in presets:
        c = PRESETS[p]
        shapes = []
        for v, r in explicit or c["shapes"]:
            v = a.input_views if a.input_views is not None else v
            r = a.rays_per_scene if a.rays_per_scene is not None else r
            if (v, r) not in shapes:
                shapes.append((v, r))
        for bs in (ints(a.batch_size) if a.batch_size else [c["batch_size"]]):
            for v, r in shapes:
                for d in dtypes:
                    cases.append(dict(
                        preset=p, batch_size=bs, input_views=v, rays_per_scene=r,
                        image_size=a.image_size or c["image_size"], dtype=d,
                        device=a.device, steps=a.steps, warmup=a.warmup,
                        render=not a.no_render, profile=a.profile, ledger=a.ledger,
                        micro_batch_size=a.micro_batch_size))
    return cases


def label(r, by_threads):
    if by_threads:  # the one default CPU case: keyed by thread count, as before
        return str(r["threads"])
    key = (f"{r['preset']} b{r['batch_size']} {r['input_views']}v {r['rays_per_scene']}r "
           f"{r['image_size']}px {r['dtype']}")
    return key + (f" {r['threads']}t" if r["device"] == "cpu" else "")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=10, help="timed steps after the warm-up")
    ap.add_argument("--warmup", type=int,
                    help="untimed steps first (default 1 on the CPU, 2 on CUDA; CUDA needs ≥ 2)")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                    help="cpu: one child process per case and thread count; cuda: one "
                         "process, model, batch and optimiser on the GPU")
    ap.add_argument("--threads", default="1,2",
                    help="CPU thread counts, one child process each (ignored with cuda)")
    ap.add_argument("--presets", default="clevr-lite-cpu",
                    help=f"comma list of {', '.join(PRESETS)}")
    ap.add_argument("--batch-size", help="comma list of batch sizes replacing each "
                                         "preset's (clevr-lite-cpu 16, paper 32)")
    ap.add_argument("--micro-batch-size", type=int,
                    help="run each step's batch in passes of at most this many scenes, "
                         "their gradients accumulated in .grad (as osrt's "
                         "--micro-batch-size)")
    ap.add_argument("--image-size", type=int,
                    help="input-view side in pixels (default: clevr-lite-cpu 32, paper 128)")
    ap.add_argument("--input-views", type=int,
                    help="input views per scene, replacing each preset case's")
    ap.add_argument("--rays-per-scene", type=int,
                    help="target rays per scene, replacing each preset case's")
    ap.add_argument("--cases", help="VIEWSxRAYS comma list replacing every preset's "
                                    "(views, rays) cases (clevr-lite-cpu 1x512, paper "
                                    "1x8192,5x2304)")
    ap.add_argument("--dtypes", help="comma list of f32, bf16 (default f32)")
    ap.add_argument("--bf16", action="store_true",
                    help="same as --dtypes bf16: torch.autocast bf16 around forward + loss, "
                         "f32 weights and AdamW")
    ap.add_argument("--tf32", action="store_true",
                    help="cuda: allow TF32 in f32 matmuls and cuDNN convolutions (default: "
                         "off in both, so f32 is f32)")
    ap.add_argument("--no-render", action="store_true", help="skip the render timing")
    ap.add_argument("--profile", action="store_true",
                    help="after the timed steps, one forward and backward pass under the "
                    "PyTorch profiler: its ops by self time (the counterpart of "
                    "`osrt bench model --profile`)")
    ap.add_argument("--ledger", action="store_true",
                    help="after the timed steps, one more step's ledger: every product, cast "
                    "and copy (bench/torch_ledger.py; the counterpart of "
                    "`osrt bench model --ledger`)")
    ap.add_argument("--list", action="store_true", help="print the cases and exit")
    ap.add_argument("--out", default="target/bench/torch.json")
    ap.add_argument("--worker-allocator", action="store_true",
                    help="give the children the glibc malloc settings `osrt bench model` uses")
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--child-case", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.steps < 1:
        ap.error("--steps must be at least 1")
    if a.warmup is None:
        a.warmup = 2 if a.device == "cuda" else 1
    if a.device == "cuda" and a.warmup < 2:
        ap.error("--warmup must be at least 2 on cuda (the first steps load kernels)")
    if a.warmup < 0:
        ap.error("--warmup must not be negative")
    if a.micro_batch_size is not None and a.micro_batch_size < 1:
        ap.error("--micro-batch-size must be at least 1")
    if a.child:
        print(json.dumps(child(a.child, json.loads(a.child_case))))
        return
    cases = plan(a, ap)
    if a.list:
        for case in cases:
            print(json.dumps(case))
        return

    results = []
    if a.device == "cpu":
        heap_lib = heap_counter_library(os.path.dirname(a.out) or ".")
        for case in cases:
            for t in ints(a.threads):
                print(f"benchmarking {case['preset']} batch {case['batch_size']}, "
                      f"{case['input_views']} view(s), {case['rays_per_scene']} rays, "
                      f"{case['image_size']}px, {case['dtype']}, {t} thread(s)…",
                      file=sys.stderr)
                env = dict(os.environ, OMP_NUM_THREADS=str(t), MKL_NUM_THREADS=str(t))
                if a.worker_allocator:
                    env.update(WORKER_MALLOC_ENV)
                if heap_lib:
                    env["LD_PRELOAD"] = " ".join(
                        x for x in (heap_lib, env.get("LD_PRELOAD")) if x)
                out = subprocess.run([sys.executable, os.path.abspath(__file__),
                                      "--child", str(t), "--child-case", json.dumps(case),
                                      "--steps", str(a.steps)],
                                     env=env, capture_output=True, text=True)
                if out.returncode != 0:
                    sys.exit(f"benchmark child ({t} threads) failed:\n{out.stderr}")
                r = json.loads(out.stdout.strip().splitlines()[-1])
                r["worker_allocator"] = a.worker_allocator
                results.append(r)
    else:
        import torch
        if not torch.cuda.is_available():
            sys.exit("--device cuda: torch.cuda.is_available() is False")
        torch.backends.cuda.matmul.allow_tf32 = a.tf32
        torch.backends.cudnn.allow_tf32 = a.tf32
        for case in cases:
            print(f"benchmarking {case['preset']} batch {case['batch_size']}, "
                  f"{case['input_views']} view(s), {case['rays_per_scene']} rays, "
                  f"{case['image_size']}px, {case['dtype']} on "
                  f"{torch.cuda.get_device_name()}…", file=sys.stderr)
            try:
                results.append(run_case(torch, case))
            except torch.cuda.OutOfMemoryError as e:
                print(f"  out of memory: {str(e).splitlines()[0]}", file=sys.stderr)
                results.append(dict(case, error="out of memory",
                                    framework=f"torch {torch.__version__}",
                                    device_name=torch.cuda.get_device_name()))
            gc.collect()
            torch.cuda.empty_cache()

    ok = True
    ran = [r for r in results if "error" not in r]
    for p in dict.fromkeys(r["preset"] for r in ran):
        r = next(x for x in ran if x["preset"] == p)
        n, want = r["parameters"], RUST_PARAMETERS[p]
        check = "= Rust" if n == want else f"!= Rust {want:,} — MISMATCH"
        ok &= n == want
        print(f"{p} mirror, {r['framework']} on {r['device_name']}: {n:,} parameters "
              f"({check}; " + ", ".join(f"{k} {m:,}" for k, m in r["parameters_by_module"].items())
              + f"), median of {a.steps} step(s) after {a.warmup} warm-up"
              + (", workers' allocator" if a.worker_allocator else "")
              + (", TF32 allowed" if a.device == "cuda" and a.tf32 else ""))
    head = ("preset", "params", "threads" if a.device == "cpu" else "device", "batch", "views",
            "rays", "px", "dtype", "step ms", "fwd+bwd ms", "optim ms", "scenes/s", "peak GiB",
            "heap GiB", "render ms", "render fps")
    widths = (14, 11, 7, 5, 5, 6, 4, 5, 9, 10, 8, 9, 8, 8, 9, 10)
    print("  ".join(f"{h:>{w}}" for h, w in zip(head, widths)))
    for r in results:
        where = str(r.get("threads")) if a.device == "cpu" else "cuda"
        if "error" in r:
            row = (r["preset"], "", where, r["batch_size"], r["input_views"],
                   r["rays_per_scene"], r["image_size"], r["dtype"], r["error"])
            print("  ".join(f"{x!s:>{w}}" for x, w in zip(row, widths)))
            continue
        row = (r["preset"], f"{r['parameters']:,}", where, r["batch_size"], r["input_views"],
               r["rays_per_scene"], r["image_size"], r["dtype"],
               f"{r['median_step_s'] * 1e3:.1f}", f"{r['median_forward_backward_s'] * 1e3:.1f}",
               f"{r['median_optimizer_s'] * 1e3:.1f}",
               f"{r['scenes_per_s']:.{1 if r['scenes_per_s'] >= 10 else 3}f}",
               f"{r['peak_memory_gib']:.2f}",
               "-" if r.get("peak_heap_gib") is None else f"{r['peak_heap_gib']:.2f}",
               f"{r['render']['median_frame_s'] * 1e3:.2f}" if "render" in r else "-",
               f"{r['render']['fps']:.1f}" if "render" in r else "-")
        print("  ".join(f"{x!s:>{w}}" for x, w in zip(row, widths)))
    for r in results:
        if "profile" in r:
            print_profile(r)
        if "ledger" in r:
            t = r["ledger"]["totals"]
            print(f"ledger of {label(r, False)}: {t['products']} products, "
                  + ", ".join(f"{k} {v / 1e9:.2f} GFLOP" for k, v in sorted(t['flops'].items()))
                  + "; " + ", ".join(f"{k} {v / 1e6:.1f} MB" for k, v in sorted(t['bytes'].items()))
                  + f"; at {r['ledger']['rates']['name']}: products {t['product_s'] * 1e3:.3f} ms, "
                  f"moves {t['movement_s'] * 1e3:.3f} ms")
    by_threads = a.device == "cpu" and len(cases) == 1
    saved = {label(r, by_threads): r for r in results}
    os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
    with open(a.out, "w") as f:
        json.dump(saved, f, indent=2)
    print(f"saved to {a.out}")
    if not ok:
        sys.exit(1)


if __name__ == "__main__":
    main()
