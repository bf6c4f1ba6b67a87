/* Test and utility kernels for cl/include/grid.h.
 *
 * grid_density_many: out[i] = density at world point p[i] (0 outside the box)
 * box_intersect_many: t[i] = (t0, t1) or (+inf, -inf) for a miss; rays o[i] + t d[i], t >= tmin
 * camera_rays:       dir[row][col] for pixel centres
 * Points and directions are packed float3 (3 floats). Twin: reference/grid.py.
 */
#include "grid.h"

__kernel void grid_density_many(__global const float *density, const int nx, const int ny,
                                const int nz, const float4 bmin, const float4 bmax,
                                __global const float *p, const int n, __global float *out) {
    int i = get_global_id(0);
    if (i >= n) return;
    out[i] = grid_density(density, nx, ny, nz, bmin.xyz, bmax.xyz, vload3(i, p));
}

__kernel void box_intersect_many(__global const float *o, __global const float *d,
                                 const float4 bmin, const float4 bmax, const float tmin,
                                 const int n, __global float2 *t) {
    int i = get_global_id(0);
    if (i >= n) return;
    float t0, t1;
    if (box_intersect(vload3(i, o), vload3(i, d), bmin.xyz, bmax.xyz, tmin, &t0, &t1))
        t[i] = (float2)(t0, t1);
    else
        t[i] = (float2)(INFINITY, -INFINITY);
}

__kernel void camera_rays(const float4 forward, const float4 right, const float4 up,
                          const float tan_half, const int width, const int height,
                          __global float *dir) {
    int i = get_global_id(0);
    if (i >= width * height) return;
    int row = i / width, col = i - row * width;
    vstore3(camera_ray(forward.xyz, right.xyz, up.xyz, tan_half, width, height,
                       (float)col + 0.5f, (float)row + 0.5f), i, dir);
}
