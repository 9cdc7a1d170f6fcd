"""What an assembly writes: assembly.glb (every fragment placed, groups side by side) and
merged.stl (the placed fragments of a group united into one solid).

Fragments come in three kinds here:

- closed meshes: united with manifold3d;
- open meshes (scans with holes): each hole is capped (a fan from the centre of its
  boundary loop) so that it joins the union; one that still does not make a closed solid is
  added as an open surface, and the notes say that merged.stl is then not watertight;
- faceless point clouds (`relicgpu.cloud.points.CloudFragment`): points in assembly.glb; in
  merged.stl the surface each closes into (`triangulate.surface_of`, as a dense cloud is meshed for
  matching), or left out where it closes into none; a note says which.

A fragment thinned at load (`Fragment.thinned_from`) is written at full resolution: its
file is read again when it is written, one fragment at a time, so the thinned and the
original meshes are never all in memory together. Both files are streamed: assembly.glb's
binary chunk goes to a temporary file a fragment at a time (`relicgpu.io.glb.write_glb`), merged.stl is
written a set of fragments at a time (`write_merged`, numpy facets, no trimesh).

Pieces placed edge to edge leave the union two vertices at one position; one is moved a hair
(`separate_pinches`), since STL stores positions only and would read the edge as one of four faces.

Only fragments whose placed bounding boxes overlap are united (`overlap_sets`); the
others are written side by side, so merged.stl may hold several separate shells (a note
says so). A lone mesh goes in without manifold3d: as it is when it bounds a solid
(`is_closed`), else capped. Fragments whose union would take more memory than
UNION_MEMORY (about 5.9M faces in all) are written at full resolution as separate,
overlapping shells, and a note says that merged.stl is then not one watertight solid.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from ..cloud.triangulate import surface_of
from ..io.files import atomic_open, write_stl
from ..io.fragment import Fragment, FragmentError, is_cloud, unique_rows
from ..io.glb import colour, full_faces, full_resolution, scene_glb, write_glb
from ..progress import progress_bar


def _bbox(points: np.ndarray) -> np.ndarray:
    return np.stack([points.min(axis=0), points.max(axis=0)])


def _placed(pose, points: np.ndarray) -> np.ndarray:
    m = np.eye(4) if pose is None else np.asarray(pose, np.float64)
    return points @ m[:3, :3].T + m[:3, 3]


def group_layout(assembly, fragments: list[Fragment], gap: float = 0.1) -> dict[int, np.ndarray]:
    """A translation per group that sets the groups (an unplaced fragment is a group of its own)
    side by side along +x, in group order, `gap` times the largest group size apart."""
    boxes = {}
    for g, members in sorted(assembly.group_members().items()):
        pts = np.concatenate([_placed(assembly.poses[i], fragments[i].vertices) for i in members])
        boxes[g] = _bbox(pts)
    spacing = gap * max(float(np.linalg.norm(b[1] - b[0])) for b in boxes.values())
    out, x = {}, 0.0
    for g, box in boxes.items():
        shift = np.eye(4)
        shift[:3, 3] = [x - box[0, 0], -0.5 * (box[0, 1] + box[1, 1]), -0.5 * (box[0, 2] + box[1, 2])]
        out[g] = shift
        x += float(box[1, 0] - box[0, 0]) + spacing
    return out


def assembly_items(assembly, fragments: list[Fragment]):
    """The (fragment, rgba, transform) items of assembly.glb: one per fragment, own colour, its
    transform the fragment's pose followed by its group's translation from `group_layout`
    (groups side by side)."""
    layout = group_layout(assembly, fragments)
    return ((frag, colour(i), layout[assembly.groups[i]] @ (
        np.eye(4) if assembly.poses[i] is None else np.asarray(assembly.poses[i])))
        for i, frag in enumerate(fragments))


def assembly_glb(assembly, fragments: list[Fragment]) -> bytes:
    """assembly.glb in memory (see `assembly_items`; `write_outputs` streams it to disk)."""
    return scene_glb(assembly_items(assembly, fragments))


# --- the merged solid ---------------------------------------------------------------

def closed_solid(fragment: Fragment):
    """The fragment as a manifold3d solid, or None when it is not a closed 2-manifold
    (an open scan, a point cloud)."""
    import manifold3d as m3d

    if is_cloud(fragment):
        return None
    mesh = m3d.Mesh(vert_properties=np.asarray(fragment.vertices, np.float32),
                    tri_verts=np.asarray(fragment.faces, np.uint32))
    mesh.merge()
    solid = m3d.Manifold(mesh)
    if solid.status() != m3d.Error.NoError or solid.is_empty() or solid.volume() <= 0:
        return None
    return solid


def cap_holes(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Close each hole of a mesh with a fan from the centre of its boundary loop.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int

    Returns
    -------
    vertices : (V + H, 3), one centre added per hole
    faces : (F + B, 3), one cap face per boundary edge, turned to match its neighbour
    holes : int, H
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, np.int64)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    _, inverse, counts = unique_rows(np.sort(directed, axis=1))
    boundary = directed[counts[inverse] == 1]  # (B, 2) as the faces run
    del directed, inverse
    if len(boundary) == 0:
        return vertices, faces, 0
    used, local = np.unique(boundary, return_inverse=True)
    local = local.reshape(-1, 2)
    graph = coo_matrix((np.ones(len(local)), (local[:, 0], local[:, 1])), shape=(len(used), len(used)))
    holes, label = connected_components(graph, directed=False)
    centres = np.stack([np.bincount(label, weights=vertices[used, k], minlength=holes) for k in range(3)], 1)
    centres /= np.bincount(label, minlength=holes)[:, None]
    hole = label[local[:, 0]]
    caps = np.stack([boundary[:, 1], boundary[:, 0], len(vertices) + hole], axis=1)
    return np.vstack([vertices, centres]), np.vstack([f, caps]), int(holes)


def _solid_or_surface(frag: Fragment, notes: list[str]):
    """(manifold3d solid, None), or (None, open Fragment) when it cannot be closed; notes say so."""
    solid = closed_solid(frag)
    if solid is not None:
        return solid, None
    v, f, holes = cap_holes(frag.vertices, frag.faces)
    solid = closed_solid(Fragment(frag.name, v, f.astype(np.int32))) if holes else None
    if solid is not None:
        notes.append(f"{frag.name}: open mesh; {holes} hole(s) capped to make it a closed solid in merged.stl")
        return solid, None
    notes.append(_open_note(frag.name))
    return None, frag


def _open_note(name: str) -> str:
    return (f"{name}: open mesh that could not be closed; merged.stl holds it as an open surface, "
            "so merged.stl is not watertight")


def _shell(frag: Fragment, notes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """A mesh as a shell of its own, without manifold3d: as it is when it bounds a solid
    (`is_closed`), else with its holes capped when that closes it, else as an open surface;
    `notes` says which where it is not the first."""
    if is_closed(frag.vertices, frag.faces):
        return frag.vertices, frag.faces
    v, f, holes = cap_holes(frag.vertices, frag.faces)
    if holes and is_closed(v, f):
        notes.append(f"{frag.name}: open mesh; {holes} hole(s) capped to make it a closed solid in merged.stl")
        return v, f
    notes.append(_open_note(frag.name))
    return frag.vertices, frag.faces


def is_closed(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """A cheap test that a mesh bounds a solid as it is (no manifold3d, no copy the size of a
    Manifold): with vertices at equal positions welded, every edge is used once in each
    direction (closed, consistently oriented) and the signed volume is positive (outward).

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
    """
    if len(faces) == 0:
        return False
    _, weld, _ = unique_rows(np.ascontiguousarray(vertices, np.float64).view(np.int64))  # exact positions
    f = weld[faces]
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    _, _, once = unique_rows(directed)
    if (once != 1).any():
        return False
    _, _, twice = unique_rows(np.sort(directed, axis=1))
    del directed
    if (twice != 2).any():
        return False
    a, b, c = (np.asarray(vertices, np.float64)[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->", a, np.cross(b, c))) > 0


def overlap_sets(boxes: np.ndarray) -> list[list[int]]:
    """Sets of boxes that overlap, directly or through others (connected components).

    Parameters
    ----------
    boxes : (n, 2, 3) float, each [min corner, max corner]

    Returns
    -------
    list of lists of indices, in order of their lowest index
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(boxes)
    if n == 0:
        return []
    overlap = ((boxes[:, None, 0] <= boxes[None, :, 1]) & (boxes[None, :, 0] <= boxes[:, None, 1])).all(-1)
    _, label = connected_components(coo_matrix(overlap), directed=False)
    sets: dict[int, list[int]] = {}
    for i, lab in enumerate(label):
        sets.setdefault(int(lab), []).append(i)
    return list(sets.values())


