"""`glb`: glTF 2.0 binary with the Khronos extension ``KHR_gaussian_splatting`` (kernel
``ellipse``): one mesh primitive of mode POINTS whose attributes are the Gaussians.

The container (glTF 2.0 §4.4): a 12-byte header (magic "glTF", version 2, total length), a JSON
chunk (padded with spaces to 4 bytes) and a BIN chunk (padded with zeros), all little-endian. The
JSON's mesh primitive has ``extensions.KHR_gaussian_splatting = {kernel: "ellipse", colorSpace:
"srgb_rec709_display", sortingMethod: "cameraDistance", projection: "perspective"}`` (radfield's
colours are those of the photos it was trained on, display-referred sRGB) and, one tightly packed
bufferView each, the attributes (float32 unless said):

- ``POSITION`` VEC3 (with min and max);
- ``KHR_gaussian_splatting:ROTATION`` VEC4, the unit quaternion in glTF's x y z w order;
- ``KHR_gaussian_splatting:SCALE`` VEC3, linear σ = exp(log σ);
- ``KHR_gaussian_splatting:OPACITY`` SCALAR, sigmoid(opacity logit);
- ``KHR_gaussian_splatting:SH_DEGREE_0_COEF_0`` VEC3 and ``SH_DEGREE_l_COEF_n`` VEC3 (n = 0 .. 2l,
  m = −l .. l, the 3DGS order) for each band l ≤ the model's degree; r g b in each;
- ``COLOR_0`` VEC4 unsigned byte normalised, the point-cloud fallback the extension suggests:
  clamp(0.5 + C0·f_dc) decoded from sRGB to linear, and the opacity.

Axes: glTF's LUF (+y up, +z forward), the 3DGS PLY's frame (RDF) turned half a turn about z
(base.py), as splat-transform writes its GLB. Read: the same, and also the accessor types the
extension allows (normalised signed byte/short rotations; unsigned byte/short scales; normalised
unsigned byte/short opacities), strided bufferViews, and the node transforms of the default scene
(translation, rotation and a uniform positive scale applied to the Gaussians; anything else, sparse
accessors, external buffers or another kernel: refused in one line).
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import torch

from radfield.core.kinds.gaussian import Gaussians
from radfield.core.splat.sh import C0
from radfield.errors import RadfieldError
from radfield.model_formats.base import (HALF_TURN_Z, ModelFormat, checked, cpu, gaussians, opacity_logit, suffix_is,
                                         turned, unit_quats)
from radfield.util.atomic import atomic_write_bytes

EXTENSION = "KHR_gaussian_splatting"
MAGIC, JSON_CHUNK, BIN_CHUNK = b"glTF", 0x4E4F534A, 0x004E4942
FLOAT, UBYTE, BYTE, USHORT, SHORT, UINT = 5126, 5121, 5120, 5123, 5122, 5125
DTYPES = {FLOAT: "<f4", UBYTE: "u1", BYTE: "i1", USHORT: "<u2", SHORT: "<i2", UINT: "<u4"}
WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
ARRAY_BUFFER = 34962


def _pad(data: bytes, fill: bytes) -> bytes:
    return data + fill * (-len(data) % 4)


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def glb_bytes(g: Gaussians) -> bytes:
    """The GLB file of `g` (see the module docstring)."""
    g = turned(g, HALF_TURN_Z)
    means = cpu(g.means)
    sh = cpu(g.sh)
    opacity = (1 / (1 + np.exp(-cpu(g.opacities).astype(np.float64))))
    rgb = _srgb_to_linear(np.clip(0.5 + C0 * sh[:, 0, :].astype(np.float64), 0, 1))
    colour = np.round(np.concatenate([rgb, opacity[:, None]], 1) * 255).astype(np.uint8)
    attributes = [("POSITION", means, FLOAT, "VEC3"), ("COLOR_0", colour, UBYTE, "VEC4"),
                  (f"{EXTENSION}:ROTATION", unit_quats(g)[:, [1, 2, 3, 0]].astype(np.float32), FLOAT, "VEC4"),
                  (f"{EXTENSION}:SCALE", np.exp(cpu(g.log_scales).astype(np.float64)).astype(np.float32), FLOAT, "VEC3"),
                  (f"{EXTENSION}:OPACITY", opacity.astype(np.float32), FLOAT, "SCALAR")]
    k = 0
    for degree in range(g.sh_degree + 1):
        for n in range(2 * degree + 1):
            attributes.append((f"{EXTENSION}:SH_DEGREE_{degree}_COEF_{n}", sh[:, k, :], FLOAT, "VEC3"))
            k += 1
    blob, views, accessors, names = b"", [], [], {}
    for i, (name, array, component, kind) in enumerate(attributes):
        data = np.ascontiguousarray(array, DTYPES[component]).tobytes()
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data), "target": ARRAY_BUFFER})
        accessor = {"bufferView": i, "componentType": component, "count": len(g), "type": kind}
        if component != FLOAT:
            accessor["normalized"] = True
        if name == "POSITION":
            accessor["min"], accessor["max"] = means.min(0).tolist(), means.max(0).tolist()
        accessors.append(accessor)
        names[name] = i
        blob += _pad(data, b"\0")
    document = {
        "asset": {"version": "2.0", "generator": "radfield"},
        "extensionsUsed": [EXTENSION],
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": names, "mode": 0, "extensions": {EXTENSION: {
            "kernel": "ellipse", "colorSpace": "srgb_rec709_display", "sortingMethod": "cameraDistance",
            "projection": "perspective"}}}]}],
        "buffers": [{"byteLength": len(blob)}], "bufferViews": views, "accessors": accessors,
    }
    text = _pad(json.dumps(document, separators=(",", ":")).encode(), b" ")
    total = 12 + 8 + len(text) + 8 + len(blob)
    return (MAGIC + struct.pack("<II", 2, total) + struct.pack("<II", len(text), JSON_CHUNK) + text
            + struct.pack("<II", len(blob), BIN_CHUNK) + blob)


class _Damaged(Exception):
    pass


def _chunks(raw: bytes) -> tuple[dict, bytes]:
    if len(raw) < 20 or raw[:4] != MAGIC:
        raise _Damaged("no 'glTF' magic: not a GLB file")
    version, total = struct.unpack_from("<II", raw, 4)
    if version != 2:
        raise _Damaged(f"glTF container version {version}, not 2")
    if total != len(raw):
        raise _Damaged(f"the header says {total} bytes, the file has {len(raw)}")
    offset, found = 12, {}
    while offset < total:
        if offset + 8 > total:
            raise _Damaged("a truncated chunk header")
        length, kind = struct.unpack_from("<II", raw, offset)
        if offset + 8 + length > total:
            raise _Damaged("a chunk runs past the end of the file")
        found.setdefault(kind, raw[offset + 8: offset + 8 + length])
        offset += 8 + length
    if JSON_CHUNK not in found:
        raise _Damaged("no JSON chunk")
    try:
        document = json.loads(found[JSON_CHUNK].decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as error:
        raise _Damaged(f"its JSON does not parse ({error})") from None
    return document, found.get(BIN_CHUNK, b"")


def _accessor(document: dict, binary: bytes, index: int) -> np.ndarray:
    """(count, width) float64 values of accessor `index` (normalised integers mapped as glTF says)."""
    accessor = document["accessors"][index]
    if "sparse" in accessor:
        raise _Damaged("sparse accessors are not read")
    component, width, count = accessor["componentType"], WIDTHS[accessor["type"]], accessor["count"]
    dtype = np.dtype(DTYPES[component])
    view = document["bufferViews"][accessor["bufferView"]]
    if document["buffers"][view["buffer"]].get("uri") is not None:
        raise _Damaged("external buffers (a 'uri') are not read: only the GLB's own BIN chunk")
    stride = view.get("byteStride") or dtype.itemsize * width
    start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    end = start + stride * (count - 1) + dtype.itemsize * width if count else start
    if end > view.get("byteOffset", 0) + view["byteLength"] or end > len(binary):
        raise _Damaged(f"accessor {index} runs past its bufferView or the BIN chunk")
    values = np.ndarray((count, width), dtype, binary, start, (stride, dtype.itemsize)).astype(np.float64)
    if accessor.get("normalized"):
        values = np.maximum(values / float(np.iinfo(dtype).max), -1.0)
    return values


def _node_matrices(document: dict) -> list[tuple[int, np.ndarray]]:
    """(mesh index, 4 × 4 global matrix) of every node of the default scene (all root nodes when
    there is no scene) that holds a mesh."""
    nodes = document.get("nodes", [])
    scenes = document.get("scenes")
    if scenes:
        roots = scenes[document.get("scene", 0)].get("nodes", [])
    else:
        children = {c for node in nodes for c in node.get("children", [])}
        roots = [i for i in range(len(nodes)) if i not in children]
    out, stack = [], [(i, np.eye(4)) for i in roots]
    while stack:
        i, parent = stack.pop()
        node = nodes[i]
        if "matrix" in node:
            local = np.array(node["matrix"], np.float64).reshape(4, 4).T     # column-major
        else:
            t = np.array(node.get("translation", [0, 0, 0]), np.float64)
            x, y, z, w = node.get("rotation", [0, 0, 0, 1])
            r = cpu_rot(w, x, y, z)
            s = np.array(node.get("scale", [1, 1, 1]), np.float64)
            local = np.eye(4)
            local[:3, :3], local[:3, 3] = r * s[None, :], t
        world = parent @ local
        if "mesh" in node:
            out.append((node["mesh"], world))
        stack.extend((c, world) for c in node.get("children", []))
    if not out and document.get("meshes"):
        out = [(m, np.eye(4)) for m in range(len(document["meshes"]))]
    return out


def cpu_rot(w, x, y, z) -> np.ndarray:
    from radfield.core.geometry.rotations import quat_to_rotmat

    return quat_to_rotmat(torch.tensor([[w, x, y, z]], dtype=torch.float64))[0].numpy()


def _splats(document: dict, binary: bytes, attributes: dict, extension: dict) -> Gaussians:
    if extension.get("kernel") != "ellipse":
        raise _Damaged(f"kernel {extension.get('kernel')!r} (radfield reads the 'ellipse' kernel)")
    get = lambda name: _accessor(document, binary, attributes[f"{EXTENSION}:{name}"])
    for name in ("ROTATION", "SCALE", "OPACITY", "SH_DEGREE_0_COEF_0"):
        if f"{EXTENSION}:{name}" not in attributes:
            raise _Damaged(f"the splat primitive lacks {EXTENSION}:{name}")
    if "POSITION" not in attributes:
        raise _Damaged("the splat primitive lacks POSITION")
    means = _accessor(document, binary, attributes["POSITION"])
    sh = [get("SH_DEGREE_0_COEF_0")]
    for degree in (1, 2, 3):
        names = [f"SH_DEGREE_{degree}_COEF_{n}" for n in range(2 * degree + 1)]
        present = [f"{EXTENSION}:{name}" in attributes for name in names]
        if not any(present):
            break
        if not all(present):
            raise _Damaged(f"SH degree {degree} is partly defined")
        sh += [get(name) for name in names]
    opacity = get("OPACITY")[:, 0]
    if ((opacity < 0) | (opacity > 1)).any():
        raise _Damaged(f"an opacity outside [0, 1] at Gaussian {int(np.flatnonzero((opacity < 0) | (opacity > 1))[0])}")
    scale = get("SCALE")
    if (scale < 0).any():
        raise _Damaged(f"a negative scale at Gaussian {int(np.flatnonzero((scale < 0).any(1))[0])}")
    with np.errstate(divide="ignore"):
        log_scales = np.log(scale)
    q = get("ROTATION")
    return gaussians(means, log_scales, q[:, [3, 0, 1, 2]], np.stack(sh, 1), opacity_logit(opacity, 2.0**-24))


def _placed(g: Gaussians, matrix: np.ndarray) -> Gaussians:
    """`g` under a node's matrix: a rotation times a uniform positive scale, and a translation."""
    from radfield.core.geometry.rotations import quat_to_rotmat, rotmat_to_quat
    from radfield.core.splat.sh import rotate_sh

    if np.allclose(matrix, np.eye(4), atol=1e-12):
        return g
    m = matrix[:3, :3]
    lengths = np.linalg.norm(m, axis=0)
    s = float(lengths.mean())
    r = m / s if s > 0 else m
    if not (np.allclose(lengths, s, rtol=1e-4) and np.allclose(r.T @ r, np.eye(3), atol=1e-4)
            and np.linalg.det(r) > 0 and np.allclose(matrix[3], [0, 0, 0, 1])):
        raise _Damaged("a node transform that is not a rotation, a uniform positive scale and a translation")
    rot = torch.from_numpy(r)
    quats = rotmat_to_quat(rot[None] @ quat_to_rotmat(g.quats.double())).float()
    return Gaussians(means=torch.from_numpy(cpu(g.means) @ m.T.astype(np.float32) + matrix[:3, 3].astype(np.float32)),
                     log_scales=g.log_scales + float(np.log(s)), quats=quats, sh=rotate_sh(g.sh, rot),
                     opacities=g.opacities)


