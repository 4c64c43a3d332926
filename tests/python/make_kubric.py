"""Writes small MSN-Hard-style TFDS TFRecord shards (Kubric's multi_shapenet_conditional
frames as sunds exports them), independently of osrt, for the importer's tests
(tests/import.rs): tf.train.Example messages built with Google's protobuf package from a
runtime descriptor of TensorFlow's example.proto, framed as TFRecords with the crc32c
package's CRC-32C.

    python3 make_kubric.py OUT

OUT/msn-train.tfrecord-0000{0,1}-of-00002 (3 + 2 scenes), OUT/msn-val.tfrecord-00000-of-00001
(1), OUT/msn-test.tfrecord-00000-of-00001 (2); 10 cameras of 20x16 each. Also the expected
values in record order (train, val, test): expected_images.npy [8, 10, 16, 20, 3],
expected_masks.npy (clip(instance, 1, 34) - 1), expected_positions.npy [8, 10, 3] and
expected_rays.npy [8, 10, 16, 20, 3] (K⁻¹ of the pixel centre, to world, normalised).
"""

import io
import os
import struct
import sys

import crc32c
import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from PIL import Image

W, H, CAMERAS = 20, 16, 10


def example_class():
    f = descriptor_pb2.FileDescriptorProto(name="example.proto", package="tensorflow", syntax="proto3")
    T = descriptor_pb2.FieldDescriptorProto

    def message(name, *fields):
        m = f.message_type.add(name=name)
        for fname, number, ftype, label, type_name, packed, oneof in fields:
            fd = m.field.add(name=fname, number=number, type=ftype, label=label)
            if type_name:
                fd.type_name = type_name
            if packed:
                fd.options.packed = True
            if oneof is not None:
                fd.oneof_index = oneof
        return m

    rep, opt = T.LABEL_REPEATED, T.LABEL_OPTIONAL
    message("BytesList", ("value", 1, T.TYPE_BYTES, rep, None, False, None))
    message("FloatList", ("value", 1, T.TYPE_FLOAT, rep, None, True, None))
    message("Int64List", ("value", 1, T.TYPE_INT64, rep, None, True, None))
    feat = message("Feature",
                   ("bytes_list", 1, T.TYPE_MESSAGE, opt, ".tensorflow.BytesList", False, 0),
                   ("float_list", 2, T.TYPE_MESSAGE, opt, ".tensorflow.FloatList", False, 0),
                   ("int64_list", 3, T.TYPE_MESSAGE, opt, ".tensorflow.Int64List", False, 0))
    feat.oneof_decl.add(name="kind")
    feats = message("Features", ("feature", 1, T.TYPE_MESSAGE, rep, ".tensorflow.Features.FeatureEntry", False, None))
    entry = feats.nested_type.add(name="FeatureEntry")
    entry.options.map_entry = True
    entry.field.add(name="key", number=1, type=T.TYPE_STRING, label=opt)
    entry.field.add(name="value", number=2, type=T.TYPE_MESSAGE, label=opt, type_name=".tensorflow.Feature")
    message("Example", ("features", 1, T.TYPE_MESSAGE, opt, ".tensorflow.Features", False, None))
    pool = descriptor_pool.DescriptorPool()
    pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName("tensorflow.Example"))


def masked(data):
    c = crc32c.crc32c(data)
    return (((c >> 15) | (c << 17)) + 0xA282EAD8) & 0xFFFFFFFF


def record(payload):
    length = struct.pack("<Q", len(payload))
    return length + struct.pack("<I", masked(length)) + payload + struct.pack("<I", masked(payload))


def png(array, mode):
    buf = io.BytesIO()
    Image.fromarray(array, mode).save(buf, format="PNG")
    return buf.getvalue()


def main():
    out = sys.argv[1]
    os.makedirs(out, exist_ok=True)
    Example = example_class()
    rng = np.random.default_rng(11)
    shards = [("msn-train.tfrecord-00000-of-00002", 3), ("msn-train.tfrecord-00001-of-00002", 2),
              ("msn-val.tfrecord-00000-of-00001", 1), ("msn-test.tfrecord-00000-of-00001", 2)]
    images, masks, positions, rays = [], [], [], []
    f = 0.035 / 0.032 * W
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    pixels = np.stack([u, v, np.ones_like(u)], -1)
    for name, count in shards:
        with open(os.path.join(out, name), "wb") as fh:
            for _ in range(count):
                ex = Example()
                feats = ex.features.feature
                feats["scene_name"].bytes_list.value.append(b"scene_%d" % rng.integers(1 << 30))
                imgs, ms, ps, rs = [], [], [], []
                for k in range(CAMERAS):
                    p = f"cameras/camera_{k}/"
                    a = rng.uniform(0, 2 * np.pi)
                    r = rng.uniform(8, 12)
                    pos = np.array([r * np.cos(a), r * np.sin(a), rng.uniform(1, 6)])
                    fwd = -pos / np.linalg.norm(pos)
                    right = np.cross(fwd, [0, 0, 1.0])
                    right /= np.linalg.norm(right)
                    down = np.cross(fwd, right)
                    c2w = np.stack([right, down, fwd], 1)
                    R = c2w.T
                    t = -R @ pos
                    color = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
                    inst = rng.integers(0, 7, (H, W), dtype=np.uint8)
                    feats[p + "color_image"].bytes_list.value.append(png(color, "RGB"))
                    feats[p + "instance_image"].bytes_list.value.append(png(inst, "L"))
                    feats[p + "category_image"].bytes_list.value.append(png(inst // 2, "L"))
                    depth = rng.uniform(5, 15, (H, W)).astype(np.float32)
                    feats[p + "depth_image"].bytes_list.value.append(
                        png(depth.view(np.uint8).reshape(H, W, 4), "RGBA"))
                    feats[p + "intrinsics/K"].float_list.value.extend(K.astype(np.float32).ravel())
                    feats[p + "extrinsics/R"].float_list.value.extend(R.astype(np.float32).ravel())
                    feats[p + "extrinsics/t"].float_list.value.extend(t.astype(np.float32).ravel())
                    feats[p + "intrinsics/image_width"].int64_list.value.append(W)
                    d = pixels @ np.linalg.inv(K).T
                    d /= np.linalg.norm(d, axis=-1, keepdims=True)
                    d = d @ c2w.T
                    imgs.append(color)
                    ms.append(np.clip(inst, 1, 34) - 1)
                    ps.append(pos)
                    rs.append(d / np.linalg.norm(d, axis=-1, keepdims=True))
                images.append(imgs)
                masks.append(ms)
                positions.append(ps)
                rays.append(rs)
                fh.write(record(ex.SerializeToString()))
    np.save(os.path.join(out, "expected_images.npy"), np.array(images, np.uint8))
    np.save(os.path.join(out, "expected_masks.npy"), np.array(masks, np.uint8))
    np.save(os.path.join(out, "expected_positions.npy"), np.array(positions))
    np.save(os.path.join(out, "expected_rays.npy"), np.array(rays, np.float32))


if __name__ == "__main__":
    main()
