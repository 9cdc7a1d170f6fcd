"""GLB scenes (binary glTF 2.0), streamed a fragment at a time: each fragment a named node in its
colour, at full resolution (a fragment thinned at load is read again), points for a cloud."""
from __future__ import annotations

import colorsys
import io
import json
import shutil
import struct
import tempfile
import warnings

import numpy as np

from .fragment import Fragment, is_cloud
from .load import load_original


def colour(i: int) -> tuple[int, int, int, int]:
    """Well separated colours: golden-angle hues (RGBA, 0-255)."""
    r, g, b = colorsys.hsv_to_rgb((i * 0.618033988749895) % 1.0, 0.55, 0.9)
    return int(r * 255), int(g * 255), int(b * 255), 255


def full_resolution(fragment: Fragment) -> Fragment:
    """The fragment as its file holds it: read again where it was thinned at load, else itself
    (`io.load_original`)."""
    with warnings.catch_warnings():  # what cleaning warns of was said when it was loaded
        warnings.simplefilter("ignore")
        return load_original(fragment)


# --- assembly.glb, written a fragment at a time -------------------------------------------

GLB_MAGIC, GLB_JSON, GLB_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942
GL_FLOAT, GL_UNSIGNED_BYTE, GL_UNSIGNED_INT = 5126, 5121, 5125
GL_ARRAY_BUFFER, GL_ELEMENT_ARRAY_BUFFER = 34962, 34963
GL_POINTS, GL_TRIANGLES = 0, 4


def _append_accessor(doc: dict, binary, array: np.ndarray, component: int, kind: str, target: int,
                     normalized: bool = False, bounds: bool = False) -> int:
    """Append an array to the binary chunk as one buffer view and accessor of `doc`; its index.

    Parameters
    ----------
    array : (N, k) or (N,) float32, uint8 or uint32, written as it is (every item a multiple
        of 4 bytes, so views stay aligned)
    """
    array = np.ascontiguousarray(array)
    offset = binary.tell()
    binary.write(memoryview(array).cast("B"))
    doc["bufferViews"].append({"buffer": 0, "byteOffset": offset, "byteLength": array.nbytes, "target": target})
    accessor = {"bufferView": len(doc["bufferViews"]) - 1, "componentType": component,
                "count": int(array.size if kind == "SCALAR" else len(array)), "type": kind}
    if normalized:
        accessor["normalized"] = True
    if bounds:
        accessor["min"], accessor["max"] = array.min(0).tolist(), array.max(0).tolist()
    doc["accessors"].append(accessor)
    return len(doc["accessors"]) - 1


def _glb_primitive(doc: dict, binary, fragment: Fragment, rgba) -> dict:
    """A glTF primitive of a fragment in one colour: triangles with a material, or coloured
    points for a cloud (glTF has no face colours; per-face colours would split every vertex)."""
    position = _append_accessor(doc, binary, fragment.vertices.astype(np.float32), GL_FLOAT, "VEC3",
                                GL_ARRAY_BUFFER, bounds=True)
    if is_cloud(fragment):
        colours = np.tile(np.asarray(rgba, np.uint8), (len(fragment.vertices), 1))
        return {"attributes": {"POSITION": position, "COLOR_0": _append_accessor(
            doc, binary, colours, GL_UNSIGNED_BYTE, "VEC4", GL_ARRAY_BUFFER, normalized=True)}, "mode": GL_POINTS}
    doc["materials"].append({"pbrMetallicRoughness": {"baseColorFactor": [c / 255 for c in rgba],
                                                      "metallicFactor": 0.0, "roughnessFactor": 0.8}})
    indices = _append_accessor(doc, binary, fragment.faces.astype(np.uint32).ravel(), GL_UNSIGNED_INT, "SCALAR",
                               GL_ELEMENT_ARRAY_BUFFER)
    return {"attributes": {"POSITION": position}, "indices": indices, "material": len(doc["materials"]) - 1,
            "mode": GL_TRIANGLES}


def write_glb(fh, items, on_faces=None, status=None) -> None:
    """Write a GLB scene of fragments, one named node and mesh each, at full resolution.

    Each fragment is read (`full_resolution`), appended to a temporary binary chunk and
    freed before the next: only one original mesh is in memory at a time, and the file is
    never held whole.

    Parameters
    ----------
    fh : binary file open for writing
    items : iterable of (Fragment, rgba (4 ints 0-255), transform (4, 4))
    on_faces : callable(int), optional
        Told the faces (points, for a cloud) of each fragment once written (a progress bar).
    status : callable(str), optional
        Told the fragment being read (a progress bar's postfix).
    """
    doc = {"asset": {"version": "2.0", "generator": "relicgpu"}, "scene": 0, "scenes": [{"nodes": []}],
           "nodes": [], "meshes": [], "materials": [], "accessors": [], "bufferViews": []}
    with tempfile.TemporaryFile() as binary:
        for fragment, rgba, transform in items:
            if status is not None:
                status(fragment.name)
            full = full_resolution(fragment)
            doc["meshes"].append({"name": fragment.name, "primitives": [_glb_primitive(doc, binary, full, rgba)]})
            matrix = np.asarray(transform, np.float64).T.ravel().tolist()  # glTF: column-major
            doc["nodes"].append({"name": fragment.name, "mesh": len(doc["meshes"]) - 1, "matrix": matrix})
            doc["scenes"][0]["nodes"].append(len(doc["nodes"]) - 1)
            if on_faces is not None:
                on_faces(len(full.faces) or len(full.vertices))
            del full
        size = binary.tell()
        if size:
            doc["buffers"] = [{"byteLength": size}]
        text = json.dumps({k: v for k, v in doc.items() if v != []}, separators=(",", ":")).encode()
        text += b" " * (-len(text) % 4)
        fh.write(struct.pack("<III", GLB_MAGIC, 2, 12 + 8 + len(text) + (8 + size if size else 0)))
        fh.write(struct.pack("<II", len(text), GLB_JSON) + text)
        if size:
            fh.write(struct.pack("<II", size, GLB_BIN))
            binary.seek(0)
            shutil.copyfileobj(binary, fh, 1 << 22)


def scene_glb(items) -> bytes:
    """A GLB scene of (fragment, rgba, 4x4 transform) items, one named node each, at full resolution
    (`write_glb` into memory: for small scenes such as a matched pair)."""
    buf = io.BytesIO()
    write_glb(buf, items)
    return buf.getvalue()


def full_faces(fragment: Fragment) -> int:
    """Faces of the fragment as written (its file's, where thinned at load); points for a cloud."""
    return fragment.thinned_from or len(fragment.faces) or len(fragment.vertices)
