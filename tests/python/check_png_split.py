"""pyarrow reads an imported split stored with the PNG codec, and Pillow decodes every
view's image and mask bytes to the source release's pixels.

    python3 check_png_split.py DATASET SPLIT SRC
"""

import io
import json
import sys

import numpy as np
import pyarrow.parquet as pq
from PIL import Image


def main():
    dataset, split, src = sys.argv[1:4]
    table = pq.read_table(f"{dataset}/{split}")
    meta = pq.read_metadata(sorted(__import__("glob").glob(f"{dataset}/{split}/*.parquet"))[0])
    kv = {k.decode(): v.decode() for k, v in meta.metadata.items()}
    assert kv["osrt.image_codec"] == "png", kv
    assert kv["osrt.scene_schema_version"] == "2", kv
    checked = 0
    for row in table.to_pylist():
        s = row["scene_id"]
        for v, view in enumerate(row["views"]):
            img = Image.open(io.BytesIO(view["image"]))
            assert img.mode == "RGB", img.mode
            want = np.asarray(Image.open(f"{src}/images/img_{s}_{v}.png"))[..., :3]
            assert np.array_equal(np.asarray(img), want), (s, v)
            mask = Image.open(io.BytesIO(view["mask"]))
            assert mask.mode == "L", mask.mode
            checked += 1
    print(json.dumps({"views": checked}))


if __name__ == "__main__":
    main()