# Placed boxes are widened by this fraction of each fragment's size before the overlap test:
# a thinned mesh's box lies a little inside its original's.
BOX_MARGIN = 0.05
# What a manifold3d union takes at its peak, per face of its inputs: 3.43 GiB over the rest for a
# 6.1M-face piece and a 5k-face one (manifold3d 3.5; both solids, the result and the boolean's
# temporaries). A set of fragments whose union would take more than UNION_MEMORY is not united:
# its meshes are written at full resolution as separate shells, and a note says so (the rest of
# `relicgpu assemble` stays under 0.5 GiB at that point: under 4 GiB in all).
UNION_BYTES_PER_FACE = 600
UNION_MEMORY = 3.4 * 2 ** 30


def surfaces(fragments: list[Fragment], poses: list[np.ndarray], notes: list[str], status=None):
    """The fragments with each point cloud replaced by the surface it closes into
    (`triangulate.surface_of`) or left out where it closes into none, with their poses: (list of
    Fragment, list of (4, 4) arrays). `notes` gets a line for each cloud."""
    kept, placed = [], []
    for frag, pose in zip(fragments, poses):
        if is_cloud(frag):
            (status or (lambda text: None))(f"meshing {frag.name}")
            try:
                frag = surface_of(frag)
            except FragmentError as exc:
                notes.append(f"{frag.name}: a point cloud (no faces); left out of merged.stl ({exc})")
                continue
            notes.append(f"{frag.name}: a point cloud; meshed into {len(frag.faces)} faces for merged.stl")
        kept.append(frag)
        placed.append(np.asarray(pose, np.float64))
    return kept, placed


