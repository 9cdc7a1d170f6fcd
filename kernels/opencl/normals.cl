/* Family 1: face normals and the angle across every shared edge (OpenCL).
   Vertices arrive as float32 shifted to their bounding-box centre (done on the
   host in float64). Points are packed xyz triples (vload3/vstore3).
   No contraction into fused multiply-adds: with FMA, a x a is not exactly zero,
   and a face with two equal vertices must get a zero normal. */

#pragma OPENCL FP_CONTRACT OFF

__kernel void face_normals(__global const float *vertices, __global const int *faces, const int n_faces,
                           __global float *normals, __global float *areas)
{
    const int f = get_global_id(0);
    if (f >= n_faces) return;
    const int3 tri = vload3(f, faces);
    const float3 p0 = vload3(tri.x, vertices);
    const float3 a = vload3(tri.y, vertices) - p0, b = vload3(tri.z, vertices) - p0;
    const float3 c = (float3)(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x);
    const float len = length(c);
    vstore3(len > 0.0f ? c / len : (float3)(0.0f), f, normals);
    areas[f] = 0.5f * len;
}

__kernel void edge_angles(__global const float *normals, __global const int *edge_faces, const int n_edges,
                          __global float *angles)
{
    const int e = get_global_id(0);
    if (e >= n_edges) return;
    const int2 pr = vload2(e, edge_faces);
    const float3 n0 = vload3(pr.x, normals);
    const float3 n1 = vload3(pr.y, normals);
    float angle = 0.0f;  /* an edge next to a zero-area face (zero normal) has angle 0 */
    if (dot(n0, n0) > 0.0f && dot(n1, n1) > 0.0f)
        angle = atan2(length(cross(n0, n1)), dot(n0, n1));
    angles[e] = angle;
}
