"""PyTorch's ledger of one train step, and its comparison with osrt's.

`record` runs one forward and backward pass (and the optimiser's step) of the mirror model
under a `TorchDispatchMode`, which sees every ATen op after autocast has chosen its types:
each matrix product (`mm`, `addmm`, `bmm`, `baddbmm`, and the products inside
`convolution` / `convolution_backward`) with its m, n, k, batch count, operand and output
types and whether it reads an operand transposed; each cast (`_to_copy` to another type)
and copy (`clone`, `copy_`, `cat`, a same-type `_to_copy`) with its bytes; and every other
op's bytes read and written (views read nothing). Backward ops are those run while
autograd's engine runs a graph task (`torch._C._current_graph_task_id() >= 0`).
`bench/torch_step.py --ledger` calls it; the counterpart is `osrt bench model --ledger`.

`python3 bench/torch_ledger.py compare` sets the two side by side: FLOPs by operand type,
bytes cast and copied, the time at an H200's rates (the same constants as
`osrt_kernels::ledger::H200`), and the products osrt runs in f32 where PyTorch runs bf16.
Given ledgers at two batch sizes it extrapolates both linearly to a third (every count is
a constant plus a multiple of the batch: the weights' casts are per step, the rest per
scene).
"""
import argparse
import json
import sys

# NVIDIA H200 SXM datasheet peaks (nvidia.com/en-us/data-center/h200, read 2026-11-29):
# BF16 tensor core 989 TFLOPS dense, FP32 67 TFLOPS, HBM3e 4.8 TB/s. As in
# crates/kernels/src/ledger.rs.
H200 = dict(name="H200 SXM (datasheet peaks)", bf16_flops=989e12, f32_flops=67e12,
            bandwidth=4.8e12)

VIEWS = {"view", "_unsafe_view", "t", "transpose", "permute", "expand", "alias", "detach",
         "slice", "select", "unsqueeze", "squeeze", "as_strided", "split", "chunk",
         "unbind", "narrow", "reshape", "_reshape_alias", "split_with_sizes", "lift_fresh",
         "empty", "empty_like", "empty_strided", "zeros", "zeros_like", "ones_like",
         "_local_scalar_dense", "is_same_size", "new_empty_strided", "new_empty"}
COPIES = {"clone", "copy_", "cat", "contiguous", "stack"}


def dtype_name(torch, d):
    return {torch.float32: "f32", torch.bfloat16: "bf16", torch.float16: "f16",
            torch.float64: "f64"}.get(d, str(d).replace("torch.", ""))


def tensors(x):
    import torch
    if isinstance(x, torch.Tensor):
        yield x
    elif isinstance(x, (list, tuple)):
        for y in x:
            yield from tensors(y)


def nbytes(x):
    return sum(t.numel() * t.element_size() for t in tensors(x))


def transposed(t):
    """Whether a matrix operand is read transposed (column-major last two dims)."""
    if t.dim() < 2:
        return False
    s, (r, c) = t.stride(), t.shape[-2:]
    return (s[-2] == 1 or r == 1) and (s[-1] == r or c == 1) and not (s[-1] == 1 and c > 1)


class Book:
    """Entries keyed by their fields, with counts (as osrt's `Entries`)."""

    def __init__(self):
        self.products, self.movements = {}, {}

    def product(self, kind, phase, batch, m, n, k, a, b, out, tr):
        key = (kind, phase, batch, m, n, k, a, b, out, tuple(tr))
        self.products[key] = self.products.get(key, 0) + 1

    def moved(self, kind, phase, moved, what, read, written):
        key = (kind, phase, moved, what, read, written)
        self.movements[key] = self.movements.get(key, 0) + 1

    def entries(self):
        pf = ("kind", "phase", "batch", "m", "n", "k", "a", "b", "out", "transposed")
        mf = ("kind", "phase", "moved", "what", "read", "written")
        return dict(products=[[dict(zip(pf, k)), n] for k, n in sorted(self.products.items())],
                    movements=[[dict(zip(mf, k)), n] for k, n in sorted(self.movements.items())])


def conv_products(torch, book, phase, name, args, out):
    """The products inside a convolution (im2col · kernel) and its backward pass."""
    dn = lambda t: dtype_name(torch, t.dtype)
    if name == "convolution":
        x, w, groups = args[0], args[1], args[8] if len(args) > 8 else 1
        n, co, ho, wo = out.shape
        k = w.shape[1] * w.shape[2] * w.shape[3]
        book.product("convolution", phase, groups, n * ho * wo, co // groups, k,
                     dn(x), dn(w), dn(out), (False, True))
        return
    g, x, w = args[0], args[1], args[2]
    mask = args[-1]
    groups = args[9] if len(args) > 9 else 1
    n, co, ho, wo = g.shape
    k = w.shape[1] * w.shape[2] * w.shape[3]
    if mask[0]:
        book.product("convolution", phase, groups, n * ho * wo, k, co // groups,
                     dn(g), dn(w), dn(x), (False, False))
    if mask[1]:
        book.product("convolution", phase, groups, co // groups, k, n * ho * wo,
                     dn(g), dn(x), dn(w), (True, False))


