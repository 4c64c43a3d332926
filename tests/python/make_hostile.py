"""Writes hostile and broken inputs for osrt's readers, independently of osrt, for
tests/hostile.rs: each case is a valid dataset made by this folder's other writers
(make_obsurf.py, make_kubric.py) or by `osrt data generate` (given as BASE_PARQUET), with
one thing broken the way a hostile or careless writer would break it.

    python3 make_hostile.py OUT BASE_PARQUET

OUT/<case>/ holds the input (`src/`) and `case.json`: the command to run on it
("import clevr3d", "import msn-hard" or "inspect"), what must happen ("error" with the
file the message must name, or "ok": the import succeeds and trains), and what was
broken. Bombs are built from streams of zeros (1 GiB inflated, a few MB on disk).
"""

import json
import os
import shutil
import struct
import subprocess
import sys
import zipfile
import zlib

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
GIB = 1 << 30


def npy_header(descr, shape):
    """A version-1 .npy header for `descr` and `shape` (a tuple, or any text)."""
    shape_text = shape if isinstance(shape, str) else repr(tuple(shape))
    header = "{'descr': '%s', 'fortran_order': False, 'shape': %s, }" % (descr, shape_text)
    header += " " * ((64 - (10 + len(header) + 1) % 64) % 64) + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode("latin-1")


def npy_bytes(array):
    return npy_header(array.dtype.str, array.shape) + np.ascontiguousarray(array).tobytes()


def rewrite_npz(path, replace=None, add=None, zeros_after=None):
    """Rewrites the .npz archive at `path`: entries in `replace` (name -> bytes) swapped,
    `add` (name -> bytes) appended, and for `zeros_after` = (name, header bytes) an entry
    of that header followed by 1 GiB of zeros, streamed (never held in memory)."""
    with zipfile.ZipFile(path) as z:
        entries = [(n, z.read(n)) for n in z.namelist()]
    replace = replace or {}
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as z:
        for name, data in entries:
            if zeros_after and name == zeros_after[0]:
                continue
            z.writestr(name, replace.get(name, data))
        for name, data in (add or {}).items():
            z.writestr(name, data)
        if zeros_after:
            name, header = zeros_after
            with z.open(name, "w", force_zip64=True) as f:
                f.write(header)
                block = bytes(1 << 20)
                for _ in range(GIB >> 20):
                    f.write(block)


