"""Family 1: face normals and the angle across every shared edge (Warp).

Vertices arrive as float32 shifted to their bounding-box centre (the host does
the shift in float64), so edge vectors keep their precision far from the origin.
No fused multiply-add: with FMA, a x a is not exactly zero (one product is
rounded, the other not), and a face with two equal vertices must get a zero
normal, as in the float64 reference.
"""
import warp as wp

wp.set_module_options({"enable_backward": False, "fuse_fp": False})


@wp.kernel
def face_normals(
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    normals: wp.array(dtype=wp.vec3),
    areas: wp.array(dtype=wp.float32),
):
    f = wp.tid()
    tri = faces[f]
    p0 = vertices[tri[0]]
    c = wp.cross(vertices[tri[1]] - p0, vertices[tri[2]] - p0)
    length = wp.length(c)
    n = wp.vec3()
    if length > 0.0:
        n = c / length
    normals[f] = n
    areas[f] = 0.5 * length


@wp.kernel
def edge_angles(
    normals: wp.array(dtype=wp.vec3),
    edge_faces: wp.array(dtype=wp.vec2i),
    angles: wp.array(dtype=wp.float32),
):
    e = wp.tid()
    pair = edge_faces[e]
    n0 = normals[pair[0]]
    n1 = normals[pair[1]]
    angle = float(0.0)
    # an edge next to a zero-area face (zero normal) has angle 0
    if wp.length_sq(n0) > 0.0 and wp.length_sq(n1) > 0.0:
        angle = wp.atan2(wp.length(wp.cross(n0, n1)), wp.dot(n0, n1))
    angles[e] = angle
