"""What an assembly writes: assembly.glb (every fragment placed, groups side by side) and
merged.stl (the placed fragments of a group united into one solid).

Fragments come in three kinds here:

- closed meshes: united with manifold3d;
- open meshes (scans with holes): each hole is capped (a fan from the centre of its
  boundary loop) so that it joins the union; one that still does not make a closed solid is
  added as an open surface, and the notes say that merged.stl is then not watertight;
- faceless point clouds (`pointcloud.CloudFragment`): points in assembly.glb, left out of
  merged.stl with a note.

A fragment thinned at load (`io.Fragment.thinned_from`) is written at full resolution: its
file is read again when it is written, one fragment at a time, so the thinned and the
original meshes are never all in memory together.
"""
from __future__ import annotations

import colorsys
from pathlib import Path

import numpy as np

from .io import Fragment, FragmentError, atomic_write_bytes, load_fragments, write_mesh


def colour(i: int) -> tuple[int, int, int, int]:
    """Well separated colours: golden-angle hues (RGBA, 0-255)."""
    r, g, b = colorsys.hsv_to_rgb((i * 0.618033988749895) % 1.0, 0.55, 0.9)
    return int(r * 255), int(g * 255), int(b * 255), 255


def is_cloud(fragment: Fragment) -> bool:
    """True for a fragment without faces (a point cloud)."""
    return len(fragment.faces) == 0


def full_resolution(fragment: Fragment) -> Fragment:
    """The fragment as its file holds it: read again where it was thinned at load, else itself."""
    if not fragment.thinned_from or not fragment.source:
        return fragment
    bases = [fragment.name] + ([fragment.name.rsplit("#", 1)[0]] if "#" in fragment.name else [])
    for base in bases:
        try:
            frags, _, _ = load_fragments(fragment.source, base, thin_above=None)
        except FragmentError:
            return fragment
        for f in frags:
            if f.name == fragment.name:
                return f
    return fragment


def geometry(fragment: Fragment, rgba):
    """A trimesh geometry of a fragment in one colour: a Trimesh, or a PointCloud without faces.

    Parameters
    ----------
    fragment : Fragment
        (V, 3) vertices, (F, 3) faces (F may be 0).
    rgba : sequence of 4 ints
    """
    import trimesh

    if is_cloud(fragment):
        return trimesh.PointCloud(fragment.vertices, colors=np.tile(rgba, (len(fragment.vertices), 1)))
    # one material colour, not a colour per face: glTF has no face colours, and trimesh would
    # split every vertex per face to write them (about 1 GB more on a 5M-face mesh)
    material = trimesh.visual.material.PBRMaterial(baseColorFactor=list(rgba), metallicFactor=0.0,
                                                   roughnessFactor=0.8)
    return trimesh.Trimesh(fragment.vertices, fragment.faces, process=False,
                           visual=trimesh.visual.TextureVisuals(material=material))


def scene_glb(items) -> bytes:
    """A GLB scene of (fragment, rgba, 4x4 transform) items, one named node each, at full resolution."""
    import trimesh

    scene = trimesh.Scene()
    for fragment, rgba, transform in items:
        scene.add_geometry(geometry(full_resolution(fragment), rgba), node_name=fragment.name,
                           geom_name=fragment.name, transform=np.asarray(transform, np.float64))
    return scene.export(file_type="glb")


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


def assembly_glb(assembly, fragments: list[Fragment]) -> bytes:
    """A glTF scene: one named node per fragment, own colour, its transform the fragment's pose
    followed by its group's translation from `group_layout` (groups side by side); point
    clouds as points."""
    layout = group_layout(assembly, fragments)
    return scene_glb((frag, colour(i), layout[assembly.groups[i]] @ (
        np.eye(4) if assembly.poses[i] is None else np.asarray(assembly.poses[i])))
        for i, frag in enumerate(fragments))


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
    key = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = directed[counts[inverse.ravel()] == 1]  # (B, 2) as the faces run
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
    notes.append(f"{frag.name}: open mesh that could not be closed; merged.stl holds it as an open surface, "
                 "so merged.stl is not watertight")
    return None, frag


def merged_solid(fragments: list[Fragment], poses: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The placed fragments united into one solid with manifold3d, watertight where they all close.

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
        result is then not watertight), point clouds left out.
    """
    import manifold3d as m3d

    solids, surfaces, notes = [], [], []
    for frag, pose in zip(fragments, poses):
        if is_cloud(frag):
            notes.append(f"{frag.name}: a point cloud (no faces); left out of merged.stl")
            continue
        solid, surface = _solid_or_surface(full_resolution(frag), notes)
        m = np.asarray(pose, np.float64)
        if solid is not None:
            solids.append(solid.transform(m[:3, :]))
        else:
            surfaces.append((_placed(m, surface.vertices), np.asarray(surface.faces, np.int64)))
    parts = []
    if solids:
        out = m3d.Manifold.batch_boolean(solids, m3d.OpType.Add).to_mesh()
        parts.append((np.asarray(out.vert_properties[:, :3], np.float64), np.asarray(out.tri_verts, np.int64)))
    parts += surfaces
    if not parts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), notes
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    return (np.vstack([v for v, _ in parts]), np.vstack([f + o for (_, f), o in zip(parts, offsets)]), notes)


def write_outputs(assembly, fragments: list[Fragment], out_dir) -> list[str]:
    """assembly.glb, and the merged solids: merged.stl is the largest group; when several
    groups have two or more placed fragments, each also gets merged_<group>.stl.
    (assembly.json is written last by `assemble`, once the timings are complete.)
    The notes of the merge are returned, kept in ``assembly.stats["merge_notes"]`` and
    added to ``assembly.notes`` (so to assembly.json)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sources = [Path(f.source).resolve() for f in fragments if f.source]
    for name in ("assembly.json", "assembly.glb", "merged.stl"):
        if (out / name).resolve() in sources:
            raise FragmentError(f"{out / name}: refusing to overwrite an input file")
    atomic_write_bytes(out / "assembly.glb", assembly_glb(assembly, fragments))
    notes = []
    members = assembly.group_members()
    placed_groups = [g for g, m in sorted(members.items()) if any(assembly.poses[i] is not None for i in m)]
    for g in placed_groups:
        m = members[g]
        v, f, why = merged_solid([fragments[i] for i in m], [assembly.poses[i] for i in m])
        notes += why
        if len(f) == 0:
            continue
        if g == placed_groups[0]:
            write_mesh(out / "merged.stl", v, f)
        if len(placed_groups) > 1:
            write_mesh(out / f"merged_{g}.stl", v, f)
    if not placed_groups:
        notes.append("no two fragments were joined: no merged.stl written")
    assembly.stats["merge_notes"] = notes
    assembly.notes = list(assembly.notes) + [n for n in notes if n not in assembly.notes]
    return notes