def read_glb(path: str | Path) -> Gaussians:
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise RadfieldError(f"{path}: cannot read ({error.strerror or error})") from None
    try:
        document, binary = _chunks(raw)
        parts = []
        for mesh, matrix in _node_matrices(document):
            for primitive in document["meshes"][mesh].get("primitives", []):
                extension = (primitive.get("extensions") or {}).get(EXTENSION)
                if extension is None:
                    continue
                if primitive.get("mode", 4) != 0:
                    raise _Damaged(f"a splat primitive of mode {primitive.get('mode', 4)}, not POINTS (0)")
                parts.append(_placed(_splats(document, binary, primitive["attributes"], extension), matrix))
    except _Damaged as error:
        raise RadfieldError(f"{path}: not a readable {EXTENSION} GLB ({error})") from None
    except (KeyError, IndexError, TypeError, ValueError, AttributeError) as error:
        raise RadfieldError(f"{path}: damaged GLB ({type(error).__name__}: {error})") from None
    if not parts:
        raise RadfieldError(f"{path}: no mesh primitive with the {EXTENSION} extension")
    degree = min(p.sh.shape[1] for p in parts)
    g = Gaussians(**{name: torch.cat([p.sh[:, :degree] if name == "sh" else getattr(p, name) for p in parts])
                     for name in ("means", "log_scales", "quats", "sh", "opacities")})
    return checked(turned(g, HALF_TURN_Z), path, "GLB")


def write_glb(g: Gaussians, path: Path) -> dict:
    data = glb_bytes(g)
    atomic_write_bytes(path, data)
    return {"gaussians": len(g), "bytes": len(data)}


FORMAT = ModelFormat(
    name="glb", suffixes=(".glb",),
    summary="glTF 2.0 binary with KHR_gaussian_splatting (three.js, Babylon.js, Cesium)",
    loses="nothing beyond float32 rounding: σ stored as exp(log σ), opacity as sigmoid(logit) (the "
          "opacity is kept to float32 precision, its logit less so where the opacity is near 0 or 1)",
    read=read_glb, write=write_glb, exact=True, recognises=suffix_is(".glb"))