def merged_parts(fragments: list[Fragment], poses: list[np.ndarray], notes: list[str], status=None):
    """The placed fragments as the meshes of a merged solid, one mesh at a time.

    Fragments whose placed boxes overlap (`overlap_sets`) are united with manifold3d; a set
    of one fragment is passed on as a shell of its own (`_shell`: as it is when it already
    bounds a solid), and so is each fragment of a set whose union would take more memory
    than UNION_MEMORY (a note says so: merged.stl is then not one watertight solid). Each
    original mesh is read (`full_resolution`) only when its set is reached and freed once
    passed on or made a solid. Holes are capped, meshes that cannot be closed kept as open
    surfaces, point clouds meshed (or left out where they close into no solid); `notes` gets a line
    for each such decision, and one when the solid holds several separate shells.

    Parameters
    ----------
    fragments : list of Fragment
    poses : list of (4, 4) arrays, file coordinates -> the group's frame
    notes : list of str, appended to
    status : callable(str), optional
        Told each long step as it starts (a progress bar's postfix).

    Yields
    ------
    vertices : (V, 3) float, placed
    faces : (F, 3) int
    """
    meshes = list(zip(*surfaces(fragments, poses, notes, status)))
    boxes = np.array([_bbox(_placed(m, f.vertices)) for f, m in meshes]).reshape(-1, 2, 3)
    margin = BOX_MARGIN * np.array([f.size for f, _ in meshes])[:, None]
    sets = overlap_sets(boxes + np.stack([-margin, margin], axis=1))
    if len(sets) > 1:
        notes.append(f"the merged solid holds {len(sets)} separate shells: fragments whose bounding boxes do not "
                     "overlap are written side by side, not united")
    for members in sets:
        yield from _set_parts([meshes[i] for i in members], notes, status or (lambda text: None))


