/* Majorant grid traversal: a 3D DDA over a coarse grid of per-block maximum densities.
 *
 * The majorant grid (built by cl/majorant.cl, twin reference/majorant.py) has
 * mres = ceil(n / block) cells per axis, stored maj[mz][my][mx] (x fastest). Coarse cell
 * (i, j, k) covers the fine cells [i*block, (i+1)*block) etc., i.e. the world box
 *     bmin + (i, j, k) * bsize  ..  bmin + (i+1, j+1, k+1) * bsize,   bsize = cell * block,
 * and holds the maximum of the fine voxels [i*block - 1, (i+1)*block] (clamped to the grid):
 * every voxel the trilinear lookup of grid.h can blend for a point of that box. Trilinear
 * interpolation is a convex combination, so the value is >= the density anywhere in the box
 * (to float rounding of the lerps: trackers compare u * majorant < density, which never
 * yields a negative probability). The footprint reaches half a voxel beyond the box on each
 * side, so a point that float rounding places in the neighbouring coarse cell is still
 * covered. The last coarse cell of an axis may reach past bmax; rays are clipped to the box.
 *
 * Densities are raw: multiply by density_scale for sigma_t (the same product the trackers
 * use for the density, so sigma_t <= majorant holds after scaling too).
 * A single global majorant is the special case block >= max(nx, ny, nz): one coarse cell.
 *
 * Use (one loop in the caller, events returned to it, STYLE.md pattern 6):
 *     maj_dda s;
 *     if (maj_dda_init(&s, o, d, bmin, bmax, bsize, mres, tmin, tmax)) {
 *         do {
 *             float tb = maj_dda_seg_end(&s), m = maj_dda_value(&s, maj);
 *             ... segment [s.t, tb] has majorant m (raw density) ...
 *         } while (maj_dda_step(&s));
 *     }
 * or maj_dda_track() below, which walks segments consuming an optical depth tau and stops
 * at the tentative collision (delta / ratio tracking).
 */
#ifndef CLVOL_MAJORANT_H
#define CLVOL_MAJORANT_H

#include "grid.h"

/* Scalar members only: Oclgrind's uninitialised-value checker crashes on vector members
 * of a private struct that are updated element by element. */
typedef struct {
    float tnx, tny, tnz;   /* ray parameter of the next coarse-cell boundary per axis (INF if d = 0) */
    float tdx, tdy, tdz;   /* parameter length of one coarse cell per axis (INF if d = 0) */
    int cx, cy, cz;        /* current coarse cell */
    int sx, sy, sz;        /* step +1 / -1 per axis */
    int mx, my, mz;        /* coarse grid size */
    float t;               /* start of the current segment */
    float t_end;           /* where the ray leaves the box (or tmax) */
} maj_dda;

/* One axis of the DDA set-up: step, next boundary and cell length in ray parameter. */
__attribute__((always_inline))
void maj_dda_axis(float o, float d, float bmin, float bsize, int cell, int *step,
                  float *t_next, float *t_delta) {
    if (d > 0.0f) {
        *step = 1;
        *t_next = (bmin + (float)(cell + 1) * bsize - o) / d;
        *t_delta = bsize / d;
    } else if (d < 0.0f) {
        *step = -1;
        *t_next = (bmin + (float)cell * bsize - o) / d;
        *t_delta = -bsize / d;
    } else {
        *step = 0;
        *t_next = INFINITY;
        *t_delta = INFINITY;
    }
}

/* Start a traversal of o + t d, t in [tmin, tmax], through the box. Returns 0 if the ray
 * misses the box in that range (then s is unusable). */