def png_chunk(kind, data):
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_bomb(width, height):
    """A PNG whose header announces width x height RGB pixels; its data holds 16 rows."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    c = zlib.compressobj(9)
    row = bytes(1 + 3 * width)
    idat = b"".join(c.compress(row) for _ in range(16)) + c.flush()
    return (b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", idat)
            + png_chunk(b"IEND", b""))


def png_of(array, mode):
    import io
    from PIL import Image
    buf = io.BytesIO()
    Image.fromarray(array, mode).save(buf, format="PNG")
    return buf.getvalue()


# --- TFRecord framing (as make_kubric.py writes it) -------------------------------------

def masked_crc(data):
    import crc32c
    c = crc32c.crc32c(data)
    return (((c >> 15) | (c << 17)) + 0xA282EAD8) & 0xFFFFFFFF


def records(path):
    """The payloads of a TFRecord file."""
    out, data, at = [], open(path, "rb").read(), 0
    while at < len(data):
        (n,) = struct.unpack("<Q", data[at:at + 8])
        out.append(data[at + 12:at + 12 + n])
        at += 16 + n
    return out


def frame(payload, length=None):
    length = struct.pack("<Q", len(payload) if length is None else length)
    return (length + struct.pack("<I", masked_crc(length)) + payload
            + struct.pack("<I", masked_crc(payload)))


def write_records(path, payloads):
    with open(path, "wb") as f:
        for p in payloads:
            f.write(frame(p))


def example_class():
    sys.path.insert(0, HERE)
    import make_kubric
    return make_kubric.example_class()


# --- the cases --------------------------------------------------------------------------

class Cases:
    def __init__(self, out, base_obsurf, base_kubric, base_parquet):
        self.out = out
        self.bases = {"import clevr3d": base_obsurf, "import msn-hard": base_kubric,
                      "inspect": base_parquet}
        self.names = []

    def case(self, name, command, expect, names, why):
        """A fresh copy of the base of `command` as OUT/name/src; returns its path."""
        root = os.path.join(self.out, name)
        src = os.path.join(root, "src")
        shutil.copytree(self.bases[command], src)
        with open(os.path.join(root, "case.json"), "w") as f:
            json.dump({"command": command, "expect": expect, "names": names, "why": why}, f)
        self.names.append(name)
        return src


def obsurf_cases(c):
    meta = lambda src: os.path.join(src, "metadata.npz")
    cmd = "import clevr3d"

    src = c.case("npz-bomb-unused-entry", cmd, "ok", "",
                 "metadata.npz holds an extra entry of 1 GiB of zeros the importer never needs")
    rewrite_npz(meta(src), zeros_after=("depths.npy", npy_header("<f8", (GIB // 8,))))

    src = c.case("npz-entry-longer-than-its-header", cmd, "error", "camera_pos.npy",
                 "camera_pos announces [2, 3, 3] and inflates to 1 GiB")
    rewrite_npz(meta(src), zeros_after=("camera_pos.npy", npy_header("<f8", (2, 3, 3))))

    src = c.case("npz-entry-too-big", cmd, "error", "shape.npy",
                 "shape announces 1 GiB of values (and holds them, as zeros)")
    rewrite_npz(meta(src), zeros_after=("shape.npy", npy_header("<f8", (GIB // 8,))))

    src = c.case("npz-shape-overflows", cmd, "error", "camera_pos.npy",
                 "camera_pos announces 2^64 elements")
    rewrite_npz(meta(src), replace={"camera_pos.npy": npy_header("<f8", (1 << 32, 1 << 32, 3))})

    for name, descr in [("npy-descr-bare-order", "<"), ("npy-descr-empty", ""),
                        ("npy-descr-non-ascii", "\u00e98"), ("npy-descr-U0", "<U0")]:
        src = c.case(name, cmd, "error", "shape.npy", f"shape has dtype {descr!r}")
        rewrite_npz(meta(src), replace={"shape.npy": npy_header(descr, (2, 8)) + bytes(128)})

    src = c.case("npy-data-shorter-than-shape", cmd, "error", "camera_pos.npy",
                 "camera_pos announces [2, 3, 3] and holds 10 values")
    rewrite_npz(meta(src), replace={
        "camera_pos.npy": npy_header("<f8", (2, 3, 3)) + np.zeros(10).tobytes()})

    src = c.case("npy-header-length-past-the-end", cmd, "error", "camera_pos.npy",
                 "camera_pos's header length field says 65535 bytes; 40 follow")
    rewrite_npz(meta(src), replace={
        "camera_pos.npy": b"\x93NUMPY\x01\x00\xff\xff" + b"{'descr': '<f8', 'shape': (2,)}"})

    src = c.case("npz-truncated", cmd, "error", "metadata.npz", "metadata.npz cut in half")
    data = open(meta(src), "rb").read()
    open(meta(src), "wb").write(data[: len(data) // 2])

    src = c.case("npz-not-a-zip", cmd, "error", "metadata.npz", "metadata.npz is noise")
    open(meta(src), "wb").write(np.random.default_rng(1).bytes(4096))

    src = c.case("png-bomb", cmd, "error", "img_0_0.png",
                 "img_0_0.png announces 100000 x 100000 pixels")
    open(os.path.join(src, "images/img_0_0.png"), "wb").write(png_bomb(100_000, 100_000))

    src = c.case("png-truncated", cmd, "error", "img_1_2.png", "img_1_2.png cut to 60 bytes")
    path = os.path.join(src, "images/img_1_2.png")
    data = open(path, "rb").read()
    open(path, "wb").write(data[:60])

    src = c.case("odd-sized-view", cmd, "error", "img_1_1.png",
                 "img_1_1.png (and its mask) is 16 x 12, the others 32 x 24")
    rng = np.random.default_rng(2)
    from PIL import Image
    Image.fromarray(rng.integers(0, 256, (12, 16, 3), dtype=np.uint8), "RGB").save(
        os.path.join(src, "images/img_1_1.png"))
    Image.fromarray(rng.integers(0, 2, (12, 16), dtype=np.uint8), "L").save(
        os.path.join(src, "masks/masks_1_1.png"))

    src = c.case("mask-of-another-size", cmd, "error", "masks_0_2.png",
                 "masks_0_2.png is 8 x 8 beside a 32 x 24 image")
    Image.fromarray(np.zeros((8, 8), np.uint8), "L").save(
        os.path.join(src, "masks/masks_0_2.png"))


def kubric_cases(c):
    cmd = "import msn-hard"
    shard = "msn-train.tfrecord-00000-of-00002"
    Example = example_class()

    def edit_example(src, fn):
        path = os.path.join(src, shard)
        payloads = records(path)
        ex = Example()
        ex.ParseFromString(payloads[1])
        fn(ex.features.feature)
        payloads[1] = ex.SerializeToString()
        write_records(path, payloads)

    src = c.case("tfrecord-length-near-2^64", cmd, "error", shard,
                 "record 3's length is 2^64 - 1, with a valid length checksum")
    with open(os.path.join(src, shard), "ab") as f:
        f.write(frame(b"tail", length=(1 << 64) - 1))

    src = c.case("tfrecord-length-past-the-end", cmd, "error", shard,
                 "record 3 announces 1 GiB; the file ends after 4 bytes")
    with open(os.path.join(src, shard), "ab") as f:
        f.write(frame(b"tail", length=GIB))

    src = c.case("tfrecord-payload-checksum", cmd, "error", shard,
                 "one byte of record 0's payload flipped")
    path = os.path.join(src, shard)
    data = bytearray(open(path, "rb").read())
    data[100] ^= 0x40
    open(path, "wb").write(bytes(data))

    src = c.case("tfrecord-truncated", cmd, "error", shard, "the shard cut 7 bytes short")
    path = os.path.join(src, shard)
    data = open(path, "rb").read()
    open(path, "wb").write(data[:-7])

    src = c.case("example-not-a-protobuf", cmd, "error", shard,
                 "record 1's payload is 0xff bytes, with valid checksums")
    path = os.path.join(src, shard)
    payloads = records(path)
    payloads[1] = b"\xff" * 64
    write_records(path, payloads)

    src = c.case("example-length-past-the-end", cmd, "error", shard,
                 "record 1 is one field announcing 2^40 bytes")
    payloads = records(os.path.join(src, shard))
    payloads[1] = b"\x0a\x80\x80\x80\x80\x80\x20" + b"\0" * 16
    write_records(os.path.join(src, shard), payloads)

    src = c.case("example-png-bomb", cmd, "error", shard,
                 "camera 3's colour image announces 100000 x 100000 pixels")
    bomb = png_bomb(100_000, 100_000)

    def put_bomb(f):
        f["cameras/camera_3/color_image"].bytes_list.value[0] = bomb
    edit_example(src, put_bomb)

    src = c.case("example-odd-sized-camera", cmd, "error", shard,
                 "camera 2 of record 1 is 10 x 8, the others 20 x 16")
    rng = np.random.default_rng(3)

    def shrink(f):
        p = "cameras/camera_2/"
        f[p + "color_image"].bytes_list.value[0] = png_of(
            rng.integers(0, 256, (8, 10, 3), dtype=np.uint8), "RGB")
        f[p + "instance_image"].bytes_list.value[0] = png_of(np.zeros((8, 10), np.uint8), "L")
    edit_example(src, shrink)

    src = c.case("example-intrinsics-short", cmd, "error", shard,
                 "camera 0 of record 1 has 8 intrinsics values instead of 9")

    def short_k(f):
        del f["cameras/camera_0/intrinsics/K"].float_list.value[-1]
    edit_example(src, short_k)


def parquet_cases(c):
    cmd = "inspect"
    part = "train/part-00000.parquet"

    def edit(src, fn):
        path = os.path.join(src, part)
        data = bytearray(open(path, "rb").read())
        open(path, "wb").write(bytes(fn(data)))

    src = c.case("parquet-footer-length-huge", cmd, "error", "part-00000.parquet",
                 "the footer's length field says 2^31 - 1 bytes")
    edit(src, lambda d: d[:-8] + struct.pack("<I", (1 << 31) - 1) + b"PAR1")

    src = c.case("parquet-footer-noise", cmd, "error", "part-00000.parquet",
                 "the footer's thrift bytes replaced with noise")

    def noise(d):
        (n,) = struct.unpack("<I", d[-8:-4])
        d[-8 - n:-8] = np.random.default_rng(4).bytes(n)
        return d
    edit(src, noise)

    src = c.case("parquet-truncated", cmd, "error", "part-00000.parquet",
                 "the part file cut to its first 1000 bytes")
    edit(src, lambda d: d[:1000])

    src = c.case("parquet-foreign-schema", cmd, "error", "part-00000.parquet",
                 "the part file replaced by pyarrow's table of another schema")
    import pyarrow as pa
    import pyarrow.parquet as pq
    pq.write_table(pa.table({"scene_id": pa.array(["a", "b"]), "views": pa.array([1.5, 2.5])}),
                   os.path.join(src, part))


def main():
    out, base_parquet = sys.argv[1], sys.argv[2]
    os.makedirs(out, exist_ok=True)
    bases = os.path.join(out, "_bases")
    obsurf, kubric = os.path.join(bases, "obsurf"), os.path.join(bases, "kubric")
    subprocess.run([sys.executable, os.path.join(HERE, "make_obsurf.py"), obsurf, "8"],
                   check=True)
    subprocess.run([sys.executable, os.path.join(HERE, "make_kubric.py"), kubric], check=True)
    for f in os.listdir(obsurf):
        if f.startswith("expected"):
            os.remove(os.path.join(obsurf, f))
    for f in os.listdir(kubric):
        if f.startswith("expected"):
            os.remove(os.path.join(kubric, f))
    c = Cases(out, obsurf, kubric, base_parquet)
    obsurf_cases(c)
    kubric_cases(c)
    parquet_cases(c)
    print(json.dumps(c.names))


if __name__ == "__main__":
    main()