def recorder(torch, book, kind):
    from torch.utils._python_dispatch import TorchDispatchMode

    class Mode(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            kwargs = kwargs or {}
            out = func(*args, **kwargs)
            name = func.overloadpacket.__name__
            if kind() == "optimiser":
                phase, k = "backward", "optimiser"
            else:
                phase = "backward" if torch._C._current_graph_task_id() >= 0 else "forward"
                k = "products" if name in ("mm", "addmm", "bmm", "baddbmm") else "other"
            dn = lambda t: dtype_name(torch, t.dtype)
            if name in ("mm", "bmm", "addmm", "baddbmm"):
                a, b = (args[1], args[2]) if name in ("addmm", "baddbmm") else (args[0], args[1])
                batch = a.shape[0] if a.dim() == 3 else 1
                book.product(k, phase, batch, a.shape[-2], b.shape[-1], a.shape[-1],
                             dn(a), dn(b), dn(out), (transposed(a), transposed(b)))
                if name in ("addmm", "baddbmm"):
                    book.moved(k, phase, "op", f"{name} bias", nbytes(args[0]), 0)
            elif name in ("convolution", "convolution_backward"):
                conv_products(torch, book, phase, name, args, out)
            elif name == "_to_copy":
                src = args[0]
                moved = "cast" if out.dtype != src.dtype else "copy"
                what = (f"cast {dn(src)}→{dn(out)}" if moved == "cast" else f"copy {dn(src)}")
                book.moved(k, phase, moved, what, nbytes(src), nbytes(out))
            elif name in COPIES:
                what = f"{name} {dn(next(tensors(out)))}" if nbytes(out) else name
                read = nbytes(args[1]) if name == "copy_" else nbytes(args)
                book.moved(k, phase, "copy", what, read, nbytes(out))
            elif name not in VIEWS:
                book.moved(k, phase, "op", name, nbytes(args) + nbytes(kwargs.get("out")),
                           nbytes(out))
            return out

    return Mode()


def record(torch, step, optimise):
    """The ledger of `step()` (forward and backward) then `optimise()`."""
    book, where = Book(), ["step"]
    with recorder(torch, book, lambda: where[0]):
        step()
        where[0] = "optimiser"
        optimise()
    e = book.entries()
    return dict(entries=e, totals=totals(e, H200), rates=H200)


# ---------------------------------------------------------------- totals, comparison

def bytes_of(d):
    return {"f64": 8, "bf16": 2, "f16": 2, "u8": 1}.get(d, 4)


def flops(p):
    return 2.0 * p["batch"] * p["m"] * p["n"] * p["k"]


def precision(p):
    return p["a"] if p["a"] == p["b"] else "mixed"


def product_s(p, rates):
    mk, kn, mn = p["batch"] * p["m"] * p["k"], p["batch"] * p["k"] * p["n"], \
        p["batch"] * p["m"] * p["n"]
    b = mk * bytes_of(p["a"]) + kn * bytes_of(p["b"]) + mn * bytes_of(p["out"])
    rate = rates["bf16_flops"] if precision(p) in ("bf16", "f16") else rates["f32_flops"]
    return max(flops(p) / rate, b / rates["bandwidth"])


def totals(e, rates):
    """The step's totals: FLOPs by operand type (and made again), bytes by movement, time."""
    t = dict(products=0, flops={}, recompute_flops=0.0, bytes={}, product_s=0.0,
             movement_s=0.0)
    for p, n in e["products"]:
        t["products"] += n
        t["flops"][precision(p)] = t["flops"].get(precision(p), 0.0) + n * flops(p)
        if p["phase"] == "recompute":
            t["recompute_flops"] += n * flops(p)
        t["product_s"] += n * product_s(p, rates)
    for m, n in e["movements"]:
        t["bytes"][m["moved"]] = t["bytes"].get(m["moved"], 0) + n * (m["read"] + m["written"])
        t["movement_s"] += n * (m["read"] + m["written"]) / rates["bandwidth"]
    return t


def load(path, key, views=None):
    """An osrt ledger (`osrt bench model --ledger` JSON) or a PyTorch one
    (`bench/torch_step.py --ledger` JSON), the case of `views` input views where the file
    holds several: (batch size, entries)."""
    with open(path) as f:
        j = json.load(f)
    fits = lambda r: views is None or r["input_views"] == views
    if key == "osrt":
        led = next(r for v in j.values() for r in v.get("ledgers", []) if fits(r))
        return led["batch_size"], led["entries"]
    r = next(r for r in j.values() if isinstance(r, dict) and "ledger" in r and fits(r))
    return r["batch_size"], r["ledger"]["entries"]


def flat(e):
    """Entries as {(kind-free key): count}, the kinds dropped (the two sides name them
    differently)."""
    out = {}
    for p, n in e["products"]:
        key = ("p", p["phase"], p["batch"], p["m"], p["n"], p["k"], p["a"], p["b"], p["out"])
        out[key] = out.get(key, 0) + n
    for m, n in e["movements"]:
        key = ("m", m["phase"], m["moved"], m["what"], m["read"], m["written"])
        out[key] = out.get(key, 0) + n
    return out


def extrapolate(small, big, bs, bb, to):
    """Totals at batch `to` from totals at batches `bs` < `bb`, each figure linear in the
    batch."""
    f = (to - bs) / (bb - bs)
    lin = lambda a, b: a + f * (b - a)
    out = dict(products=lin(small["products"], big["products"]))
    for key in ("flops", "bytes"):
        ks = set(small[key]) | set(big[key])
        out[key] = {k: lin(small[key].get(k, 0), big[key].get(k, 0)) for k in ks}
    for key in ("recompute_flops", "product_s", "movement_s"):
        out[key] = lin(small[key], big[key])
    return out


def compare(a):
    rows = []
    for side, paths in (("osrt", a.osrt), ("PyTorch", a.torch)):
        loaded = sorted((load(p, "osrt" if side == "osrt" else "torch", a.views)
                         for p in paths), key=lambda x: x[0])
        t = [totals(e, H200) for _, e in loaded]
        if len(loaded) == 2 and a.batch:
            (bs, _), (bb, _) = loaded
            rows.append((side, a.batch, extrapolate(t[0], t[1], bs, bb, a.batch)))
        else:
            rows.extend((side, b, x) for (b, _), x in zip(loaded, t))
    print(f"time at {H200['name']}")
    print(f"  {'':8} {'batch':>5} {'bf16 GFLOP':>11} {'f32 GFLOP':>10} {'of which again':>14} "
          f"{'cast MB':>9} {'copy MB':>9} {'other MB':>9} {'products ms':>11} {'moves ms':>9}")
    for side, b, t in rows:
        fl = lambda k: t["flops"].get(k, 0.0) / 1e9
        by = lambda k: t["bytes"].get(k, 0) / 1e6
        print(f"  {side:8} {b:>5} {fl('bf16'):>11.1f} {fl('f32') + fl('mixed'):>10.1f} "
              f"{t['recompute_flops'] / 1e9:>14.1f} {by('cast'):>9.1f} {by('copy'):>9.1f} "
              f"{by('op'):>9.1f} {t['product_s'] * 1e3:>11.2f} {t['movement_s'] * 1e3:>9.2f}")
    o, p = [r for r in rows if r[0] == "osrt"], [r for r in rows if r[0] == "PyTorch"]
    if o and p:
        fo = sum(o[-1][2]["flops"].values()) - o[-1][2]["recompute_flops"]
        fp = sum(p[-1][2]["flops"].values())
        co = o[-1][2]["bytes"].get("cast", 0) + o[-1][2]["bytes"].get("copy", 0)
        cp = p[-1][2]["bytes"].get("cast", 0) + p[-1][2]["bytes"].get("copy", 0)
        print(f"  osrt / PyTorch: product FLOPs (less those made again) {fo / fp:.3f}×, "
              f"bytes cast and copied {co / cp:.2f}×")
    # Products osrt runs in f32 where PyTorch's shapes of the same size run in bf16.
    _, eo = max((load(x, "osrt", a.views) for x in a.osrt), key=lambda x: x[0])
    _, ep = max((load(x, "torch", a.views) for x in a.torch), key=lambda x: x[0])
    sizes = lambda p: (p["batch"], tuple(sorted((p["m"], p["n"], p["k"]))))
    bf16_shapes = {sizes(p) for p, _ in ep["products"] if precision(p) == "bf16"}
    odd = [(p, n) for p, n in eo["products"]
           if precision(p) != "bf16" and sizes(p) in bf16_shapes]
    print(f"  osrt products not in bf16 whose size PyTorch runs in bf16: {len(odd)}")
    for p, n in odd:
        print(f"    {n} × {p['kind']} {p['phase']} {p['batch']}·{p['m']}×{p['n']}×{p['k']} "
              f"{p['a']}×{p['b']}→{p['out']}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("compare", help="osrt's and PyTorch's ledgers side by side")
    c.add_argument("--osrt", nargs="+", required=True,
                   help="`osrt bench model --ledger` JSON (one, or two batch sizes)")
    c.add_argument("--torch", nargs="+", required=True,
                   help="`bench/torch_step.py --ledger` JSON (one, or two batch sizes)")
    c.add_argument("--batch", type=int, help="extrapolate two batch sizes to this one")
    c.add_argument("--views", type=int, help="the case of this many input views (files "
                   "with several)")
    a = ap.parse_args()
    if a.cmd == "compare":
        compare(a)


if __name__ == "__main__":
    sys.exit(main())