__attribute__((always_inline))
int maj_dda_init(maj_dda *s, float3 o, float3 d, float3 bmin, float3 bmax, float3 bsize,
                 int3 mres, float tmin, float tmax) {
    float t0, t1;
    if (!box_intersect(o, d, bmin, bmax, tmin, &t0, &t1)) return 0;
    t1 = fmin(t1, tmax);
    if (!(t0 < t1)) return 0;
    s->t = t0;
    s->t_end = t1;
    s->mx = mres.x;
    s->my = mres.y;
    s->mz = mres.z;
    /* Cell of the entry point; clamping first makes the cast a floor (docs/conventions.md). */
    float3 c = clamp((o + t0 * d - bmin) / bsize, (float3)(0.0f), convert_float3(mres - 1));
    s->cx = (int)c.x;
    s->cy = (int)c.y;
    s->cz = (int)c.z;
    maj_dda_axis(o.x, d.x, bmin.x, bsize.x, s->cx, &s->sx, &s->tnx, &s->tdx);
    maj_dda_axis(o.y, d.y, bmin.y, bsize.y, s->cy, &s->sy, &s->tny, &s->tdy);
    maj_dda_axis(o.z, d.z, bmin.z, bsize.z, s->cz, &s->sz, &s->tnz, &s->tdz);
    return 1;
}

/* End of the current segment [s->t, maj_dda_seg_end(s)]. */
__attribute__((always_inline))
float maj_dda_seg_end(const maj_dda *s) {
    return fmin(fmin(fmin(s->tnx, s->tny), s->tnz), s->t_end);
}

/* Raw majorant (density units) of the current segment. */
__attribute__((always_inline))
float maj_dda_value(const maj_dda *s, __global const float *maj) {
    return maj[((size_t)s->cz * (size_t)s->my + (size_t)s->cy) * (size_t)s->mx + (size_t)s->cx];
}

/* Move to the next coarse cell. Returns 0 when the ray has left the box (or passed tmax). */
__attribute__((always_inline))
int maj_dda_step(maj_dda *s) {
    float tb = maj_dda_seg_end(s);
    s->t = tb;
    if (tb >= s->t_end) return 0;
    /* Advance the axis whose boundary comes first; ties advance one axis per call and
     * give a zero-length segment, which is harmless. */
    int inside;
    if (s->tnx <= s->tny && s->tnx <= s->tnz) {
        s->cx += s->sx;
        s->tnx += s->tdx;
        inside = s->cx >= 0 && s->cx < s->mx;
    } else if (s->tny <= s->tnz) {
        s->cy += s->sy;
        s->tny += s->tdy;
        inside = s->cy >= 0 && s->cy < s->my;
    } else {
        s->cz += s->sz;
        s->tnz += s->tdz;
        inside = s->cz >= 0 && s->cz < s->mz;
    }
    if (!inside) s->t = s->t_end;
    return inside;
}

/* Walk the segments consuming optical depth *tau (against majorant * scale) from s->t.
 * Returns 1 at a tentative collision: *t_hit is its parameter, *sigma_maj the scaled
 * majorant there, and s is left in that cell with s->t = *t_hit, so calling again with a
 * fresh tau continues the same ray (delta / ratio tracking). Returns 0 if the ray leaves
 * the box first; *tau then holds the unspent optical depth. Segments with majorant 0 are
 * crossed without sampling: empty space costs one DDA step per coarse cell. */
__attribute__((always_inline))
int maj_dda_track(maj_dda *s, __global const float *maj, float scale, float *tau,
                  float *t_hit, float *sigma_maj) {
    for (;;) {
        float tb = maj_dda_seg_end(s);
        float sm = maj_dda_value(s, maj) * scale;
        float dtau = sm * (tb - s->t);
        if (sm > 0.0f && dtau >= *tau) {
            /* tau / sm <= tb - t, so the hit stays inside the segment (clamped for rounding). */
            float th = fmin(s->t + *tau / sm, tb);
            *t_hit = th;
            *sigma_maj = sm;
            s->t = th;
            return 1;
        }
        *tau -= dtau;
        if (!maj_dda_step(s)) return 0;
    }
}

#endif
