/* Dense grids, boxes and camera rays: the conventions of docs/conventions.md in device code.
 *
 * A grid is float density[z][y][x] (x fastest) filling the box bmin..bmax.
 * Voxel i sits at the centre of cell i: bmin + (i + 0.5) * cell. Lookups are
 * trilinear between centres and clamped at the edges (like GPU textures and
 * Mitsuba's gridvolume); density is 0 outside the box (callers test the box).
 * Twin: reference/grid.py.
 */
#ifndef CLVOL_GRID_H
#define CLVOL_GRID_H

#define CLVOL_PI 3.14159265358979323846f
#define CLVOL_INV_4PI 0.07957747154594767f

/* Trilinear lookup at continuous voxel coordinates g = (p - bmin) / cell - 0.5. */
__attribute__((always_inline))
float grid_lookup(__global const float *d, int nx, int ny, int nz, float3 g) {
    /* Clamp to [0, n-1] first: the casts below are then floors (non-negative). */
    float x = clamp(g.x, 0.0f, (float)(nx - 1));
    float y = clamp(g.y, 0.0f, (float)(ny - 1));
    float z = clamp(g.z, 0.0f, (float)(nz - 1));
    int x0 = (int)x, y0 = (int)y, z0 = (int)z;
    int x1 = min(x0 + 1, nx - 1), y1 = min(y0 + 1, ny - 1), z1 = min(z0 + 1, nz - 1);
    float fx = x - (float)x0, fy = y - (float)y0, fz = z - (float)z0;
    size_t sy = (size_t)nx, sz = (size_t)nx * (size_t)ny;
    size_t r00 = (size_t)z0 * sz + (size_t)y0 * sy, r01 = (size_t)z0 * sz + (size_t)y1 * sy;
    size_t r10 = (size_t)z1 * sz + (size_t)y0 * sy, r11 = (size_t)z1 * sz + (size_t)y1 * sy;
    float c00 = mix(d[r00 + x0], d[r00 + x1], fx);
    float c01 = mix(d[r01 + x0], d[r01 + x1], fx);
    float c10 = mix(d[r10 + x0], d[r10 + x1], fx);
    float c11 = mix(d[r11 + x0], d[r11 + x1], fx);
    return mix(mix(c00, c01, fy), mix(c10, c11, fy), fz);
}

/* Density at world position p: 0 outside the box, trilinear inside. */
__attribute__((always_inline))
float grid_density(__global const float *d, int nx, int ny, int nz,
                   float3 bmin, float3 bmax, float3 p) {
    if (any(p < bmin) || any(p > bmax)) return 0.0f;
    float3 cell = (bmax - bmin) / (float3)((float)nx, (float)ny, (float)nz);
    return grid_lookup(d, nx, ny, nz, (p - bmin) / cell - 0.5f);
}

/* Ray/box slab test. Returns 1 and the parametric interval [t0, t1] (t0 clamped to
 * tmin) if the ray o + t d meets the box for t in [tmin, inf), else 0. Zero direction
 * components are handled: such a ray hits iff its origin lies within that slab. */
__attribute__((always_inline))
int box_intersect(float3 o, float3 d, float3 bmin, float3 bmax, float tmin,
                  float *t0, float *t1) {
    float lo = tmin, hi = INFINITY;
    float oc[3] = {o.x, o.y, o.z}, dc[3] = {d.x, d.y, d.z};
    float mn[3] = {bmin.x, bmin.y, bmin.z}, mx[3] = {bmax.x, bmax.y, bmax.z};
    for (int a = 0; a < 3; ++a) {
        if (dc[a] == 0.0f) {
            if (oc[a] < mn[a] || oc[a] > mx[a]) return 0;
            continue;
        }
        float inv = 1.0f / dc[a];
        float ta = (mn[a] - oc[a]) * inv, tb = (mx[a] - oc[a]) * inv;
        lo = fmax(lo, fmin(ta, tb));
        hi = fmin(hi, fmax(ta, tb));
    }
    *t0 = lo;
    *t1 = hi;
    return lo <= hi;
}

/* Camera ray through image position (px, py) in pixels (pixel centres at +0.5).
 * Column 0 is the left edge, row 0 the top; right = normalize(cross(forward, up)).
 * tan_half = tan(fov_y / 2); aspect = width / height. Twin: Camera.pixel_directions. */
__attribute__((always_inline))
float3 camera_ray(float3 forward, float3 right, float3 up, float tan_half,
                  int width, int height, float px, float py) {
    float sx = (2.0f * px / (float)width - 1.0f) * tan_half * ((float)width / (float)height);
    float sy = (1.0f - 2.0f * py / (float)height) * tan_half;
    return normalize(forward + sx * right + sy * up);
}

#endif
