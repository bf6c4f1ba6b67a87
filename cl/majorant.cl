/* Majorant grid: per-block maximum density, and a test kernel for the DDA of majorant.h.
 *
 * Seed context: the path tracer's free-flight sampling (delta tracking, Woodcock et al.)
 * needs sigma_maj >= sigma_t everywhere along a ray; a coarse grid of local maxima keeps
 * sigma_maj tight in sparse clouds (pbrt-v4's majorant grid). Twin: reference/majorant.py.
 *
 * majorant_build (one work-item per coarse cell, 3-D launch (mx, my, mz))
 *   density   float [nz][ny][nx]    raw density (sigma_t = density * density_scale)
 *   nx,ny,nz  int                  fine grid size
 *   block     int                  fine voxels per coarse cell per axis (>= 1)
 *   mx,my,mz  int                  coarse size = ceil(n / block)
 *   maj       float [mz][my][mx]   out: max of the fine voxels [i*block - 1, (i+1)*block]
 *                                  per axis, clamped to the grid (the trilinear footprint
 *                                  of the coarse cell's box; see majorant.h)
 *
 * majorant_segments (one work-item per ray; test and debugging aid)
 *   o, d      float [n][3]         ray origins and directions (world units)
 *   bmin,bmax float4               the grid's box
 *   bsize     float4               coarse cell size in world units (cell * block)
 *   maj       float [mz][my][mx]   majorant grid
 *   tmin,tmax float                parameter range of the rays
 *   max_seg   int                  segments stored per ray (more are counted, not stored)
 *   seg       float [n][max_seg][4] out: (t_a, t_b, majorant, 0) per segment
 *   count     int [n]              out: number of segments (0 for a miss)
 */
#include "majorant.h"

__kernel void majorant_build(__global const float *density, const int nx, const int ny,
                             const int nz, const int block, const int mx, const int my,
                             const int mz, __global float *maj) {
    /* 3-D launch (mx padded, my, mz): no division to find the coarse cell. */
    int bx = get_global_id(0), by = get_global_id(1), bz = get_global_id(2);
    if (bx >= mx || by >= my || bz >= mz) return;
    int x0 = max(bx * block - 1, 0), x1 = min((bx + 1) * block, nx - 1);
    int y0 = max(by * block - 1, 0), y1 = min((by + 1) * block, ny - 1);
    int z0 = max(bz * block - 1, 0), z1 = min((bz + 1) * block, nz - 1);
    float m = 0.0f;
    for (int z = z0; z <= z1; ++z)
        for (int y = y0; y <= y1; ++y) {
            __global const float *row = density + ((size_t)z * ny + y) * (size_t)nx;
            for (int x = x0; x <= x1; ++x) m = fmax(m, row[x]);
        }
    maj[((size_t)bz * my + by) * (size_t)mx + bx] = m;
}

__kernel void majorant_segments(__global const float *o, __global const float *d, const int n,
                                const float4 bmin, const float4 bmax, const float4 bsize,
                                __global const float *maj, const int mx, const int my,
                                const int mz, const float tmin, const float tmax,
                                const int max_seg, __global float *seg,
                                __global int *count) {
    int i = get_global_id(0);
    if (i >= n) return;
    maj_dda s;
    int k = 0;
    if (maj_dda_init(&s, vload3(i, o), vload3(i, d), bmin.xyz, bmax.xyz, bsize.xyz,
                     (int3)(mx, my, mz), tmin, tmax)) {
        do {
            if (k < max_seg) {
                /* Scalar stores: Oclgrind flags a vector built from scalars as uninitialised. */
                __global float *out = seg + 4 * ((size_t)i * max_seg + k);
                out[0] = s.t;
                out[1] = maj_dda_seg_end(&s);
                out[2] = maj_dda_value(&s, maj);
                out[3] = 0.0f;
            }
            ++k;
        } while (maj_dda_step(&s));
    }
    count[i] = k;
}
