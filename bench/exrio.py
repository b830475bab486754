"""Read and write multi-layer OpenEXR images as dicts of HxWxC numpy arrays.

A file holds named layers (e.g. ``noisy``, ``ref``, ``albedo``, ``normal``, ``roughness``); each layer is
stored as EXR channels ``<layer>.<suffix>``. Suffixes follow the layer's meaning: ``R,G,B`` for colours,
``X,Y,Z`` for vectors, ``Y`` for a single channel. EXR sorts channels alphabetically on disk, so the
channel order of every layer is recorded in a header attribute (``srd_layers``) and restored on read.

Writes are atomic (temp name in the same directory + ``os.replace``), so an interrupted dataset build never
leaves a half-written frame behind under the final name. Any failure to read a file (truncated, corrupt,
missing channel) raises ``ExrError`` naming the file.
"""
import json
import os
import tempfile

import numpy as np
import OpenEXR

# Default channel suffixes by channel count; a layer may override them (normals use X,Y,Z).
DEFAULT_SUFFIXES = {1: ("Y",), 2: ("X", "Y"), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}
_LAYERS_ATTR = "srd_layers"


class ExrError(RuntimeError):
    """An EXR file could not be read or written; the message names the file."""


def write_exr(path, layers, suffixes=None, half=False, attributes=None):
    """Write ``layers`` (name -> HxW or HxWxC array) to one multi-channel EXR at ``path``, atomically.

    suffixes: optional dict layer -> tuple of channel suffixes (default from DEFAULT_SUFFIXES by C).
    half: True to store every layer as float16, or a collection of layer names stored as float16
        (the rest float32). Half halves disk use; it is exact enough for gBuffers but clips above 65504.
    attributes: optional dict of extra string header attributes (e.g. provenance).
    """
    suffixes = suffixes or {}
    half_layers = set(layers) if half is True else set(half or ())
    channels, order, shape = {}, {}, None
    for name, image in layers.items():
        image = np.asarray(image)
        image = image[..., None] if image.ndim == 2 else image
        if shape is None:
            shape = image.shape[:2]
        if image.shape[:2] != shape:
            raise ExrError(f"{path}: layer {name!r} is {image.shape[:2]}, expected {shape}")
        names = tuple(suffixes.get(name) or DEFAULT_SUFFIXES.get(image.shape[2], ()))
        if len(names) != image.shape[2]:
            names = tuple(str(i) for i in range(image.shape[2]))
        dtype = np.float16 if name in half_layers else np.float32
        for c, suffix in enumerate(names):
            channels[f"{name}.{suffix}"] = np.ascontiguousarray(image[..., c], dtype=dtype)
        order[name] = list(names)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              _LAYERS_ATTR: json.dumps(order)}
    for key, value in (attributes or {}).items():
        header[key] = str(value)
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp_", suffix=".exr", dir=directory)
    os.close(fd)
    try:
        with OpenEXR.File(header, channels) as f:
            f.write(tmp)
        umask = os.umask(0)  # mkstemp made the file private (0600): give it the mode any new file gets here
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except Exception as err:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise ExrError(f"{path}: could not write EXR ({err})") from err


def _suffix_order(suffixes):
    """Order for a layer's suffixes when the file carries no recorded order (foreign EXRs)."""
    for canon in (("R", "G", "B", "A"), ("X", "Y", "Z", "W")):
        if set(suffixes) <= set(canon):
            return [s for s in canon if s in suffixes]
    return sorted(suffixes)


def read_exr(path, layers=None, dtype=np.float32):
    """Read layers from the EXR at ``path`` as a dict name -> HxWxC array of ``dtype``.

    layers: names to read (None: all). Channels without a dot form a layer named ''.
    Raises ExrError naming the file if it is missing, truncated or lacks a requested layer.
    """
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            header = f.header()
            channels = {name: ch.pixels for name, ch in f.channels().items()}
    except Exception as err:
        raise ExrError(f"{path}: unreadable or corrupt EXR ({err})") from err
    grouped = {}
    for full in channels:
        layer, _, suffix = full.rpartition(".")
        grouped.setdefault(layer, []).append(suffix)
    recorded = json.loads(header.get(_LAYERS_ATTR, "{}"))
    wanted = list(grouped) if layers is None else list(layers)
    out = {}
    for layer in wanted:
        if layer not in grouped:
            raise ExrError(f"{path}: no layer {layer!r} (has {sorted(grouped)})")
        order = recorded.get(layer) or _suffix_order(grouped[layer])
        planes = [channels[f"{layer}.{s}" if layer else s] for s in order]
        out[layer] = np.stack(planes, axis=-1).astype(dtype, copy=False)
    return out


def exr_header(path):
    """(names of the layers stored in ``path``, (width, height)), from one read of its header alone.
    Raises ExrError if unreadable."""
    try:
        with OpenEXR.File(str(path), header_only=True) as f:
            header = f.header()
            names = [c.name for c in header["channels"]]
            (x0, y0), (x1, y1) = header["dataWindow"]
    except Exception as err:
        raise ExrError(f"{path}: unreadable or corrupt EXR ({err})") from err
    return sorted({n.rpartition(".")[0] for n in names}), (int(x1 - x0 + 1), int(y1 - y0 + 1))


def exr_layers(path):
    """Names of the layers stored in ``path`` (reads only the header). Raises ExrError if unreadable."""
    return exr_header(path)[0]


def is_valid_exr(path, layers=None):
    """True if ``path`` exists, decodes completely and holds every layer in ``layers``.

    Used by the resumable dataset build: decoding all pixels (not only the header) catches files
    truncated mid-write by an external copy or a full disk.
    """
    if not os.path.exists(path):
        return False
    try:
        read_exr(path, layers)
    except ExrError:
        return False
    return True
