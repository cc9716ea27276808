// Area-weighted vertex normals of deformed frames (OpenCLDeformer.normals).

// Cross product per triangle (length = 2 * area), for the area-weighted vertex normals.
__kernel void face_normals(const uint n_faces, __global const int *tri,
                           __global const float *verts, __global float *fn)
{
    const uint t = get_global_id(0);
    if (t >= n_faces) return;
    const int a = tri[3 * t], b = tri[3 * t + 1], c = tri[3 * t + 2];
    const float3 p0 = vload3(a, verts), p1 = vload3(b, verts), p2 = vload3(c, verts);
    vstore3(cross(p1 - p0, p2 - p0), t, fn);
}

// Sum of the incident triangles' cross products, normalised; (0, 0, 0) when it vanishes.
__kernel void vertex_normals(const uint n_vertices, __global const uint *adj_ptr,
                             __global const uint *adj, __global const float *fn,
                             __global float *out)
{
    const uint v = get_global_id(0);
    if (v >= n_vertices) return;
    float3 n = (float3)(0.0f);
    for (uint e = adj_ptr[v]; e < adj_ptr[v + 1]; ++e) n += vload3(adj[e], fn);
    const float len = sqrt(n.x * n.x + n.y * n.y + n.z * n.z);
    vstore3(len > 0.0f ? n / len : (float3)(0.0f), v, out);
}
