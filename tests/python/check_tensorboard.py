"""TensorBoard's own readers see a run's event files (RUN/tb) as metrics.jsonl says:
every record's figures as scalars at its step, exactly one value per tag and step, and
each validation's pictures as PNG images.

    python3 check_tensorboard.py RUN

Prints a JSON summary; exits non-zero with the first disagreement.
"""

import collections
import glob
import io
import json
import math
import os
import sys

import numpy as np
from PIL import Image
from tensorboard.backend.event_processing import event_accumulator, event_file_loader
from tensorboard.compat.proto import event_pb2

TRAIN = {
    "train/loss": "loss",
    "train/lr": "lr",
    "train/scenes_per_s": "scenes_per_s",
    "train/grad_norm": "grad_norm",
    "train/skipped_steps": "skipped",
    "train/workers": "workers",
    "job/restarts": "restarts",
}
EVAL = {
    "eval/psnr": "psnr",
    "eval/baseline_psnr": "baseline_psnr",
    "eval/fg_ari": "fg_ari",
    "eval/fg_ari_2d": "fg_ari_2d",
    "eval/ari": "ari",
    "eval/render_fps": "render_fps",
}


def expected(records):
    """(tag, step) -> float32 value that metrics.jsonl implies."""
    want = {}
    for r in records:
        table = TRAIN if "loss" in r else EVAL
        for tag, key in table.items():
            v = r.get(key, 0 if key == "restarts" else None)
            if v is not None and math.isfinite(v):
                want[(tag, r["step"])] = float(np.float32(v))
        for o in r.get("by_objects", []):
            if o.get("fg_ari") is not None:
                want[(f"eval/fg_ari_by_objects/{o['objects']}", r["step"])] = float(
                    np.float32(o["fg_ari"])
                )
    return want


def main():
    run = sys.argv[1]
    records = [json.loads(l) for l in open(os.path.join(run, "metrics.jsonl")) if l.strip()]
    files = sorted(glob.glob(os.path.join(run, "tb", "events.out.tfevents.*")))
    assert files, "no event files"

    # The events as written, file by file, framed by TensorBoard's own record reader.
    seen = collections.Counter()
    scalars, images = {}, {}
    for f in files:
        for raw in event_file_loader.RawEventFileLoader(f).Load():
            ev = event_pb2.Event.FromString(raw)
            if not ev.HasField("summary"):
                continue
            for v in ev.summary.value:
                key = (v.tag, ev.step)
                seen[key] += 1
                if v.HasField("simple_value"):
                    scalars[key] = v.simple_value
                elif v.HasField("image"):
                    images[key] = v.image
    dup = [k for k, n in seen.items() if n > 1]
    assert not dup, f"more than one value for {dup[:5]}"

    want = expected(records)
    missing = sorted(set(want) - set(scalars))
    assert not missing, f"scalars missing: {missing[:5]}"
    for k, v in want.items():
        assert scalars[k] == v, f"{k}: {scalars[k]} in the events, {v} in metrics.jsonl"
    extra_steps = {s for (t, s) in scalars if t in TRAIN or t in EVAL} - {r["step"] for r in records}
    assert not extra_steps, f"events at steps without a record: {sorted(extra_steps)[:5]}"

    eval_steps = sorted(r["step"] for r in records if "psnr" in r)
    for s in eval_steps:
        img = images.get(("eval/render", s))
        assert img is not None, f"no render picture at step {s}"
        decoded = Image.open(io.BytesIO(img.encoded_image_string))
        assert decoded.format == "PNG", decoded.format
        assert decoded.size == (img.width, img.height), (decoded.size, img.width, img.height)
        assert ("eval/segmentation", s) in images, f"no segmentation picture at step {s}"

    # The accumulator the TensorBoard server runs on the folder: it migrates the scalar
    # and image summaries to their plugins and sees them all.
    acc = event_accumulator.EventAccumulator(
        os.path.join(run, "tb"),
        size_guidance={event_accumulator.SCALARS: 0, event_accumulator.IMAGES: 0},
    )
    acc.Reload()
    tags = acc.Tags()
    losses = [e.step for e in acc.Scalars("train/loss")]
    want_losses = sorted(s for (t, s) in want if t == "train/loss")
    assert losses == want_losses, (losses[:10], want_losses[:10])
    assert [e.step for e in acc.Images("eval/render")] == eval_steps
    print(
        json.dumps(
            {
                "files": len(files),
                "scalars": len(scalars),
                "images": len(images),
                "train_steps": len(want_losses),
                "eval_steps": eval_steps,
                "tags": sorted(tags["scalars"]) + sorted(tags["images"]),
            }
        )
    )


main()
