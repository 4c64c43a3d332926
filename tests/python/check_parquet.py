"""Cross-check a generated osrt dataset with an independent Parquet reader (pyarrow).

Usage: python3 check_parquet.py DATASET_DIR SPLIT EXPECTED_SCENES
Checks: the schema version key, row count, views per scene against the manifest,
image and mask byte sizes against width × height, and camera rotations orthonormal.
Prints one line per check and exits non-zero on the first failure.
"""
import glob
import json
import os
import sys

import pyarrow.parquet as pq


def main():
    root, split, expected = sys.argv[1], sys.argv[2], int(sys.argv[3])
    manifest = json.load(open(os.path.join(root, "manifest.json")))
    files = sorted(glob.glob(os.path.join(root, split, "*.parquet")))
    assert files, f"no parquet files in {root}/{split}"
    rows = 0
    for f in files:
        pf = pq.ParquetFile(f)
        kv = pf.metadata.metadata or {}
        version = kv.get(b"osrt.scene_schema_version")
        assert version == str(manifest["schema_version"]).encode(), f"{f}: version {version!r}"
        table = pf.read()
        rows += table.num_rows
        lo, hi = manifest["views_per_scene"]
        for scene in table.to_pylist():
            views = scene["views"]
            assert lo <= len(views) <= hi, f"{f}: scene {scene['scene_id']} has {len(views)} views"
            for v in views:
                w, h = v["width"], v["height"]
                assert [w, h] == manifest["image_size"], (w, h)
                assert len(v["image"]) == w * h * 3, f"image bytes {len(v['image'])} != {w * h * 3}"
                assert len(v["mask"]) == w * h, f"mask bytes {len(v['mask'])} != {w * h}"
                r = v["camera_rotation"]
                for i in range(3):
                    for j in range(3):
                        dot = sum(r[3 * k + i] * r[3 * k + j] for k in range(3))
                        assert abs(dot - (1.0 if i == j else 0.0)) < 1e-4, "rotation not orthonormal"
            objs = scene["objects"]
            lo_o, hi_o = manifest["objects_per_scene"]
            assert objs is not None and lo_o <= len(objs) <= hi_o, f"objects {objs and len(objs)}"
    assert rows == expected, f"{rows} rows, expected {expected}"
    assert manifest["splits"][split]["scenes"] == expected
    print(f"pyarrow check passed: {split} has {rows} scenes in {len(files)} files")


if __name__ == "__main__":
    main()