def _set_parts(meshes: list, notes: list[str], status):
    """The placed meshes of one set of (Fragment, (4, 4) pose) whose boxes overlap: each as a
    shell of its own (`_shell`) when it is alone or the union would not fit in UNION_MEMORY,
    else the union of those that close (`_solid_or_surface`) and the open surfaces of the rest."""
    import manifold3d as m3d

    faces = sum(full_faces(frag) for frag, _ in meshes)
    united = len(meshes) > 1 and faces * UNION_BYTES_PER_FACE <= UNION_MEMORY
    if len(meshes) > 1 and not united:
        notes.append(f"{', '.join(f.name for f, _ in meshes)}: not united in merged.stl: their union at full "
                     f"resolution ({faces:,} faces) would take about {faces * UNION_BYTES_PER_FACE / 2 ** 30:.2f} GiB, "
                     f"more than the {UNION_MEMORY / 2 ** 30:.2f} GiB allowed; written as separate shells that "
                     "overlap where they join, so merged.stl is not one watertight solid")
    solids = []
    for frag, m in meshes:
        status(f"reading {frag.name}")
        full = full_resolution(frag)
        if not united:
            status(f"checking {frag.name}")
            v, f = _shell(full, notes)
            del full
            yield _placed(m, v), f
            continue
        status(f"closing {frag.name} ({len(full.faces):,} faces)")
        solid, surface = _solid_or_surface(full, notes)
        del full
        if solid is not None:
            solids.append(solid.transform(m[:3, :]))
        else:
            yield _placed(m, surface.vertices), surface.faces
    if solids:
        n = len(solids)
        status(f"uniting {n} solids ({faces:,} faces)")
        out = (solids[0] if n == 1 else m3d.Manifold.batch_boolean(solids, m3d.OpType.Add)).to_mesh()
        del solids
        v, f = out.vert_properties[:, :3], out.tri_verts  # float32 as STL stores them; uint32 (write_stl takes either)
        status(f"checking the union of {n} solids")
        if not is_closed(v, f):
            v = separate_pinches(v, f)
        if not is_closed(v, f):
            notes.append(f"{', '.join(g.name for g, _ in meshes)}: their union is not closed as merged.stl stores "
                         "it (float32 corners, welded by position: some edges are not shared by exactly two "
                         "faces once each way), so merged.stl is not watertight there")
        status(f"writing the union of {n} solids")
        yield v, f


PINCH_STEP = 1e-6  # x the mesh's extent: how far `separate_pinches` moves a vertex


def separate_pinches(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The vertices of a closed mesh with every vertex that shares its position with an earlier
    one moved a hair (PINCH_STEP of the extent, and at least 64 float32 steps) towards the
    centres of its own faces.

    A union keeps two vertices at one position where two sheets of its surface touch at an edge
    or a corner (pieces placed edge to edge); it is closed with its vertex indices, but STL
    stores only positions, and a reader that welds them sees an edge of four faces. Moving one
    copy apart keeps the file closed.

    Parameters
    ----------
    vertices : (V, 3) float32
    faces : (F, 3) int

    Returns
    -------
    (V, 3) float32, a copy
    """
    v = np.array(vertices, np.float32)
    first, weld, _ = unique_rows(np.ascontiguousarray(v, np.float64).view(np.int64))
    copies = np.flatnonzero(first[weld] != np.arange(len(v)))
    if len(copies) == 0:
        return v
    f = np.asarray(faces, np.int64)
    centres = np.repeat(v[f].astype(np.float64).mean(axis=1), 3, axis=0)
    towards = np.zeros((len(v), 3))
    np.add.at(towards, f.ravel(), centres)
    uses = np.bincount(f.ravel(), minlength=len(v))
    d = towards[copies] / np.maximum(uses[copies], 1)[:, None] - v[copies]
    d /= np.maximum(np.linalg.norm(d, axis=1), 1e-300)[:, None]
    lo, hi = v.min(axis=0).astype(np.float64), v.max(axis=0).astype(np.float64)
    step = max(PINCH_STEP * float(np.linalg.norm(hi - lo)), 64 * float(np.finfo(np.float32).eps) * float(np.abs(v).max()))
    v[copies] += (step * d).astype(np.float32)
    return v


def merged_solid(fragments: list[Fragment], poses: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The placed fragments as one mesh (`merged_parts` joined), watertight where they all close.

    Parameters
    ----------
    fragments : list of Fragment
    poses : list of (4, 4) arrays, file coordinates -> the group's frame

    Returns
    -------
    vertices : (V, 3) float64
    faces : (F, 3) int64
    notes : list of str
        Holes capped, meshes that could not be closed (added as open surfaces: the
        result is then not watertight), point clouds left out, separate shells.
    """
    notes: list[str] = []
    parts = list(merged_parts(fragments, poses, notes))
    if not parts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), notes
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    return (np.vstack([np.asarray(v, np.float64) for v, _ in parts]),
            np.vstack([np.asarray(f, np.int64) + o for (_, f), o in zip(parts, offsets)]), notes)


def write_merged(path, fragments: list[Fragment], poses: list[np.ndarray], notes: list[str],
                 progress: bool = False) -> bool:
    """Write the merged solid of placed fragments as a binary STL (`merged_parts` streamed into
    `io.write_stl`: one set of originals in memory at a time); False, and nothing written,
    when they are all point clouds that close into no solid. `notes` gets the merge's decisions; `progress`: a bar
    in faces on a terminal."""
    fragments, poses = surfaces(fragments, poses, notes)
    if not fragments:
        return False
    total = sum(full_faces(f) for f in fragments)
    with progress_bar(total, f"writing {Path(path).name}", progress, unit="faces") as bar, atomic_open(path) as fh:
        # the bar counts faces written; its postfix names the step under way (reading, closing, uniting)
        write_stl(fh, merged_parts(fragments, poses, notes, bar.set_postfix_str), bar.update)
    return True


def write_outputs(assembly, fragments: list[Fragment], out_dir, progress: bool = False) -> list[str]:
    """assembly.glb, and the merged solids: merged.stl is the largest group; when several
    groups have two or more placed fragments, each also gets merged_<group>.stl.
    (assembly.json is written last by `assemble`, once the timings are complete.)
    The notes of the merge are returned, kept in ``assembly.stats["merge_notes"]`` and
    added to ``assembly.notes`` (so to assembly.json). Both files are streamed, one original
    mesh at a time; `progress`: bars in faces while stderr is a terminal."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sources = [Path(f.source).resolve() for f in fragments if f.source]
    for name in ("assembly.json", "assembly.glb", "merged.stl"):
        if (out / name).resolve() in sources:
            raise FragmentError(f"{out / name}: refusing to overwrite an input file")
    total = sum(full_faces(f) for f in fragments)
    with progress_bar(total, "writing assembly.glb", progress, unit="faces") as bar, \
            atomic_open(out / "assembly.glb") as fh:
        write_glb(fh, assembly_items(assembly, fragments), bar.update, bar.set_postfix_str)
    notes: list[str] = []
    members = assembly.group_members()
    placed_groups = [g for g, m in sorted(members.items()) if any(assembly.poses[i] is not None for i in m)]
    for g in placed_groups:
        m = members[g]
        name = "merged.stl" if g == placed_groups[0] else f"merged_{g}.stl"
        if not write_merged(out / name, [fragments[i] for i in m], [assembly.poses[i] for i in m], notes, progress):
            continue
        if name == "merged.stl" and len(placed_groups) > 1:  # the largest group also under its own name
            with open(out / name, "rb") as src, atomic_open(out / f"merged_{g}.stl") as dst:
                shutil.copyfileobj(src, dst, 1 << 22)
    if not placed_groups:
        notes.append("no two fragments were joined: no merged.stl written")
    assembly.stats["merge_notes"] = notes
    assembly.notes = list(assembly.notes) + [n for n in notes if n not in assembly.notes]
    return notes
