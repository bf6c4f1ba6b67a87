/* libclvol: the renderer (the Python host's clvol/render/ steps in the same order, with the
 * same launches; walk-through and kernel ABI in docs/embedding.md).
 *
 *   per volume   upload the density, majorant grid, resample the density to the light field's
 *                cube and to the network's pyramid base (host), mip chain (device);
 *   per light    light field (transmittance sweep, lambda = 1), graded transmittance (every
 *                pyramid level), bake of (tau, C) per level for the gather;
 *   per frame    F_ms at the active lattice points toward the camera (gather, MLP; the other
 *                points hold 0) when the camera position, light or medium moved; ray march.
 * A bundle whose scene the Python host renders with an analytic source instead of the network
 * (raymarch.ms_source = none or wrenninge) runs the light field and the march only.
 * Setters only record the change and mark the stages it invalidates (volume_dirty,
 * light_dirty, lattice_dirty); the next render brings those up to date, as clvol.Renderer
 * does on its next render().
 */
#define _POSIX_C_SOURCE 200809L
#include "internal.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

/* ---------------------------------------------------------- resampling to the cube (host)
 * The Python host's clvol/kernels/pyramid.py resample_to_cube: each base voxel is the mean over
 * its cell of the source field, read as boxes where the base cell is at least the source cell
 * and as the clamped linear interpolant where it is smaller; 0 outside the source box. */

static double clampd(double x, double lo, double hi) { return x < lo ? lo : (x > hi ? hi : x); }

static double hat_cdf(double x) {
    x = clampd(x, -1.0, 1.0);
    return x < 0 ? 0.5 * (x + 1) * (x + 1) : 1 - 0.5 * (1 - x) * (1 - x);
}

static double basis_cdf(double g, long i, long n, int linear) {
    g = clampd(g, -0.5, (double)n - 0.5);
    if (!linear) return clampd(g - ((double)i - 0.5), 0.0, 1.0);
    if (n == 1) return g + 0.5;
    double hc = hat_cdf(g - (double)i);
    if (i == 0) return clampd(g + 0.5, 0.0, 0.5) + fmax(hc - 0.5, 0.0);
    if (i == n - 1) return fmin(hc, 0.5) + clampd(g - (double)(n - 1), 0.0, 0.5);
    return hc;
}

typedef struct {
    long n_dst, width;
    long *first;      /* [n_dst] first source index */
    double *w;        /* [n_dst][width] */
} resample_mat;

static resample_mat resample_matrix(long n_src, double src_lo, double src_hi, long n_dst,
                                    double dst_lo, double dst_hi) {
    resample_mat r;
    double src_cell = (src_hi - src_lo) / (double)n_src, dst_cell = (dst_hi - dst_lo) / (double)n_dst;
    int linear = dst_cell < src_cell * (1 - 1e-12);
    r.n_dst = n_dst;
    r.width = (long)ceil(dst_cell / src_cell) + 3;
    r.first = xmalloc(sizeof(long) * (size_t)n_dst);
    r.w = xmalloc(sizeof(double) * (size_t)(n_dst * r.width));
    for (long a = 0; a < n_dst; ++a) {
        double lo = (dst_lo + (double)a * dst_cell - src_lo) / src_cell - 0.5;
        double hi = (dst_lo + (double)(a + 1) * dst_cell - src_lo) / src_cell - 0.5;
        long first = (long)floor(lo) - 1;
        first = first < 0 ? 0 : (first > n_src - 1 ? n_src - 1 : first);
        r.first[a] = first;
        for (long k = 0; k < r.width; ++k) {
            long i = first + k;
            r.w[a * r.width + k] = i < n_src ? (basis_cdf(hi, i, n_src, linear)
                                                - basis_cdf(lo, i, n_src, linear)) / (hi - lo)
                                             : 0.0;
        }
    }
    return r;
}

/* Apply along array axis `ax` (0 = z, 1 = y, 2 = x) of a [d0][d1][d2] array. */
static double *apply_axis(const double *in, long dims[3], int ax, const resample_mat *r) {
    long od[3] = {dims[0], dims[1], dims[2]};
    od[ax] = r->n_dst;
    double *out = xmalloc(sizeof(double) * (size_t)(od[0] * od[1] * od[2]));
    long n_src = dims[ax];
    long s_in[3] = {dims[1] * dims[2], dims[2], 1}, s_out[3] = {od[1] * od[2], od[2], 1};
    for (long i0 = 0; i0 < od[0]; ++i0)
        for (long i1 = 0; i1 < od[1]; ++i1)
            for (long i2 = 0; i2 < od[2]; ++i2) {
                long idx[3] = {i0, i1, i2};
                long a = idx[ax];
                idx[ax] = 0;
                const double *src = in + idx[0] * s_in[0] + idx[1] * s_in[1] + idx[2] * s_in[2];
                double acc = 0.0;
                for (long k = 0; k < r->width; ++k) {
                    long i = r->first[a] + k;
                    if (i < n_src) acc += r->w[a * r->width + k] * src[i * s_in[ax]];
                }
                out[i0 * s_out[0] + i1 * s_out[1] + i2 * s_out[2]] = acc;
            }
    dims[ax] = r->n_dst;
    return out;
}

/* base^3 float32 [z][y][x] over the cube (written into out). */
static void resample_to_cube(const clvol_host *h, int base, float *out) {
    long n_src[3] = {h->nx, h->ny, h->nz};
    long dims[3] = {h->nz, h->ny, h->nx};
    long count = dims[0] * dims[1] * dims[2];
    double *d = xmalloc(sizeof(double) * (size_t)count);
    for (long i = 0; i < count; ++i) d[i] = h->density[i];
    /* shrink the most-reducing world axis first (as the Python host does) */
    int order[3] = {0, 1, 2};
    for (int i = 0; i < 3; ++i)
        for (int j = i + 1; j < 3; ++j)
            if ((double)base / (double)n_src[order[j]] < (double)base / (double)n_src[order[i]]) {
                int t = order[i];
                order[i] = order[j];
                order[j] = t;
            }
    for (int s = 0; s < 3; ++s) {
        int a = order[s];
        resample_mat r = resample_matrix(n_src[a], h->bmin[a], h->bmax[a], base, h->cube_min[a],
                                         h->cube_min[a] + h->cube_size);
        double *next = apply_axis(d, dims, 2 - a, &r);
        xfree(d);
        xfree(r.first);
        xfree(r.w);
        d = next;
    }
    for (long i = 0; i < (long)base * base * base; ++i) out[i] = (float)d[i];
    xfree(d);
}

/* -------------------------------------------------------------------- transmittance */

typedef struct {
    int a, sa;
    double su, sv, inv_la;
} sweep_geom;

static sweep_geom sweep_geometry(const double *l) {
    sweep_geom g;
    int a = 0;
    for (int i = 1; i < 3; ++i)
        if (fabs(l[i]) > fabs(l[a])) a = i;
    int lat[2], k = 0;
    for (int i = 0; i < 3; ++i)
        if (i != a) lat[k++] = i;
    double la = fabs(l[a]);
    g.a = a;
    g.sa = l[a] > 0 ? 1 : -1;
    g.su = l[lat[0]] / la;
    g.sv = l[lat[1]] / la;
    g.inv_la = 1.0 / la;
    return g;
}

static long layout_size(const clvol_host *h, long n) {
    return (n + 2) * (n + 2 * h->sweep_pad + 1) * (n + 3 * h->sweep_pad);
}

/* Padded per-axis copy of levels 0..n_levels-1 of `pyr` (clvol/kernels/transmittance.py
 * sweep_layout): made once per volume and sweep axis, kept in *cached (as the Python host
 * caches it on its pyramid; the volume stage releases it); offsets in s_off. */
static cl_mem sweep_layout(clvol_host *h, cl_mem pyr, const long *loff, int base, int n_levels,
                           int axis, long *s_off, cl_mem *cached) {
    long total = 0;
    for (int l = 0; l < n_levels; ++l) {
        s_off[l] = total;
        total += layout_size(h, base >> l);
    }
    if (*cached) return *cached;
    cl_mem buf = *cached = buffer(h, 4 * (size_t)(total + h->sweep_slack), NULL);
    for (int l = 0; l < n_levels; ++l) {
        set_args(h->k_layout, "miiimi", pyr, (int)loff[l], base >> l, axis, buf, (int)s_off[l]);
        launch(h, h->k_layout, padded((size_t)layout_size(h, base >> l), (size_t)h->pad), 0);
    }
    return buf;
}

/* One level's sweep (clvol/kernels/transmittance.py _sweep_level). */
static void sweep_level(clvol_host *h, cl_mem layout, long s_off, int n, double scale,
                        const double *l, int out_depth, cl_mem out, long out_off) {
    sweep_geom g = sweep_geometry(l);
    int width = n >= h->sweep_vmin ? h->lanes : 1;
    cl_kernel k = width > 1 ? h->k_sweepL : h->k_sweep1;
    if (!k) fail(BUNDLE, "%s: program transmittance_w%s is not in the bundle's programs", h->mf.where,
                 width > 1 ? "L" : "1");
    int *stab = xmalloc(sizeof(int) * 3 * (size_t)n);
    float *sftab = xmalloc(sizeof(float) * 2 * (size_t)n);
    int umin_all = 0, umax_all = 0, vmin_all = 0, vmax_all = 0;
    for (int j = 0; j < n; ++j) {
        double fu = (double)j * g.su, fv = (double)j * g.sv;
        int iu = (int)floor(fu), iv = (int)floor(fv);
        stab[3 * j] = g.sa > 0 ? n - 1 - j : j;
        stab[3 * j + 1] = iu;
        stab[3 * j + 2] = iv;
        sftab[2 * j] = (float)(fu - iu);
        sftab[2 * j + 1] = (float)(fv - iv);
        if (j == 0 || iu < umin_all) umin_all = iu;
        if (j == 0 || iu > umax_all) umax_all = iu;
        if (j == 0 || iv < vmin_all) vmin_all = iv;
        if (j == 0 || iv > vmax_all) vmax_all = iv;
    }
    int SB = h->sweep_block, nb = (n + SB - 1) / SB;
    int *btab = xmalloc(sizeof(int) * 4 * (size_t)nb);
    int bw_chunks = 0, brows = 0;
    long n_col_max = 0;
    for (int b = 0; b < nb; ++b) {
        int umin = 0, umax = 0, vmin = 0, vmax = 0;
        for (int j = b * SB; j < n && j < (b + 1) * SB; ++j) {
            int iu = stab[3 * j + 1], iv = stab[3 * j + 2];
            if (j == b * SB || iu < umin) umin = iu;
            if (j == b * SB || iu > umax) umax = iu;
            if (j == b * SB || iv < vmin) vmin = iv;
            if (j == b * SB || iv > vmax) vmax = iv;
        }
        int chunks = (umax - umin + n + 1 + width - 1) / width, rows = vmax - vmin + n + 1;
        btab[4 * b] = umin;
        btab[4 * b + 1] = vmin;
        btab[4 * b + 2] = chunks;
        btab[4 * b + 3] = rows;
        if (chunks > bw_chunks) bw_chunks = chunks;
        if (rows > brows) brows = rows;
        if ((long)chunks * rows > n_col_max) n_col_max = (long)chunks * rows;
    }
    int ou = -umin_all, ov = -vmin_all;
    int cw = umax_all + ou + n + width + 2;
    int col_rows = vmax_all + ov + n + 1;
    cl_mem col = zeros(h, 4 * (size_t)col_rows * (size_t)cw);
    int bw = bw_chunks * width;
    cl_mem bb = buffer(h, 4 * 2 * (size_t)SB * (size_t)brows * (size_t)bw, NULL);
    int n_col = (int)padded((size_t)n_col_max, (size_t)h->sweep_group);
    long n_vox = (width > 1 && g.a == 0) ? (long)n * n / width : (long)SB * n * (n / width);
    cl_mem d_stab = buffer(h, sizeof(int) * 3 * (size_t)n, stab);
    cl_mem d_sftab = buffer(h, sizeof(float) * 2 * (size_t)n, sftab);
    cl_mem d_btab = buffer(h, sizeof(int) * 4 * (size_t)nb, btab);
    set_args(k, "miiiifffmiiimiimmmiiimii", layout, (int)s_off, n, g.a, g.sa, g.su, g.sv,
             scale * g.inv_la / 6.0, col, cw, ou, ov, bb, bw, brows, d_stab, d_sftab, d_btab, 0,
             nb, out_depth, out, (int)out_off, n_col);
    for (int b = 0; b <= nb; ++b) {
        cl_int bv = b;
        CL(clSetKernelArg(k, 18, sizeof bv, &bv));
        launch(h, k, padded((size_t)(n_col + n_vox), (size_t)h->sweep_group), (size_t)h->sweep_group);
    }
    xfree(stab);
    xfree(sftab);
    xfree(btab);
}

/* The render-time (tau, C) grid of every level (clvol/kernels/gather.py bake_render_grid). */
static void bake(clvol_host *h) {
    int L = h->L, n0 = h->base, first = 0;
    long scratch = 1;
    for (int lvl = 0; lvl < L && (n0 >> lvl) >= h->bake_min; ++lvl) {
        long size = 0;
        for (int mm = lvl + 1; mm < L; ++mm) size += (long)(n0 >> mm) * (n0 >> mm) * (n0 >> lvl);
        if (size > scratch) scratch = size;
        first = lvl + 1;
    }
    if (first > 0) {
        cl_mem xbuf = buffer(h, 4 * (size_t)scratch, NULL);
        for (int lvl = 0; lvl < first; ++lvl) {
            int n = n0 >> lvl, log2n = 0;
            while ((1 << log2n) < n) ++log2n;
            int xoff[MAX_LEVELS] = {0};
            long size = 0;
            for (int mm = lvl + 1; mm < L; ++mm) {
                int nm = n0 >> mm;
                xoff[mm] = (int)size;
                size += (long)nm * nm * n;
                set_args(h->k_xpass, "miiiimi", h->d_graded, (int)h->loff[mm], nm, n, log2n, xbuf,
                         xoff[mm]);
                launch(h, h->k_xpass, padded((size_t)nm * nm * n, (size_t)h->pad), 0);
            }
            cl_mem d_xoff = buffer(h, sizeof(int) * (size_t)L, xoff);
            int span = n < h->bake_span ? n : h->bake_span;
            set_args(h->k_rows, "mmmmmiiiifmfm", h->d_pyr, h->d_graded, xbuf, h->d_loff, d_xoff, L,
                     n0, lvl, log2n, h->density_scale * (h->cube_size / (double)n), h->d_wbuf,
                     h->level_bias, h->d_baked);
            /* taufac as the Python host rounds it: float32 of density_scale * voxel size */
            launch(h, h->k_rows, padded((size_t)n * n * n / (size_t)span, (size_t)h->pad), 0);
        }
    }
    if (first < L) {
        set_args(h->k_small, "mmmiiimmfm", h->d_pyr, h->d_graded, h->d_loff, L, n0, first,
                 h->d_taufac, h->d_wbuf, h->level_bias, h->d_baked);
        launch(h, h->k_small, padded((size_t)(h->pyr_size - h->loff[first]), (size_t)h->pad), 0);
    }
}

/* ------------------------------------------------------------------------- the bundle */

/* A kernel argument block as the bundle wrote it (raymarch.<name>, cl/include/blocks.h), of
 * the 16 floats this libclvol passes (host.<name>_floats). */
static void read_block(const manifest *m, const char *name, double out[16]) {
    char key[64];
    snprintf(key, sizeof key, "host.%s_floats", name);
    if (mf_int(m, key) != 16)
        fail(BUNDLE, "%s: %s = %d: this libclvol passes 16 floats", m->where, key, mf_int(m, key));
    snprintf(key, sizeof key, "raymarch.%s", name);
    mf_doubles(m, key, out, 16);
}

static void read_host_constants(clvol_host *h) {
    const manifest *m = &h->mf;
    h->pad = mf_int_in(m, "host.pad", 1, 1024);
    h->sweep_pad = mf_int_in(m, "host.sweep_pad", 1, 1024);
    h->sweep_block = mf_int_in(m, "host.sweep_block", 1, 1024);
    h->sweep_slack = mf_int_in(m, "host.sweep_slack", 0, 4096);
    h->sweep_group = mf_int_in(m, "host.sweep_group", 1, 1024);
    h->sweep_vmin = mf_int_in(m, "host.sweep_vector_min_n", 1, 4096);
    h->bake_min = mf_int_in(m, "host.bake_min_row_level", 1, 4096);
    h->bake_span = mf_int_in(m, "host.bake_span", 1, 4096);
    h->bake_pad = mf_int_in(m, "host.bake_pad", 0, 4096);
    h->sort_bits = mf_int_in(m, "host.sort_bits", 1, 10);
    h->cfg_dim = mf_int_in(m, "host.config_dim", 3, 64);
    h->cfg_albedo = mf_int_in(m, "host.config_albedo", 0, h->cfg_dim - 1);
    h->cfg_alpha = mf_int_in(m, "host.config_alpha", 0, h->cfg_dim - 1);
    if (h->cfg_albedo > 16 || h->cfg_alpha == h->cfg_albedo)
        fail(BUNDLE, "%s: host.config_albedo %d / host.config_alpha %d: the phase fields come "
             "first (at most 16), then two distinct slots", m->where, h->cfg_albedo, h->cfg_alpha);
    h->tile = mf_int_in(m, "host.raymarch_tile", 1, 16);
    h->rm_local = mf_int_in(m, "host.raymarch_local_size", 1, 1024);
}

/* Largest optical thickness of the volume at density scale 1 along x, y or z rows (the
 * Python host's clvol/volume/stats.py volume_stats: row sums in float64 times the cell). */
static double unit_optical_thickness(const float *d, int nx, int ny, int nz, const double *bmin,
                                     const double *bmax) {
    double cell[3] = {(bmax[0] - bmin[0]) / nx, (bmax[1] - bmin[1]) / ny, (bmax[2] - bmin[2]) / nz};
    double *sx = xcalloc((size_t)ny * nz, sizeof(double));
    double *sy = xcalloc((size_t)nx * nz, sizeof(double));
    double *sz = xcalloc((size_t)nx * ny, sizeof(double));
    for (long z = 0; z < nz; ++z)
        for (long y = 0; y < ny; ++y)
            for (long x = 0; x < nx; ++x) {
                double v = d[(z * ny + y) * nx + x];
                sx[z * ny + y] += v;
                sy[z * nx + x] += v;
                sz[y * nx + x] += v;
            }
    double mx = 0, my = 0, mz = 0;
    for (long i = 0; i < (long)ny * nz; ++i) mx = fmax(mx, sx[i]);
    for (long i = 0; i < (long)nx * nz; ++i) my = fmax(my, sy[i]);
    for (long i = 0; i < (long)nx * ny; ++i) mz = fmax(mz, sz[i]);
    xfree(sx);
    xfree(sy);
    xfree(sz);
    return fmax(fmax(mx * cell[0], my * cell[1]), mz * cell[2]);
}

/* The stochastic view source's keys (clvol bundle --ms stochastic: view.*). */
static void read_view_keys(clvol_host *h) {
    const manifest *m = &h->mf;
    view_state *v = &h->vs;
    v->block = mf_int_in(m, "view.block", 1, 64);
    v->block_auto = mf_int_in(m, "view.block_auto", 0, 1);
    v->blocks_across = mf_int_in(m, "view.blocks_across", 1, 1 << 16);
    v->samples = mf_int_in(m, "view.samples", 1, 4096);
    v->still_samples = mf_int_in(m, "view.still_samples", 1, 1 << 20);
    v->move_history = mf_int_in(m, "view.move_history", 0, 1 << 20);
    v->min_samples = mf_int_in(m, "view.min_samples", 1, 4096);
    double seed = mf_double(m, "view.seed");
    if (!(seed >= 0 && seed < 4294967296.0 && seed == floor(seed)))
        fail(BUNDLE, "%s: view.seed = %g: an integer in [0, 2^32)", m->where, seed);
    v->seed = (uint32_t)seed;
    v->step_factor = mf_double(m, "view.step_factor");
    if (!(v->step_factor > 0 && isfinite(v->step_factor)))
        fail(BUNDLE, "%s: view.step_factor must be finite and > 0", m->where);
    v->reset = 1;
}

/* Read the manifest and the host constants, build the programs the bundle lists and load
 * what no change can invalidate: the network's weights and the gather's tables. The
 * density is read here and uploaded by the volume stage. */
static void open_bundle(clvol_host *h) {
    const manifest *m = &h->mf;
    double t0 = now_seconds();
    if (strcmp(mf_str(m, "format"), "clvol-bundle") != 0 || mf_int(m, "format_version") != 3)
        fail(BUNDLE, "%s: not a clvol-bundle of format_version 3 (write it again with this "
             "version's clvol bundle)", m->where);
    read_host_constants(h);
    int dims[3];
    mf_ints(m, "density.dims", dims, 3);
    h->nx = dims[0], h->ny = dims[1], h->nz = dims[2];
    if (h->nx < 1 || h->ny < 1 || h->nz < 1) fail(BUNDLE, "%s: density.dims must be >= 1", m->where);
    if ((double)h->nx * h->ny * h->nz > 2147483647.0 / 4)
        fail(BUNDLE, "%s: density.dims %d x %d x %d: too many voxels", m->where, h->nx, h->ny, h->nz);
    mf_doubles(m, "density.bbox_min", h->bmin, 3);
    mf_doubles(m, "density.bbox_max", h->bmax, 3);
    for (int a = 0; a < 3; ++a)
        if (!(isfinite(h->bmin[a]) && isfinite(h->bmax[a]) && h->bmax[a] > h->bmin[a]))
            fail(BUNDLE, "%s: density.bbox_min/max: an empty or non-finite box", m->where);
    /* clvol/volume/grid.py check_bbox: a side shorter than CLVOL_MIN_RELATIVE_SIDE of the
     * box's scale cannot be resolved in float32 */
    double scale = 0.0;
    for (int a = 0; a < 3; ++a)
        scale = fmax(scale, fmax(h->bmax[a] - h->bmin[a], fmax(fabs(h->bmin[a]), fabs(h->bmax[a]))));
    char thin[8] = "";
    size_t nthin = 0;
    for (int a = 0; a < 3; ++a)
        if (h->bmax[a] - h->bmin[a] < CLVOL_MIN_RELATIVE_SIDE * scale) {
            if (nthin) thin[nthin++] = ',', thin[nthin++] = ' ';
            thin[nthin++] = "xyz"[a];
            thin[nthin] = '\0';
        }
    if (thin[0])
        fail(BUNDLE, "%s: density.bbox_min/max: the box (%g, %g, %g) .. (%g, %g, %g) is too thin "
             "on %s (sides %g, %g, %g): each side must be at least %g of %g, the box's scale, "
             "to be resolved in float32", m->where, h->bmin[0], h->bmin[1], h->bmin[2],
             h->bmax[0], h->bmax[1], h->bmax[2], thin, h->bmax[0] - h->bmin[0],
             h->bmax[1] - h->bmin[1], h->bmax[2] - h->bmin[2], CLVOL_MIN_RELATIVE_SIDE, scale);
    size_t count = (size_t)h->nx * h->ny * h->nz;
    h->density = keep(read_raw4(h->dir, mf_str(m, "density.file"), count));
    h->density_scale = mf_double(m, "medium.density_scale");
    mf_doubles(m, "medium.albedo", h->albedo, 3);
    read_block(m, "medium", h->medium);
    h->medium_ds_slot = mf_int_in(m, "host.medium_density_scale", 0, 15);
    h->medium_albedo_slot = mf_int_in(m, "host.medium_albedo", 0, 13);
    read_block(m, "light", h->light_block);
    h->light_dir_slot = mf_int_in(m, "host.light_direction", 0, 13);
    h->light_irradiance_slot = mf_int_in(m, "host.light_irradiance", 0, 13);
    h->lit = mf_int(m, "raymarch.lit");
    const char *src = mf_str(m, "raymarch.ms_source");
    if (strcmp(src, "network") == 0) h->source = SOURCE_NETWORK;
    else if (strcmp(src, "stochastic") == 0) h->source = SOURCE_NETWORK, h->view = 1;
    else if (strcmp(src, "wrenninge") == 0) h->source = SOURCE_WRENNINGE;
    else if (strcmp(src, "none") == 0) h->source = SOURCE_NONE;
    else fail(BUNDLE, "%s: raymarch.ms_source = %s: this host runs network, stochastic, none or wrenninge", m->where, src);
    /* none and wrenninge are the kernel's own (raymarch.cl's -D MS_SOURCE): no network */
    h->network = h->lit && h->source == SOURCE_NETWORK;
    h->grey = mf_int(m, "medium.grey");
    h->channels = mf_int(m, "raymarch.channels");
    h->light_res = mf_int_in(m, "raymarch.light_resolution", 1, 4096);
    h->light_tau = mf_int(m, "raymarch.light_tau");
    h->block = mf_int_in(m, "raymarch.block", 1, 1 << 20);
    h->step = mf_double(m, "raymarch.step");
    h->threshold = mf_double(m, "raymarch.threshold");
    mf_doubles(m, "raymarch.octave_abc", h->octave_abc, 3);
    mf_doubles(m, "medium.config_phase", h->config_phase, h->cfg_albedo);
    h->step_voxels = mf_double(m, "raymarch.step_voxels");
    if (!(h->step > 0 && isfinite(h->step) && h->step_voxels > 0 && isfinite(h->step_voxels)))
        fail(BUNDLE, "%s: raymarch.step must be finite and > 0", m->where);
    h->width = mf_int(m, "camera.width");
    h->height = mf_int(m, "camera.height");
    if (h->width < 1 || h->height < 1) fail(BUNDLE, "%s: camera size must be >= 1", m->where);
    mf_doubles(m, "light.irradiance", h->irradiance, 3);
    mf_doubles(m, "light.background", h->background, 3);
    /* the smallest cube centred on the box (clvol/kernels/pyramid.py cube_of) */
    double ext = 0.0;
    for (int a = 0; a < 3; ++a) ext = fmax(ext, h->bmax[a] - h->bmin[a]);
    h->cube_size = ext;
    for (int a = 0; a < 3; ++a) h->cube_min[a] = 0.5 * (h->bmin[a] + h->bmax[a]) - 0.5 * ext;

    /* the programs the bundle lists (what the Python host builds for this scene: unlit scenes
     * need only the majorant and the march, analytic sources no network) */
    for (int p = 0; p < P_PACK; ++p)
        if (mf_has_word(m, "programs", PROGRAM_NAMES[p]))
            h->prog[p] = build_program_at(h, h->dir, m, PROGRAM_NAMES[p]);
    if (!h->prog[P_MAJORANT] || !h->prog[P_RAYMARCH])
        fail(BUNDLE, "%s: programs must list majorant and raymarch", m->where);
    /* the library's own: total + alpha into one RGBA image */
    static const char pack_src[] =
        "__kernel void pack_rgba(__global const float *rgb, __global const float *alpha,\n"
        "                        __global float *rgba, int n) {\n"
        "    int i = get_global_id(0);\n"
        "    if (i >= n) return;\n"
        "    rgba[4 * i] = rgb[3 * i]; rgba[4 * i + 1] = rgb[3 * i + 1];\n"
        "    rgba[4 * i + 2] = rgb[3 * i + 2]; rgba[4 * i + 3] = alpha[i];\n"
        "}\n";
    h->prog[P_PACK] = build_source(h, pack_src, "", "pack_rgba (libclvol)");
    h->t_build = now_seconds() - t0;
    h->k_majorant = kernel(h, P_MAJORANT, "majorant_build");
    h->k_pack = kernel(h, P_PACK, "pack_rgba");
    if (h->lit) {
        if (!h->prog[P_TRANS]) fail(BUNDLE, "%s: a lit scene's programs must list transmittance", m->where);
        h->k_layout = kernel(h, P_TRANS, "sweep_layout");
        /* the widths the bundle's levels use (one of them when only the light field is swept) */
        if (h->prog[P_TRANS_W1]) h->k_sweep1 = kernel(h, P_TRANS_W1, "transmittance_sweep_block");
        if (h->prog[P_TRANS_WL]) h->k_sweepL = kernel(h, P_TRANS_WL, "transmittance_sweep_block");
    }
    if (h->network) {
        h->net_chunk = mf_int_in(m, "host.network_chunk", 1, 1 << 24);  /* queries a launch */
        for (int p = P_PYRAMID; p <= P_MLP; ++p)
            if (p != P_MAJORANT && p != P_TRANS_W1 && p != P_TRANS_WL && !h->prog[p])
                fail(BUNDLE, "%s: the network's programs must list %s", m->where, PROGRAM_NAMES[p]);
        h->k_mip = kernel(h, P_PYRAMID, "mip_reduce");
        h->k_xpass = kernel(h, P_BAKE, "bake_xpass");
        h->k_rows = kernel(h, P_BAKE, "bake_rows");
        h->k_small = kernel(h, P_BAKE, "bake_small");
        h->k_gather = kernel(h, P_GATHER, "gather");
        h->k_mlp = kernel(h, P_MLP, "mlp_forward");
        if (h->view) {
            if (!h->prog[P_VIEWDEPTH])
                fail(BUNDLE, "%s: the stochastic view's programs must list viewdepth", m->where);
            h->k_viewdepth = kernel(h, P_VIEWDEPTH, "view_depths");
            read_view_keys(h);
        }
    }
    h->k_raymarch = kernel(h, P_RAYMARCH, "raymarch");
    h->d_dummy = buffer(h, 4, NULL);
    if (!h->network) return;

    /* the network's pyramid layout, weights and the gather's tables */
    h->base = mf_int_in(m, "network.base_resolution", 1, 1024);
    h->L = mf_int(m, "network.n_levels");
    if (h->L < 1 || h->L > MAX_LEVELS || (h->base >> (h->L - 1)) != 1)
        fail(BUNDLE, "%s: network.n_levels = %d does not match base %d", m->where, h->L, h->base);
    h->pyr_size = 0;
    for (int l = 0; l < h->L; ++l) {
        long nl = h->base >> l;
        h->loff[l] = h->pyr_size;
        h->pyr_size += nl * nl * nl;
    }
    int loff32[MAX_LEVELS];
    for (int l = 0; l < h->L; ++l) loff32[l] = (int)h->loff[l];
    h->d_loff = buffer(h, sizeof(int) * (size_t)h->L, loff32);
    h->lam = mf_double(m, "network.lambda");
    int range[2];
    mf_ints(m, "network.params", range, 2);
    int lwr[2];
    mf_ints(m, "network.level_weights", lwr, 2);
    if (lwr[1] != h->L) fail(BUNDLE, "%s: %d level weights for %d levels", m->where, lwr[1], h->L);
    int lb = mf_int(m, "network.level_bias");
    if (range[0] < 0 || range[1] < 1 || lwr[0] < 0 || lb < 0)
        fail(BUNDLE, "%s: network.params / level_weights / level_bias: negative offsets", m->where);
    char *path = path_join(h->dir, mf_str(m, "network.file"));
    size_t nbytes;
    float *net = (float *)read_file(path, &nbytes);
    if (nbytes / 4 < (size_t)range[0] + range[1] || nbytes / 4 < (size_t)lwr[0] + lwr[1]
        || nbytes / 4 <= (size_t)lb)
        fail(BUNDLE, "%s: %zu bytes, too short for the tensors the manifest names", path, nbytes);
    h->d_params = buffer(h, 4 * (size_t)range[1], net + range[0]);
    for (int l = 0; l < h->L; ++l) h->level_w[l] = net[lwr[0] + l];
    h->level_bias = net[lb];
    xfree(net);
    xfree(path);
    h->d_wbuf = buffer(h, sizeof(float) * (size_t)h->L, h->level_w);
    h->d_taufac = buffer(h, sizeof(float) * (size_t)h->L, NULL);   /* per density scale */
    h->np_ = mf_int_in(m, "gather.np", 1, 1 << 16);
    h->npad = mf_int_in(m, "gather.npad", h->np_, 1 << 16);
    h->n_alpha = mf_int_in(m, "gather.n_alpha", 1, 1 << 16);
    float *tpl = read_raw4(h->dir, mf_str(m, "gather.templates"), 3 * (size_t)h->npad);
    int *pinfo = read_raw4(h->dir, mf_str(m, "gather.pinfo"), (size_t)h->npad);
    float *ptab = read_raw4(h->dir, mf_str(m, "gather.phase_table"), (size_t)h->n_alpha * h->npad);
    /* The gather indexes levels and voxels with these: a level outside the pyramid or a
     * non-finite position would read outside its buffers (a fuzzed bundle crashed the
     * kernel that way), so they are checked here. */
    for (int j = 0; j < h->npad; ++j) {
        if (pinfo[j] >= h->L || pinfo[j] < -4)
            fail(BUNDLE, "%s: gather.pinfo[%d] = %d: must be a level 0..%d or a highlight layer "
                 "-1..-4", m->where, j, pinfo[j], h->L - 1);
        for (int a = 0; a < 3; ++a)
            if (!isfinite(tpl[(size_t)a * h->npad + j]))
                fail(BUNDLE, "%s: gather.templates: point %d is not finite", m->where, j);
    }
    for (size_t j = 0; j < (size_t)h->n_alpha * h->npad; ++j)
        if (!isfinite(ptab[j]))
            fail(BUNDLE, "%s: gather.phase_table: entry %zu is not finite", m->where, j);
    double hl[4];
    mf_doubles(m, "gather.hl_spacing", hl, 4);
    for (int k = 0; k < 4; ++k)
        if (!(isfinite(hl[k]) && hl[k] >= 0.0))
            fail(BUNDLE, "%s: gather.hl_spacing[%d] = %g: must be finite and >= 0", m->where, k, hl[k]);
    float hlf[4] = {(float)hl[0], (float)hl[1], (float)hl[2], (float)hl[3]};
    h->d_tpl = buffer(h, 4 * 3 * (size_t)h->npad, tpl);
    h->d_pinfo = buffer(h, 4 * (size_t)h->npad, pinfo);
    h->d_ptab = buffer(h, 4 * (size_t)h->n_alpha * h->npad, ptab);
    h->d_hl = buffer(h, sizeof hlf, hlf);
    xfree(tpl);
    xfree(pinfo);
    xfree(ptab);
    h->d_pyr = buffer(h, 4 * (size_t)h->pyr_size, NULL);
    h->d_graded = buffer(h, 4 * (size_t)h->pyr_size, NULL);
    h->d_baked = buffer(h, 4 * (size_t)(2 * h->pyr_size + h->bake_pad), NULL);
    const cl_float z = 0.0f;
    CL(clEnqueueFillBuffer(h->queue, h->d_baked, &z, sizeof z, 4 * (size_t)(2 * h->pyr_size),
                           4 * (size_t)h->bake_pad, 0, NULL, NULL));
    if (h->view) return;   /* its points are drawn each frame: no lattice */
    /* the lattice points the network evaluates (recomputed by clvol_set_density) */
    mf_ints(m, "network.ms_resolution", h->res, 3);
    long N = (long)h->res[0] * h->res[1] * h->res[2];
    if (h->res[0] < 1 || h->res[1] < 1 || h->res[2] < 1 || N > 1L << 24)
        fail(BUNDLE, "%s: network.ms_resolution out of range", m->where);
    mf_doubles(m, "network.ms_bbox_min", h->ms_min, 3);
    mf_doubles(m, "network.ms_bbox_max", h->ms_max, 3);
    h->n_active = mf_int(m, "network.active_points");
    if (h->n_active < 0 || h->n_active > N)
        fail(BUNDLE, "%s: network.active_points = %d: must be in [0, %ld]", m->where, h->n_active, N);
    h->active = keep(read_raw4(h->dir, mf_str(m, "network.active_file"), (size_t)h->n_active));
    for (int k = 0; k < h->n_active; ++k)
        if (h->active[k] < 0 || h->active[k] >= N || (k && h->active[k] <= h->active[k - 1]))
            fail(BUNDLE, "%s: network.active_file: index %d at %d is out of range or not ascending",
                 m->where, h->active[k], k);
}

/* The lattice points with density within reach (the Python host's clvol/render/ms/network.py
 * lattice_reach_mask with lattice_reach: one lattice cell plus one voxel (largest side) plus
 * one step (smallest side)); the others never reach the image. Replaces h->active. */
static void find_active_points(clvol_host *h) {
    int n[3] = {h->nx, h->ny, h->nz};
    double cell[3], maxc = 0, minc = INFINITY;
    for (int a = 0; a < 3; ++a) {
        cell[a] = (h->bmax[a] - h->bmin[a]) / n[a];
        maxc = fmax(maxc, cell[a]);
        minc = fmin(minc, cell[a]);
    }
    double reach = maxc + h->step_voxels * minc;
    /* summed-area table of occupied voxels, [nz+1][ny+1][nx+1] */
    long sx = n[0] + 1, sy = n[1] + 1;
    long *sat = xcalloc((size_t)sx * sy * (n[2] + 1), sizeof(long));
    for (long z = 1; z <= n[2]; ++z)
        for (long y = 1; y <= n[1]; ++y)
            for (long x = 1; x <= n[0]; ++x) {
                long occ = h->density[((z - 1) * n[1] + (y - 1)) * n[0] + (x - 1)] > 0.0f;
                sat[(z * sy + y) * sx + x] = occ + sat[((z - 1) * sy + y) * sx + x]
                    + sat[(z * sy + y - 1) * sx + x] + sat[(z * sy + y) * sx + x - 1]
                    - sat[((z - 1) * sy + y - 1) * sx + x] - sat[((z - 1) * sy + y) * sx + x - 1]
                    - sat[(z * sy + y - 1) * sx + x - 1] + sat[((z - 1) * sy + y - 1) * sx + x - 1];
            }
    long *lo[3], *hi[3];
    for (int a = 0; a < 3; ++a) {
        lo[a] = xmalloc(sizeof(long) * (size_t)h->res[a]);
        hi[a] = xmalloc(sizeof(long) * (size_t)h->res[a]);
        double ext = h->bmax[a] - h->bmin[a], cell_l = ext / h->res[a], cell_d = ext / n[a];
        for (int i = 0; i < h->res[a]; ++i) {
            double p = (i + 0.5) * cell_l, r = cell_l + reach;
            lo[a][i] = (long)clampd(ceil((p - r) / cell_d - 0.5), 0, n[a]);
            hi[a][i] = (long)clampd(floor((p + r) / cell_d - 0.5) + 1, 0, n[a]);
        }
    }
    long N = (long)h->res[0] * h->res[1] * h->res[2], k = 0;
    int *active = xmalloc(sizeof(int) * (size_t)(N > 0 ? N : 1));
    for (int iz = 0; iz < h->res[2]; ++iz)
        for (int iy = 0; iy < h->res[1]; ++iy)
            for (int ix = 0; ix < h->res[0]; ++ix) {
                long z0 = lo[2][iz], z1 = hi[2][iz], y0 = lo[1][iy], y1 = hi[1][iy],
                     x0 = lo[0][ix], x1 = hi[0][ix];
#define S(z, y, x) sat[((z) * sy + (y)) * sx + (x)]
                long c = S(z1, y1, x1) - S(z0, y1, x1) - S(z1, y0, x1) - S(z1, y1, x0)
                         + S(z0, y0, x1) + S(z0, y1, x0) + S(z1, y0, x0) - S(z0, y0, x0);
#undef S
                if (c > 0) active[k++] = (int)(((long)iz * h->res[1] + iy) * h->res[0] + ix);
            }
    for (int a = 0; a < 3; ++a) {
        xfree(lo[a]);
        xfree(hi[a]);
    }
    xfree(sat);
    free(h->active);
    h->active = keep(active);
    h->n_active = (int)k;
    /* the frame buffers are sized by the number of points: made again at the next frame */
    cl_mem *fb[] = {&h->d_points, &h->d_omegas, &h->d_order, &h->d_config, &h->d_feats,
                    &h->d_tenter, &h->d_fms};
    for (size_t i = 0; i < sizeof fb / sizeof fb[0]; ++i) release_tracked(h, fb[i]);
    h->net_cap = 0;
}

/* ------------------------------------------------------------------------ the stages */

/* V: the density and what is made from it alone (majorant, light cube, pyramid). */
static void volume_stage(clvol_host *h) {
    double t0 = now_seconds();
    size_t count = (size_t)h->nx * h->ny * h->nz;
    cl_mem *old[] = {&h->d_density, &h->d_majorant, &h->d_light_pyr, &h->d_light};
    for (size_t i = 0; i < sizeof old / sizeof old[0]; ++i) release_tracked(h, old[i]);
    for (int a = 0; a < 3; ++a) {   /* the sweep layouts are copies of the old density */
        release_tracked(h, &h->d_light_layout[a]);
        release_tracked(h, &h->d_graded_layout[a]);
    }
    h->d_density = buffer(h, 4 * count, h->density);
    /* majorant grid (clvol/kernels/majorant.py): 3-D launch, first dimension padded */
    h->mx = (h->nx + h->block - 1) / h->block;
    h->my = (h->ny + h->block - 1) / h->block;
    h->mz = (h->nz + h->block - 1) / h->block;
    h->d_majorant = buffer(h, 4 * (size_t)h->mx * h->my * h->mz, NULL);
    set_args(h->k_majorant, "miiiiiiim", h->d_density, h->nx, h->ny, h->nz, h->block, h->mx,
             h->my, h->mz, h->d_majorant);
    size_t gs[3] = {padded((size_t)h->mx, (size_t)h->pad), (size_t)h->my, (size_t)h->mz};
    CL(clEnqueueNDRangeKernel(h->queue, h->k_majorant, 3, NULL, gs, NULL, 0, NULL, NULL));
    if (h->lit) {
        /* light field's cube: level 0 only (the sweep reads nothing else) */
        int n = h->light_res;
        float *lv0 = xmalloc(4 * (size_t)n * n * n);
        resample_to_cube(h, n, lv0);
        h->d_light_pyr = buffer(h, 4 * (size_t)n * n * n, lv0);
        xfree(lv0);
        h->d_light = buffer(h, 4 * (size_t)n * n * n, NULL);
    }
    if (h->network) {
        /* network pyramid: base^3 on the host, the mip chain on the device */
        float *pyr = xmalloc(4 * (size_t)h->base * h->base * h->base);
        resample_to_cube(h, h->base, pyr);
        CL(clEnqueueWriteBuffer(h->queue, h->d_pyr, CL_TRUE, 0, 4 * (size_t)h->base * h->base * h->base,
                                pyr, 0, NULL, NULL));
        xfree(pyr);
        for (int l = 1; l < h->L; ++l) {
            int nd = h->base >> l;
            set_args(h->k_mip, "miii", h->d_pyr, (int)h->loff[l - 1], (int)h->loff[l], nd);
            launch(h, h->k_mip, padded((size_t)nd * nd * nd, (size_t)h->pad), 0);
        }
    }
    CL(clFinish(h->queue));
    h->counts[CLVOL_STAGE_VOLUME]++;
    h->t_volume = now_seconds() - t0;
}

/* L: the light field and, for the network, the graded transmittance and the bake, for the
 * light toward h->light_dir at h->density_scale. Scratch buffers are released at the end. */
static void light_stage(clvol_host *h) {
    double t0 = now_seconds();
    const double *l = h->light_dir;
    sweep_geom g = sweep_geometry(l);
    long s_off[MAX_LEVELS], gs_off[MAX_LEVELS];
    long zero = 0;
    int n = h->light_res;
    cl_mem lay = sweep_layout(h, h->d_light_pyr, &zero, n, 1, g.a, s_off, &h->d_light_layout[g.a]);
    cl_mem glay = h->network ? sweep_layout(h, h->d_pyr, h->loff, h->base, h->L, g.a, gs_off,
                                            &h->d_graded_layout[g.a]) : NULL;
    int mark = h->n_mems;   /* the sweeps' scratch buffers, released at the end */
    /* light field: lambda = 1 on the light cube's level 0 */
    sweep_level(h, lay, s_off[0], n, h->density_scale * (h->cube_size / n), l, h->light_tau,
                h->d_light, 0);
    if (h->network) {
        /* graded transmittance: every level l with lambda^(l+1) */
        for (int lv = 0; lv < h->L; ++lv) {
            int nl = h->base >> lv;
            double scale = pow(h->lam, lv + 1) * h->density_scale * (h->cube_size / nl);
            sweep_level(h, glay, gs_off[lv], nl, scale, l, 0, h->d_graded, h->loff[lv]);
        }
        /* taufac as the Python host rounds it: float32 of density_scale * voxel size */
        float taufac[MAX_LEVELS];
        for (int lv = 0; lv < h->L; ++lv)
            taufac[lv] = (float)(h->density_scale * (h->cube_size / (double)(h->base >> lv)));
        CL(clEnqueueWriteBuffer(h->queue, h->d_taufac, CL_TRUE, 0, sizeof(float) * (size_t)h->L,
                                taufac, 0, NULL, NULL));
        bake(h);
    }
    CL(clFinish(h->queue));
    /* the scratch of this stage is the newest part of the list */
    for (int i = mark; i < h->n_mems; ++i) CL(clReleaseMemObject(h->mems[i]));
    h->n_mems = mark;
    h->counts[CLVOL_STAGE_LIGHT]++;
    h->t_light = now_seconds() - t0;
}

static uint32_t spread_bits(uint32_t v, int bits) {
    uint32_t out = 0;
    for (int b = 0; b < bits; ++b) out |= ((v >> b) & 1u) << (3 * b);
    return out;
}

/* F_ms at n points toward unit directions omega (gather + MLP, the Python host's
 * NetworkSource.evaluate): fms[q * C + c], clamped at 0; a non-finite value fails, naming
 * `what` and the point (its index + `first`). Queries run in Morton order of their coarse
 * cell (only speed: every query is computed alone). The buffers grow to the largest n seen
 * (h->net_cap); network_at cuts bigger sets into launches of host.network_chunk. */
static void network_launch(clvol_host *h, int n, const double *pts_d, const double *oms_d,
                           float *fms, const char *what, long first) {
    const manifest *m = &h->mf;
    const double *l = h->light_dir, *alb = h->albedo;
    int C = h->channels, nq = n > 0 ? n : 1;   /* nq: buffers are never empty */
    /* config layout from the bundle: the phase fields [0, cfg_albedo), then the albedo and
     * alpha slots (clvol/features/layout.py CONFIG_FIELDS) */
    const int D = h->cfg_dim, NPH = h->cfg_albedo;
    const double *cphase = h->config_phase;
    float *pts = xmalloc(sizeof(float) * 3 * (size_t)nq);
    float *oms = xmalloc(sizeof(float) * 3 * (size_t)nq);
    float *cfg = xcalloc((size_t)D * (size_t)nq, sizeof(float));
    int *order = xmalloc(sizeof(int) * (size_t)nq);
    uint32_t *key = xmalloc(sizeof(uint32_t) * (size_t)nq);
    int cells = 1 << h->sort_bits;
    long nkeys = 1L << (3 * h->sort_bits);
    int *count = xcalloc((size_t)nkeys + 1, sizeof(int));
    for (int q = 0; q < n; ++q) {
        double mu = 0.0;
        uint32_t kk = 0;
        for (int a = 0; a < 3; ++a) {
            pts[3 * q + a] = (float)pts_d[3 * q + a];
            oms[3 * q + a] = (float)oms_d[3 * q + a];
            mu -= (double)oms[3 * q + a] * l[a];
            double gcell = (pts_d[3 * q + a] - h->cube_min[a]) * (cells / h->cube_size);
            uint32_t c = (uint32_t)clampd(gcell, 0.0, cells - 1);
            kk |= spread_bits(c, h->sort_bits) << a;
        }
        key[q] = kk;
        count[kk + 1]++;
        for (int f = 0; f < NPH; ++f) cfg[D * q + f] = (float)cphase[f];
        cfg[D * q + h->cfg_albedo] = (float)alb[0];
        cfg[D * q + h->cfg_alpha] = (float)acos(clampd(mu, -1.0, 1.0));
    }
    for (long i = 0; i < nkeys; ++i) count[i + 1] += count[i];
    for (int i = 0; i < n; ++i) order[count[key[i]]++] = i;
    xfree(count);
    xfree(key);
    if (nq > h->net_cap) {   /* made for the most queries so far, rewritten every frame */
        cl_mem *fb[] = {&h->d_points, &h->d_omegas, &h->d_order, &h->d_config, &h->d_feats,
                        &h->d_tenter, &h->d_fms};
        for (size_t i = 0; i < sizeof fb / sizeof fb[0]; ++i) release_tracked(h, fb[i]);
        h->net_cap = 0;
        h->d_points = buffer(h, sizeof(float) * 3 * (size_t)nq, NULL);
        h->d_omegas = buffer(h, sizeof(float) * 3 * (size_t)nq, NULL);
        h->d_order = buffer(h, sizeof(int) * (size_t)nq, NULL);
        h->d_config = buffer(h, sizeof(float) * (size_t)D * (size_t)nq, NULL);
        h->d_feats = buffer(h, sizeof(float) * 3 * (size_t)h->np_ * nq, NULL);
        h->d_tenter = buffer(h, sizeof(float) * (size_t)nq, NULL);
        h->d_fms = buffer(h, sizeof(float) * (size_t)C * nq, NULL);
        h->net_cap = nq;
    }
    if (n > 0) {
        CL(clEnqueueWriteBuffer(h->queue, h->d_points, CL_FALSE, 0, 12 * (size_t)n, pts, 0, NULL, NULL));
        CL(clEnqueueWriteBuffer(h->queue, h->d_omegas, CL_FALSE, 0, 12 * (size_t)n, oms, 0, NULL, NULL));
        CL(clEnqueueWriteBuffer(h->queue, h->d_order, CL_FALSE, 0, 4 * (size_t)n, order, 0, NULL, NULL));
        CL(clEnqueueWriteBuffer(h->queue, h->d_config, CL_FALSE, 0, sizeof(float) * (size_t)D * (size_t)n, cfg, 0, NULL, NULL));
        /* gather, render mode */
        cl_float4 cmin = f4(h->cube_min), light4 = f4(l), lg, lw;
        mf_float4(m, "medium.lobe_g", 4, &lg);
        mf_float4(m, "medium.lobe_w", 4, &lw);
        double wsum = h->level_bias;
        for (int i = 0; i < h->L; ++i) wsum += h->level_w[i];
        set_args(h->k_gather, "mmmmii4fmmmmmimm444fmimmm", h->d_pyr, h->d_graded, h->d_baked,
                 h->d_loff, h->L, h->base, &cmin, h->cube_size, h->d_dummy, h->d_tpl, h->d_pinfo,
                 h->d_hl, h->d_ptab, h->n_alpha, h->d_points, h->d_omegas, &light4, &lg, &lw,
                 (double)(float)wsum, h->d_order, n, h->d_feats, h->d_dummy, h->d_tenter);
        launch(h, h->k_gather, padded((size_t)n, (size_t)h->pad), 0);
        /* MLP: LANES queries per work-item; groups of one work-item on a CPU (private arrays
         * of ~105 KB each overflow PoCL's stack in bigger groups) */
        cl_float4 ca = {{0, 0, 0, 0}};
        if (C == 3)
            for (int c = 0; c < 3; ++c) ca.s[c] = (float)alb[c];
        set_args(h->k_mlp, "mmm4im", h->d_feats, h->d_config, h->d_params, &ca, n, h->d_fms);
        size_t items = (size_t)(n + h->lanes - 1) / (size_t)h->lanes;
        if (h->is_cpu)
            launch(h, h->k_mlp, items, 1);
        else
            launch(h, h->k_mlp, padded(items, (size_t)h->pad), 0);
        CL(clEnqueueReadBuffer(h->queue, h->d_fms, CL_TRUE, 0, sizeof(float) * (size_t)C * n, fms,
                               0, NULL, NULL));
    }
    /* F_ms: refuse non-finite, clamp at 0 (NetworkSource.evaluate) */
    for (long i = 0; i < (long)n * C; ++i) {
        if (!isfinite(fms[i]))
            fail(CLVOL_ERROR_OPENCL, "the network produced a non-finite F_ms at %s %ld", what,
                 first + i / C);
        if (!(fms[i] > 0.0f)) fms[i] = 0.0f;
    }
    xfree(pts);
    xfree(oms);
    xfree(cfg);
    xfree(order);
}

static void network_at(clvol_host *h, long n, const double *pts, const double *oms, float *fms,
                       const char *what) {
    long chunk = h->net_chunk;
    if (n <= chunk) {
        network_launch(h, (int)n, pts, oms, fms, what, 0);
        return;
    }
    for (long q = 0; q < n; q += chunk) {
        long k = n - q < chunk ? n - q : chunk;
        network_launch(h, (int)k, pts + 3 * q, oms + 3 * q, fms + (size_t)q * h->channels, what, q);
    }
}

/* F: F_ms at the active lattice points toward the camera, scattered into the planes
 * [C][gz][gy][gx] the march reads (0 at the other points). */
static void lattice_stage(clvol_host *h) {
    const double *origin = h->cam_origin;
    int C = h->channels;
    int N = h->res[0] * h->res[1] * h->res[2];
    /* the network runs at the active points only (n queries, in ascending lattice order:
     * the Python host's order); the others get F_ms = 0 */
    int n = h->n_active, nq = n > 0 ? n : 1;
    /* lattice: voxel centres over the box, [z][y][x], omega toward the camera */
    double *pts = xmalloc(sizeof(double) * 3 * (size_t)nq);
    double *oms = xmalloc(sizeof(double) * 3 * (size_t)nq);
    for (int q = 0; q < n; ++q) {
        int i = h->active[q];
        int idx[3] = {i % h->res[0], (i / h->res[0]) % h->res[1], i / (h->res[0] * h->res[1])};
        double w[3], norm = 0.0;
        for (int a = 0; a < 3; ++a) {
            pts[3 * q + a] = h->ms_min[a] + ((double)idx[a] + 0.5) * (h->ms_max[a] - h->ms_min[a]) / h->res[a];
            w[a] = origin[a] - pts[3 * q + a];
            norm += w[a] * w[a];
        }
        norm = fmax(sqrt(norm), 1e-30);
        for (int a = 0; a < 3; ++a) oms[3 * q + a] = w[a] / norm;
    }
    float *fms = xmalloc(sizeof(float) * (size_t)C * nq);
    network_at(h, n, pts, oms, fms, "lattice point (active index)");
    if (!h->d_planes) h->d_planes = buffer(h, sizeof(float) * (size_t)C * N, NULL);
    float *pl = xcalloc((size_t)C * N, sizeof(float));
    for (int q = 0; q < n; ++q)
        for (int c = 0; c < C; ++c) pl[(size_t)c * N + h->active[q]] = fms[(size_t)q * C + c];
    CL(clEnqueueWriteBuffer(h->queue, h->d_planes, CL_TRUE, 0, sizeof(float) * (size_t)C * N, pl,
                            0, NULL, NULL));
    xfree(fms);
    xfree(pl);
    xfree(pts);
    xfree(oms);
    h->counts[CLVOL_STAGE_LATTICE]++;
}

/* ------------------------------------------------------- the stochastic view table (F)
 * clvol/render/ms/view.py StochasticViewMs.prepare, step by step: per render, unless the view
 * is still and has its still_samples draws, `samples` draws of one free-flight point per
 * pixel block (cl/viewdepth.cl on a jittered ray), the history carried to the new camera when
 * it moved (_reproject), the network at the new points, their F_ms and depths added to the
 * blocks' sums, and the blocks' means uploaded as the march's one-knot view table. */

/* Philox4x32-10 (cl/include/rng.h; NumPy: clvol/kernels/rng.py host_uniform4). */
static void philox4x32_10(uint32_t c[4], uint32_t k0, uint32_t k1) {
    for (int r = 0; r < 10; ++r) {
        uint64_t p0 = (uint64_t)0xD2511F53u * c[0], p1 = (uint64_t)0xCD9E8D57u * c[2];
        uint32_t n0 = (uint32_t)(p1 >> 32) ^ c[1] ^ k0, n2 = (uint32_t)(p0 >> 32) ^ c[3] ^ k1;
        c[0] = n0;
        c[1] = (uint32_t)p1;
        c[2] = n2;
        c[3] = (uint32_t)p0;
        k0 += 0x9E3779B9u;
        k1 += 0xBB67AE85u;
    }
}

void view_jitter(uint32_t seed, uint32_t draw, long n, float *out) {
    for (long b = 0; b < n; ++b) {
        uint32_t c[4] = {(uint32_t)b, (uint32_t)((uint64_t)b >> 32), draw, 0u};
        philox4x32_10(c, seed, 0u);
        /* the top 24 bits times 2^-24: exact, in [0, 1) */
        for (int k = 0; k < 3; ++k) out[3 * b + k] = (float)(c[k] >> 8) * (1.0f / 16777216.0f);
    }
}

/* A pinhole camera as clvol.scene.Camera (directions_at, image_positions). */
typedef struct {
    double o[3], f[3], r[3], u[3], tan_half;
    int w, h;
} view_camera;

static view_camera current_camera(const clvol_host *h) {
    view_camera c;
    memcpy(c.o, h->cam_origin, sizeof c.o);
    memcpy(c.f, h->cam_fwd, sizeof c.f);
    memcpy(c.r, h->cam_right, sizeof c.r);
    memcpy(c.u, h->cam_up, sizeof c.u);
    c.tan_half = h->tan_half;
    c.w = h->width;
    c.h = h->height;
    return c;
}

/* Unit direction through the image position (col, row) in pixels (Camera.directions_at);
 * |d| >= 1 (forward is orthogonal to right and up): no division by zero. */
static void camera_direction(const view_camera *c, double col, double row, double d[3]) {
    double sx = (2.0 * col / c->w - 1.0) * c->tan_half * ((double)c->w / c->h);
    double sy = (1.0 - 2.0 * row / c->h) * c->tan_half;
    for (int a = 0; a < 3; ++a) d[a] = c->f[a] + sx * c->r[a] + sy * c->u[a];
    double n = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
    for (int a = 0; a < 3; ++a) d[a] /= n;
}

/* The block (j bx + i) of a world point's image position (Camera.image_positions), or -1
 * behind the camera or outside the image (_reproject's blocks_of). */
static long camera_block(const view_camera *c, const double p[3], int block, int bx, int by) {
    double v[3] = {p[0] - c->o[0], p[1] - c->o[1], p[2] - c->o[2]};
    double z = v[0] * c->f[0] + v[1] * c->f[1] + v[2] * c->f[2];
    if (!(z > 0)) return -1;   /* no division by a zero or negative depth */
    double vr = v[0] * c->r[0] + v[1] * c->r[1] + v[2] * c->r[2];
    double vu = v[0] * c->u[0] + v[1] * c->u[1] + v[2] * c->u[2];
    double col = (vr / z / (c->tan_half * ((double)c->w / c->h)) + 1.0) * (0.5 * c->w);
    double row = (1.0 - vu / z / c->tan_half) * (0.5 * c->h);
    double i = floor(col / block), j = floor(row / block);
    if (!(isfinite(i) && isfinite(j) && i >= 0 && i < bx && j >= 0 && j < by)) return -1;
    return (long)j * bx + (long)i;
}

/* _reproject: carry the history from the last draw's camera to `cam` (at most move_history
 * samples' worth per block). A block with a new sample (the first draw's n0 points `pts` in
 * blocks `blk`) takes the old block its point projects into; another takes an old block
 * whose mean point (old centre ray at the mean depth) projects into it; the rest start
 * empty. */
static void view_reproject(clvol_host *h, const view_camera *cam, const double *pts,
                           const long *blk, long n0) {
    view_state *v = &h->vs;
    int bx = v->bx, by = v->by, block = v->block;
    long nb = (long)bx * by;
    view_camera old = *cam;   /* the image layout is the same (else the history restarted) */
    memcpy(old.o, v->cam_origin, sizeof old.o);
    memcpy(old.f, v->cam_fwd, sizeof old.f);
    memcpy(old.r, v->cam_right, sizeof old.r);
    memcpy(old.u, v->cam_up, sizeof old.u);
    old.tan_half = v->cam_tan_half;
    long *src = xmalloc(sizeof(long) * (size_t)nb);
    for (long b = 0; b < nb; ++b) src[b] = -1;
    for (long b = 0; b < nb; ++b) {   /* forward, in ascending order: the last one wins */
        if (!(v->count[b] > 0)) continue;
        double d[3], p[3], mean_t = v->depth[b] / v->count[b];
        camera_direction(&old, ((double)(b % bx) + 0.5) * block, ((double)(b / bx) + 0.5) * block, d);
        for (int a = 0; a < 3; ++a) p[a] = old.o[a] + mean_t * d[a];
        long dst = camera_block(cam, p, block, bx, by);
        if (dst >= 0) src[dst] = b;
    }
    for (long q = 0; q < n0; ++q) src[blk[q]] = camera_block(&old, pts + 3 * q, block, bx, by);
    int C = v->C;
    double *sums = keep(xcalloc((size_t)C * nb, sizeof(double)));
    double *count = keep(xcalloc((size_t)nb, sizeof(double)));
    double *depth = keep(xcalloc((size_t)nb, sizeof(double)));
    for (long b = 0; b < nb; ++b) {
        long s = src[b];
        if (s < 0) continue;
        double keep_n = fmin(v->count[s], (double)v->move_history);
        double scale = keep_n / fmax(v->count[s], 1.0);   /* 0 where the old block was empty */
        for (int c = 0; c < C; ++c) sums[(size_t)c * nb + b] = v->sums[(size_t)c * nb + s] * scale;
        count[b] = keep_n;
        /* the old mean depth is along the old rays: the march reads only its sign */
        depth[b] = v->depth[s] * scale;
    }
    free(v->sums);
    free(v->count);
    free(v->depth);
    v->sums = sums, v->count = count, v->depth = depth;
    v->still = 0;
    xfree(src);
}

/* The view's block side for an image: the bundle's, or with view.block_auto about
 * blocks_across blocks across the longer side (view.py auto_block; Python's round: half to
 * even, as rint). */
static int view_block_for(const clvol_host *h, int width, int height) {
    const view_state *v = &h->vs;
    if (!v->block_auto) return v->block;
    int side = width > height ? width : height;
    int b = (int)rint((double)side / v->blocks_across);
    return b > 1 ? b : 1;
}

static void view_stage(clvol_host *h) {
    view_state *v = &h->vs;
    int block = v->block, C = h->channels;
    int bx = (h->width + block - 1) / block, by = (h->height + block - 1) / block;
    long nb = (long)bx * by;
    if (v->reset || v->bx != bx || v->by != by || v->C != C) {   /* the history starts again */
        free(v->sums);
        free(v->count);
        free(v->depth);
        v->sums = v->count = v->depth = NULL;
        v->sums = keep(xcalloc((size_t)C * nb, sizeof(double)));
        v->count = keep(xcalloc((size_t)nb, sizeof(double)));
        v->depth = keep(xcalloc((size_t)nb, sizeof(double)));
        v->bx = bx, v->by = by, v->C = C;
        v->have_camera = 0;
        v->still = 0;
        v->age = 0;
        v->reset = 0;
    }
    view_camera cam = current_camera(h);
    int moved = v->have_camera
        && (memcmp(v->cam_origin, cam.o, sizeof cam.o) != 0 || memcmp(v->cam_fwd, cam.f, sizeof cam.f) != 0
            || memcmp(v->cam_right, cam.r, sizeof cam.r) != 0 || memcmp(v->cam_up, cam.u, sizeof cam.u) != 0);
    if (!moved && v->still >= v->still_samples) return;   /* converged: nothing to draw */
    if (nb > v->cap) {
        cl_mem *vb[] = {&v->d_jitter, &v->d_depths, &v->d_weight, &v->d_table};
        for (size_t i = 0; i < sizeof vb / sizeof vb[0]; ++i) release_tracked(h, vb[i]);
        v->cap = 0;
        v->d_jitter = buffer(h, sizeof(cl_float4) * (size_t)nb, NULL);
        v->d_depths = buffer(h, sizeof(float) * (size_t)nb, NULL);
        v->d_weight = buffer(h, sizeof(float) * (size_t)nb, NULL);
        v->d_table = buffer(h, sizeof(float) * (size_t)(1 + C) * nb, NULL);
        v->cap = (int)nb;
    }
    /* the history's age once carried through a move (view_reproject keeps move_history), and
     * the draws that bring it to min_samples (view.py MIN_SAMPLES) */
    int age = moved && v->age > v->move_history ? v->move_history : v->age;
    int S = v->samples > v->min_samples - age ? v->samples : v->min_samples - age;
    size_t most = (size_t)nb * S;
    double *pts = xmalloc(sizeof(double) * 3 * most), *oms = xmalloc(sizeof(double) * 3 * most);
    double *t = xmalloc(sizeof(double) * most);
    long *blk = xmalloc(sizeof(long) * most), np = 0, n0 = 0;
    float *jit = xmalloc(sizeof(float) * 3 * (size_t)nb), *dep = xmalloc(sizeof(float) * (size_t)nb);
    cl_float4 *j4 = xcalloc((size_t)nb, sizeof(cl_float4));
    cl_float4 bmin = f4(h->bmin), bmax = f4(h->bmax), o4 = f4(cam.o), fw4 = f4(cam.f),
              r4 = f4(cam.r), u4 = f4(cam.u);
    double stop = h->threshold;
    for (int s = 0; s < S; ++s) {
        uint32_t draw = (uint32_t)v->draws++;
        view_jitter(v->seed, draw, nb, jit);
        for (long b = 0; b < nb; ++b)
            for (int k = 0; k < 3; ++k) j4[b].s[k] = jit[3 * b + k];
        CL(clEnqueueWriteBuffer(h->queue, v->d_jitter, CL_FALSE, 0, sizeof(cl_float4) * (size_t)nb,
                                j4, 0, NULL, NULL));
        set_args(h->k_viewdepth, "miii44f4444fiiffmmm", h->d_density, h->nx, h->ny, h->nz, &bmin,
                 &bmax, h->density_scale, &o4, &fw4, &r4, &u4, h->tan_half, h->width, h->height,
                 v->step_factor * h->step, stop, v->d_depths, v->d_weight, v->d_jitter);
        launch(h, h->k_viewdepth, padded((size_t)nb, (size_t)h->pad), 0);
        CL(clEnqueueReadBuffer(h->queue, v->d_depths, CL_TRUE, 0, sizeof(float) * (size_t)nb, dep,
                               0, NULL, NULL));
        for (long b = 0; b < nb; ++b) {
            if (!(dep[b] >= 0.0f)) continue;   /* the ray escaped: no sample this draw */
            double d[3];
            camera_direction(&cam, ((double)(b % bx) + (double)jit[3 * b]) * block,
                             ((double)(b / bx) + (double)jit[3 * b + 1]) * block, d);
            t[np] = dep[b];
            for (int a = 0; a < 3; ++a) {
                pts[3 * np + a] = cam.o[a] + t[np] * d[a];
                oms[3 * np + a] = -d[a];   /* toward the camera */
            }
            blk[np++] = b;
        }
        if (s == 0) n0 = np;
    }
    if (moved) view_reproject(h, &cam, pts, blk, n0);
    float *fms = xmalloc(sizeof(float) * (size_t)C * (size_t)(np > 0 ? np : 1));
    network_at(h, np, pts, oms, fms, "view sample");
    for (long q = 0; q < np; ++q) {
        long b = blk[q];
        for (int c = 0; c < C; ++c) v->sums[(size_t)c * nb + b] += fms[(size_t)q * C + c];
        v->count[b] += 1.0;
        v->depth[b] += t[q];
    }
    memcpy(v->cam_origin, cam.o, sizeof cam.o);
    memcpy(v->cam_fwd, cam.f, sizeof cam.f);
    memcpy(v->cam_right, cam.r, sizeof cam.r);
    memcpy(v->cam_up, cam.u, sizeof cam.u);
    v->cam_tan_half = cam.tan_half;
    v->have_camera = 1;
    v->still += S;
    v->age = age + S;
    /* the table (1 + C, by, bx, 1): mean depth (-1 where no sample yet), mean F_ms */
    float *table = xmalloc(sizeof(float) * (size_t)(1 + C) * nb);
    for (long b = 0; b < nb; ++b) {
        double c = v->count[b], inv = c > 0 ? 1.0 / fmax(c, 1.0) : 0.0;
        table[b] = c > 0 ? (float)(v->depth[b] * inv) : -1.0f;
        for (int k = 0; k < C; ++k) table[(size_t)(1 + k) * nb + b] = (float)(v->sums[(size_t)k * nb + b] * inv);
    }
    CL(clEnqueueWriteBuffer(h->queue, v->d_table, CL_TRUE, 0, sizeof(float) * (size_t)(1 + C) * nb,
                            table, 0, NULL, NULL));
    xfree(table);
    xfree(fms);
    xfree(pts);
    xfree(oms);
    xfree(t);
    xfree(blk);
    xfree(jit);
    xfree(dep);
    xfree(j4);
    h->counts[CLVOL_STAGE_LATTICE]++;
}

/* A block as the kernel argument (cl/include/blocks.h Block16: a float16's layout). */
static cl_float16 block_arg(const double v[16]) {
    cl_float16 out;
    for (int i = 0; i < 16; ++i) out.s[i] = (float)v[i];
    return out;
}

/* The ray marcher's medium argument (cl/include/medium.h): the bundle's block (read at create)
 * with the density scale and albedo this host holds now (clvol_set_medium changes them) in
 * the slots the bundle names. */
static cl_float16 medium_block(const clvol_host *h) {
    double v[16];
    memcpy(v, h->medium, sizeof v);
    v[h->medium_ds_slot] = h->density_scale;
    for (int c = 0; c < 3; ++c) v[h->medium_albedo_slot + c] = h->albedo[c];
    return block_arg(v);
}

/* The ray marcher's light argument (cl/include/light.h): the bundle's block with the
 * direction and irradiance this host holds now (clvol_set_light changes them). */
static cl_float16 light_block(const clvol_host *h) {
    double v[16];
    memcpy(v, h->light_block, sizeof v);
    for (int c = 0; c < 3; ++c) {
        v[h->light_dir_slot + c] = h->light_dir[c];
        v[h->light_irradiance_slot + c] = h->irradiance[c];
    }
    return block_arg(v);
}

/* Every frame: the march into h->d_out (total, single, multiple, alpha, depth). */
static void march_stage(clvol_host *h) {
    const double *abc = h->octave_abc;
    int gres[3] = {1, 1, 1};
    double gmin[3] = {0, 0, 0}, gmax[3] = {1, 1, 1};
    cl_mem planes = h->d_dummy;
    if (h->network && h->view) {   /* the view table (1 + C, by, bx, K = 1) */
        gres[0] = 1;
        gres[1] = h->vs.bx;
        gres[2] = h->vs.by;
        planes = h->vs.d_table;
    } else if (h->network) {
        for (int a = 0; a < 3; ++a) {
            gres[a] = h->res[a];
            gmin[a] = h->ms_min[a];
            gmax[a] = h->ms_max[a];
        }
        planes = h->d_planes;
    }
    int W = h->width, H = h->height;
    if (h->out_width != W || h->out_height != H) {   /* the image size changed (or first frame) */
        for (int i = 0; i < 6; ++i) release_tracked(h, &h->d_out[i]);
        int ch[6] = {3, 3, 3, 1, 1, 0};
        for (int i = 0; i < 5; ++i) h->d_out[i] = buffer(h, 4 * (size_t)W * H * ch[i], NULL);
        /* stats: word 0 counts the rays the march's progress bound stopped (cl/raymarch.cl,
         * an atomic add; libclvol does not read it), zeroed so the kernel adds to a defined
         * value; the per-tile counts need RAYMARCH_STATS, which libclvol never sets */
        h->d_out[5] = zeros(h, 4);
        h->out_width = W;
        h->out_height = H;
    }
    const double *origin = h->cam_origin;
    cl_float4 bmin = f4(h->bmin), bmax = f4(h->bmax), cmin4 = f4(h->cube_min), gmin4 = f4(gmin),
              gmax4 = f4(gmax), o4 = f4(origin), fw4 = f4(h->cam_fwd), r4 = f4(h->cam_right),
              u4 = f4(h->cam_up), bg4 = f4(h->background);
    cl_float16 medium = medium_block(h), light = light_block(h);
    int ln = h->lit ? h->light_res : 1;
    set_args(h->k_raymarch, "miii44Gmiiiimi4fmiii444444fiiG4fffffmmmmmm",
             h->d_density, h->nx, h->ny, h->nz, &bmin, &bmax, &medium,
             h->d_majorant, h->mx, h->my, h->mz, h->block,
             h->lit ? h->d_light : h->d_dummy, ln, &cmin4, h->lit ? h->cube_size : 1.0,
             planes, gres[0], gres[1], gres[2], &gmin4, &gmax4,
             &o4, &fw4, &r4, &u4, h->tan_half, W, H,
             &light, &bg4, abc[0], abc[1], abc[2],
             h->step, h->threshold,
             h->d_out[0], h->d_out[1], h->d_out[2], h->d_out[3], h->d_out[4], h->d_out[5]);
    /* a tile is tile x LANES / tile pixels, one a lane (cl/raymarch.cl TILE_ROWS) */
    int rows = h->lanes / h->tile;
    size_t tiles = (size_t)((W + h->tile - 1) / h->tile) * (size_t)((H + rows - 1) / rows);
    launch(h, h->k_raymarch, padded(tiles, (size_t)h->rm_local), (size_t)h->rm_local);
    h->counts[CLVOL_STAGE_MARCH]++;
}

/* Whatever the changes since the last frame invalidated, then the march. A stage's flag is
 * cleared only once it has run, so a failed stage runs again at the next render. */
static void render_frame(clvol_host *h) {
    if (h->volume_dirty) {
        volume_stage(h);
        h->volume_dirty = 0;
    }
    if (h->light_dirty) {
        if (h->lit) light_stage(h);
        h->light_dirty = 0;
    }
    if (h->network && h->view) {
        view_stage(h);   /* every render: draws until the view is still long enough */
        h->lattice_dirty = 0;
    } else if (h->lattice_dirty) {
        if (h->network) lattice_stage(h);
        h->lattice_dirty = 0;
    }
    march_stage(h);
}

/* total + alpha into the caller's [H][W][4] buffer (the library's pack kernel). */
static void pack_into(clvol_host *h, cl_mem rgba) {
    int n = h->width * h->height;
    set_args(h->k_pack, "mmmi", h->d_out[0], h->d_out[3], rgba, n);
    launch(h, h->k_pack, padded((size_t)n, (size_t)h->pad), 0);
}

/* -------------------------------------------------------------------------- the API */


/* A failure the renderer cannot recover from (its device state may be half made). */
static clvol_status end_call(clvol_host *h, guard *g) {
    /* A failure may leave non-blocking writes from this call's scratch memory in the queue
     * (a key missing from the manifest, read after the lattice's uploads were enqueued): they
     * must finish before guard_end frees that memory (the setter fuzz found PoCL's thread
     * copying freed memory; tests/test_capi.py test_fuzz_found_failures_drain_the_queue). */
    if (g->status != CLVOL_OK && h->queue) clFinish(h->queue);
    clvol_status st = guard_end(g);
    if (st == CLVOL_ERROR_OPENCL || st == CLVOL_ERROR_MEMORY) h->broken = st;
    return st;
}

/* First statement of every entry point taking a renderer. */
#define ENTER(g, h, fn)                                                                     \
    guard g;                                                                                \
    if (!(h)) {                                                                             \
        snprintf(thread_error, sizeof thread_error, "%s: the renderer is NULL", fn);        \
        return CLVOL_ERROR_ARGUMENT;                                                        \
    }                                                                                       \
    guard_init(&g, (h)->err, sizeof (h)->err);                                              \
    if (setjmp(g.jump)) return end_call((h), &g);                                           \
    if ((h)->broken)                                                                        \
        fail((h)->broken, "%s: an earlier OpenCL or memory failure left this renderer "     \
             "unusable; destroy it", fn)

static void need(const void *p, const char *fn, const char *what) {
    if (!p) fail(CLVOL_ERROR_ARGUMENT, "%s: %s is NULL", fn, what);
}

/* The largest value of a density (checked finite and >= 0). */
static double max_density(const float *d, size_t count) {
    double m = 0.0;
    for (size_t i = 0; i < count; ++i) m = fmax(m, d[i]);
    return m;
}

/* clvol/render/renderer.py _check_optical_range: density_scale x the largest density x the
 * box's diagonal must stay below CLVOL_MAX_OPTICAL_DEPTH (optical depths are float32). */
static void check_optical_range(const clvol_host *h, clvol_status status, const char *where,
                                double scale, double maxd) {
    double d2 = 0.0;
    for (int a = 0; a < 3; ++a) d2 += (h->bmax[a] - h->bmin[a]) * (h->bmax[a] - h->bmin[a]);
    double worst = scale * maxd * sqrt(d2);
    if (!(worst < CLVOL_MAX_OPTICAL_DEPTH))
        fail(status, "%s: medium.density_scale = %.9g times the largest density %g over the "
             "box's diagonal gives optical depths beyond float32 range; rescale the density",
             where, scale, maxd);
}

static void need_finite3(const float v[3], const char *fn, const char *what) {
    need(v, fn, what);
    for (int a = 0; a < 3; ++a)
        if (!isfinite(v[a]))
            fail(CLVOL_ERROR_ARGUMENT, "%s: %s = (%g, %g, %g): must be finite", fn, what,
                 (double)v[0], (double)v[1], (double)v[2]);
}

/* The --ms name of a source (the bundle's network source: network or stochastic). */
static const char *source_name(const clvol_host *h, int s) {
    return s == SOURCE_NETWORK ? (h->view ? "stochastic" : "network") : s == SOURCE_WRENNINGE ? "wrenninge" : "none";
}

/* The multiple-scattering source clvol.Renderer picks for this medium and volume
 * (clvol/render/renderer.py _active_source with the bundle's defaults: shortcuts on, domain
 * fallback on): none for an optically thin medium, the fallback outside the network's
 * training domain, else the network. */
static int renderer_source(const clvol_host *h, const double albedo[3], double scale,
                           double unit_thickness) {
    const manifest *m = &h->mf;
    double ot = unit_thickness * scale;
    if (ot < mf_double(m, "domain.thin_optical_thickness")) return SOURCE_NONE;
    double alb[2], otr[2];
    mf_doubles(m, "domain.albedo", alb, 2);
    int outside = mf_int(m, "domain.phase_outside") != 0;
    double min_alb = INFINITY;
    for (int c = 0; c < 3; ++c)
        if (albedo[c] > 0) {
            outside |= !(alb[0] <= albedo[c] && albedo[c] <= alb[1]);
            min_alb = fmin(min_alb, albedo[c]);
        }
    if (strcmp(mf_str(m, "domain.optical_thickness"), "none") != 0) {
        mf_doubles(m, "domain.optical_thickness", otr, 2);
        outside |= !(otr[0] <= ot && ot <= otr[1]);
    }
    if (!outside || !mf_int(m, "domain.backward")) return SOURCE_NETWORK;
    return isfinite(min_alb) && min_alb >= mf_double(m, "domain.backward_albedo")
               ? SOURCE_WRENNINGE : SOURCE_NONE;
}

/* Refuse a change for which clvol.Renderer would build other programs than the bundle's: lit
 * or unlit, and for a medium or volume (`medium_or_volume`) another source or a grey or
 * coloured network. (The source does not depend on the light: a light change reads no
 * domain.* key.) */
static void check_same_programs(const clvol_host *h, const char *fn, const double albedo[3],
                                const double irr[3], double scale, double unit_thickness,
                                int medium_or_volume) {
    int lit = 0;
    for (int c = 0; c < 3; ++c) lit |= albedo[c] * irr[c] > 0;
    if (lit != h->lit)
        fail(CLVOL_ERROR_UNSUPPORTED, "%s: the bundle's scene is %s (albedo x irradiance %s 0) "
             "and its programs are built for that; this change makes it %s", fn,
             h->lit ? "lit" : "unlit", h->lit ? ">" : "=", lit ? "lit" : "unlit");
    if (!lit || !medium_or_volume) return;
    int s = renderer_source(h, albedo, scale, unit_thickness);
    if (s != h->source)
        fail(CLVOL_ERROR_UNSUPPORTED, "%s: clvol.Renderer would use --ms %s for this medium "
             "(largest optical thickness %.3g), the bundle's programs run --ms %s; write a "
             "bundle of the new scene", fn, source_name(h, s), unit_thickness * scale,
             source_name(h, h->source));
    int grey = albedo[0] == albedo[1] && albedo[1] == albedo[2];
    if (h->network && grey != h->grey)
        fail(CLVOL_ERROR_UNSUPPORTED, "%s: the bundle's network runs %s (MLP_CHANNELS); a %s "
             "albedo needs the other program", fn, h->grey ? "one grey channel" : "three channels",
             grey ? "grey" : "coloured");
}

int clvol_abi_version(void) { return CLVOL_ABI_VERSION; }

static void set_camera_basis(clvol_host *h, const double origin[3], const double target[3],
                             const double up[3], double fov_y, const char *fn) {
    /* clvol.scene.Camera.basis: forward = unit(target - origin), right = unit(forward x up),
     * up = right x forward */
    double f[3], r[3], u[3], nf = 0, nr = 0;
    for (int a = 0; a < 3; ++a) {
        f[a] = target[a] - origin[a];
        nf += f[a] * f[a];
    }
    nf = sqrt(nf);
    if (!(nf > 0)) fail(CLVOL_ERROR_ARGUMENT, "%s: target equals origin; the camera needs target != origin to have a view direction", fn);
    for (int a = 0; a < 3; ++a) f[a] /= nf;
    double nu = sqrt(up[0] * up[0] + up[1] * up[1] + up[2] * up[2]);
    if (!(nu > 0)) fail(CLVOL_ERROR_ARGUMENT, "%s: up = (0, 0, 0): must not be the zero vector", fn);
    r[0] = f[1] * up[2] - f[2] * up[1];
    r[1] = f[2] * up[0] - f[0] * up[2];
    r[2] = f[0] * up[1] - f[1] * up[0];
    for (int a = 0; a < 3; ++a) nr += r[a] * r[a];
    nr = sqrt(nr);
    /* the scene file's rule (clvol/scenefile.py _parse_camera): |forward x unit(up)| >= 1e-6 */
    if (!(nr / nu >= 1e-6))
        fail(CLVOL_ERROR_ARGUMENT, "%s: up = (%g, %g, %g): is parallel to target - origin; pick "
             "an up vector that is not along the view direction", fn, up[0], up[1], up[2]);
    for (int a = 0; a < 3; ++a) r[a] /= nr;
    u[0] = r[1] * f[2] - r[2] * f[1];
    u[1] = r[2] * f[0] - r[0] * f[2];
    u[2] = r[0] * f[1] - r[1] * f[0];
    int moved = memcmp(h->cam_origin, origin, sizeof h->cam_origin) != 0;
    memcpy(h->cam_origin, origin, sizeof h->cam_origin);
    memcpy(h->cam_fwd, f, sizeof f);
    memcpy(h->cam_right, r, sizeof r);
    memcpy(h->cam_up, u, sizeof u);
    h->tan_half = tan(fov_y * (3.14159265358979323846 / 180.0) / 2.0);
    /* the lattice's omegas point toward the camera: only its position matters there */
    if (moved) h->lattice_dirty = 1;
}

clvol_status clvol_set_camera(clvol_renderer *r, const float origin[3], const float target[3],
                              const float up[3], float fov_y_degrees, int width, int height) {
    static const char fn[] = "clvol_set_camera";
    ENTER(g, r, fn);
    need_finite3(origin, fn, "origin");
    need_finite3(target, fn, "target");
    need_finite3(up, fn, "up");
    if (!(fov_y_degrees > 0 && fov_y_degrees < 180))
        fail(CLVOL_ERROR_ARGUMENT, "%s: fov_y_degrees = %g: must be in (0, 180)", fn, (double)fov_y_degrees);
    if (width < 1 || height < 1 || width > CLVOL_MAX_IMAGE_SIZE || height > CLVOL_MAX_IMAGE_SIZE)
        fail(CLVOL_ERROR_ARGUMENT, "%s: %d x %d pixels: width and height must be in [1, %d]",
             fn, width, height, CLVOL_MAX_IMAGE_SIZE);
    if (r->view && r->network && view_block_for(r, width, height) != r->vs.block)
        fail(CLVOL_ERROR_UNSUPPORTED, "%s: a %d x %d image takes view blocks of %d pixels (about "
             "%d across), the bundle's programs are built for %d; write a bundle with "
             "--view-block %d to render any size", fn, width, height,
             view_block_for(r, width, height), r->vs.blocks_across, r->vs.block, r->vs.block);
    double o[3] = {origin[0], origin[1], origin[2]}, t[3] = {target[0], target[1], target[2]},
           u[3] = {up[0], up[1], up[2]};
    double tan_half = r->tan_half;
    set_camera_basis(r, o, t, u, fov_y_degrees, fn);
    /* the view history holds for one image layout (StochasticViewMs.key_for) */
    if (width != r->width || height != r->height || tan_half != r->tan_half) r->vs.reset = 1;
    r->width = width;
    r->height = height;
    return end_call(r, &g);
}

clvol_status clvol_set_light(clvol_renderer *r, const float to_light[3], const float irradiance[3]) {
    static const char fn[] = "clvol_set_light";
    ENTER(g, r, fn);
    need_finite3(to_light, fn, "to_light");
    need_finite3(irradiance, fn, "irradiance");
    double d[3] = {to_light[0], to_light[1], to_light[2]}, irr[3], norm;
    norm = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
    if (!(norm > 0)) fail(CLVOL_ERROR_ARGUMENT, "%s: to_light is the zero vector", fn);
    for (int c = 0; c < 3; ++c) {
        d[c] /= norm;
        irr[c] = irradiance[c];
        if (irr[c] < 0)
            fail(CLVOL_ERROR_ARGUMENT, "%s: irradiance = (%g, %g, %g): must be >= 0", fn,
                 irr[0], (double)irradiance[1], (double)irradiance[2]);
    }
    check_same_programs(r, fn, r->albedo, irr, r->density_scale, r->unit_thickness, 0);
    if (memcmp(d, r->light_dir, sizeof d) != 0) {
        memcpy(r->light_dir, d, sizeof d);
        r->light_dirty = r->lattice_dirty = 1;
        r->vs.reset = 1;   /* the view history holds for one light */
    }
    memcpy(r->irradiance, irr, sizeof irr);   /* the march's argument only */
    return end_call(r, &g);
}

clvol_status clvol_set_medium(clvol_renderer *r, const float albedo[3], float density_scale) {
    static const char fn[] = "clvol_set_medium";
    ENTER(g, r, fn);
    need_finite3(albedo, fn, "albedo");
    double alb[3] = {albedo[0], albedo[1], albedo[2]}, scale = density_scale;
    for (int c = 0; c < 3; ++c)
        if (!(alb[c] >= 0 && alb[c] <= 1))
            fail(CLVOL_ERROR_ARGUMENT, "%s: albedo = (%g, %g, %g): each must be in [0, 1]", fn,
                 alb[0], alb[1], alb[2]);
    if (!(isfinite(scale) && scale >= 0))
        fail(CLVOL_ERROR_ARGUMENT, "%s: density_scale = %g: must be finite and >= 0", fn, scale);
    check_optical_range(r, CLVOL_ERROR_ARGUMENT, fn, scale, r->max_density);
    check_same_programs(r, fn, alb, r->irradiance, scale, r->unit_thickness, 1);
    if (scale != r->density_scale) r->light_dirty = r->lattice_dirty = r->vs.reset = 1;
    if (memcmp(alb, r->albedo, sizeof alb) != 0) r->lattice_dirty = r->vs.reset = 1;
    r->density_scale = scale;
    memcpy(r->albedo, alb, sizeof alb);
    return end_call(r, &g);
}

clvol_status clvol_set_density(clvol_renderer *r, const float *density, int nx, int ny, int nz) {
    static const char fn[] = "clvol_set_density";
    ENTER(g, r, fn);
    need(density, fn, "density");
    if (nx < 1 || ny < 1 || nz < 1)
        fail(CLVOL_ERROR_ARGUMENT, "%s: %d x %d x %d voxels: each size must be >= 1", fn, nx, ny, nz);
    if ((double)nx * ny * nz > 2147483647.0 / 4)
        fail(CLVOL_ERROR_ARGUMENT, "%s: %d x %d x %d voxels: more than 2^29", fn, nx, ny, nz);
    size_t count = (size_t)nx * ny * nz;
    for (size_t i = 0; i < count; ++i)
        if (!(isfinite(density[i]) && density[i] >= 0))
            fail(CLVOL_ERROR_ARGUMENT, "%s: density[%zu] (x %zu, y %zu, z %zu) = %g: every value "
                 "must be finite and >= 0", fn, i, i % (size_t)nx, i / (size_t)nx % (size_t)ny,
                 i / ((size_t)nx * ny), (double)density[i]);
    double maxd = max_density(density, count);
    check_optical_range(r, CLVOL_ERROR_ARGUMENT, fn, r->density_scale, maxd);
    double tau1 = unit_optical_thickness(density, nx, ny, nz, r->bmin, r->bmax);
    check_same_programs(r, fn, r->albedo, r->irradiance, r->density_scale, tau1, 1);
    float *copy = xmalloc(4 * count);
    memcpy(copy, density, 4 * count);
    free(r->density);
    r->density = keep(copy);
    r->nx = nx, r->ny = ny, r->nz = nz;
    r->unit_thickness = tau1;
    r->max_density = maxd;
    /* the step option is in voxels of the grid (its smallest side) */
    double min_cell = INFINITY;
    int n[3] = {nx, ny, nz};
    for (int a = 0; a < 3; ++a) min_cell = fmin(min_cell, (r->bmax[a] - r->bmin[a]) / n[a]);
    r->step = r->step_voxels * min_cell;
    if (r->network && !r->view) find_active_points(r);
    r->volume_dirty = r->light_dirty = r->lattice_dirty = r->vs.reset = 1;
    return end_call(r, &g);
}

clvol_status clvol_render(clvol_renderer *r, float *rgba) {
    static const char fn[] = "clvol_render";
    ENTER(g, r, fn);
    need(rgba, fn, "rgba");
    render_frame(r);
    size_t n = (size_t)r->width * r->height;
    float *rgb = xmalloc(12 * n), *alpha = xmalloc(4 * n);
    CL(clEnqueueReadBuffer(r->queue, r->d_out[0], CL_FALSE, 0, 12 * n, rgb, 0, NULL, NULL));
    CL(clEnqueueReadBuffer(r->queue, r->d_out[3], CL_TRUE, 0, 4 * n, alpha, 0, NULL, NULL));
    for (size_t i = 0; i < n; ++i) {
        rgba[4 * i] = rgb[3 * i];
        rgba[4 * i + 1] = rgb[3 * i + 1];
        rgba[4 * i + 2] = rgb[3 * i + 2];
        rgba[4 * i + 3] = alpha[i];
    }
    xfree(rgb);
    xfree(alpha);
    return end_call(r, &g);
}

clvol_status clvol_render_to_buffer(clvol_renderer *r, cl_mem rgba) {
    static const char fn[] = "clvol_render_to_buffer";
    ENTER(g, r, fn);
    need(rgba, fn, "rgba");
    size_t size = 0;
    cl_context ctx = NULL;
    if (clGetMemObjectInfo(rgba, CL_MEM_SIZE, sizeof size, &size, NULL) != CL_SUCCESS
        || clGetMemObjectInfo(rgba, CL_MEM_CONTEXT, sizeof ctx, &ctx, NULL) != CL_SUCCESS)
        fail(CLVOL_ERROR_ARGUMENT, "%s: rgba is not a valid cl_mem", fn);
    if (ctx != r->ctx)
        fail(CLVOL_ERROR_ARGUMENT, "%s: rgba belongs to another context than the renderer's", fn);
    size_t need_bytes = 16 * (size_t)r->width * r->height;
    if (size < need_bytes)
        fail(CLVOL_ERROR_ARGUMENT, "%s: rgba holds %zu bytes, the %d x %d image needs %zu", fn,
             size, r->width, r->height, need_bytes);
    render_frame(r);
    pack_into(r, rgba);
    CL(clFinish(r->queue));
    return end_call(r, &g);
}

const char *clvol_last_error(const clvol_renderer *r) { return r ? r->err : thread_error; }

clvol_status clvol_get_size(const clvol_renderer *r, int *width, int *height) {
    if (!r || !width || !height) {
        snprintf(thread_error, sizeof thread_error, "clvol_get_size: a NULL argument");
        return CLVOL_ERROR_ARGUMENT;
    }
    *width = r->width;
    *height = r->height;
    return CLVOL_OK;
}

long clvol_stage_count(const clvol_renderer *r, clvol_stage stage) {
    if (!r || (int)stage < 0 || stage >= CLVOL_STAGE_COUNT) return -1;
    return r->counts[stage];
}

static void create(clvol_host *h, const char *bundle_dir, cl_context context,
                   cl_device_id device, cl_command_queue queue) {
    static const char fn[] = "clvol_create";
    need(bundle_dir, fn, "bundle_dir");
    if ((context == NULL) != (queue == NULL))
        fail(CLVOL_ERROR_ARGUMENT, "%s: pass both a context and a queue, or neither", fn);
    h->dir = xstrdup(bundle_dir);
    char *mpath = path_join(bundle_dir, "manifest.txt");
    manifest_read(&h->mf, mpath);
    xfree(mpath);
    if (context) {
        cl_device_id qdev = NULL;
        cl_context qctx = NULL;
        cl_command_queue_properties props = 0;
        if (clGetCommandQueueInfo(queue, CL_QUEUE_DEVICE, sizeof qdev, &qdev, NULL) != CL_SUCCESS
            || clGetCommandQueueInfo(queue, CL_QUEUE_CONTEXT, sizeof qctx, &qctx, NULL) != CL_SUCCESS
            || clGetCommandQueueInfo(queue, CL_QUEUE_PROPERTIES, sizeof props, &props, NULL) != CL_SUCCESS)
            fail(CLVOL_ERROR_ARGUMENT, "%s: queue is not a valid command queue", fn);
        if (qctx != context) fail(CLVOL_ERROR_ARGUMENT, "%s: the queue belongs to another context", fn);
        if (device && device != qdev)
            fail(CLVOL_ERROR_ARGUMENT, "%s: device is not the queue's device", fn);
        if (props & CL_QUEUE_OUT_OF_ORDER_EXEC_MODE_ENABLE)
            fail(CLVOL_ERROR_ARGUMENT, "%s: the queue must be in-order", fn);
        h->ctx = context;
        h->queue = queue;
        h->device = qdev;
    } else {
        h->device = device;   /* NULL: open_device picks one */
        open_device(h);
    }
    describe_device(h);
    open_bundle(h);
    size_t count = (size_t)h->nx * h->ny * h->nz;
    for (size_t i = 0; i < count; ++i)
        if (!(isfinite(h->density[i]) && h->density[i] >= 0))
            fail(BUNDLE, "%s: density value %zu = %g: must be finite and >= 0", h->mf.where, i,
                 (double)h->density[i]);
    /* the bundle's medium and light in the setters' ranges (a damaged manifest may hold any
     * number) */
    if (!(isfinite(h->density_scale) && h->density_scale >= 0))
        fail(BUNDLE, "%s: medium.density_scale = %g: must be finite and >= 0", h->mf.where,
             h->density_scale);
    for (int c = 0; c < 3; ++c) {
        if (!(h->albedo[c] >= 0 && h->albedo[c] <= 1))
            fail(BUNDLE, "%s: medium.albedo = (%g, %g, %g): each must be in [0, 1]", h->mf.where,
                 h->albedo[0], h->albedo[1], h->albedo[2]);
        if (!(isfinite(h->irradiance[c]) && h->irradiance[c] >= 0))
            fail(BUNDLE, "%s: light.irradiance = (%g, %g, %g): each must be finite and >= 0",
                 h->mf.where, h->irradiance[0], h->irradiance[1], h->irradiance[2]);
    }
    h->max_density = max_density(h->density, count);
    check_optical_range(h, BUNDLE, h->mf.where, h->density_scale, h->max_density);
    h->unit_thickness = unit_optical_thickness(h->density, h->nx, h->ny, h->nz, h->bmin, h->bmax);
    /* the bundle's camera and light (the camera as its basis: it may come from any target) */
    double o[3], f[3], t[3], u[3], l[3];
    mf_doubles(&h->mf, "camera.origin", o, 3);
    mf_doubles(&h->mf, "camera.forward", f, 3);
    mf_doubles(&h->mf, "camera.up", u, 3);
    for (int a = 0; a < 3; ++a) t[a] = o[a] + f[a];
    double tan_half = mf_double(&h->mf, "camera.tan_half");
    if (!(tan_half > 0 && isfinite(tan_half))) fail(BUNDLE, "%s: camera.tan_half must be > 0", h->mf.where);
    set_camera_basis(h, o, t, u, 90.0, fn);
    mf_doubles(&h->mf, "camera.forward", h->cam_fwd, 3);   /* the bundle's exact basis */
    mf_doubles(&h->mf, "camera.right", h->cam_right, 3);
    mf_doubles(&h->mf, "camera.up", h->cam_up, 3);
    h->tan_half = tan_half;
    mf_doubles(&h->mf, "light.direction", l, 3);
    double norm = sqrt(l[0] * l[0] + l[1] * l[1] + l[2] * l[2]);
    if (!(norm > 0 && isfinite(norm))) fail(BUNDLE, "%s: light.direction must be a finite non-zero vector", h->mf.where);
    for (int a = 0; a < 3; ++a) h->light_dir[a] = l[a] / norm;
    /* the volume and the light now (what a bundle's damage shows in), the lattice at the
     * first frame (the caller may move the camera first) */
    h->volume_dirty = h->light_dirty = h->lattice_dirty = 1;
    volume_stage(h);
    h->volume_dirty = 0;
    if (h->lit) light_stage(h);
    h->light_dirty = 0;
}

clvol_status clvol_create(const char *bundle_dir, cl_context context, cl_device_id device,
                          cl_command_queue queue, clvol_renderer **out) {
    char msg[1024];
    guard g;
    clvol_host *volatile h = NULL;   /* volatile: read after a longjmp */
    guard_init(&g, msg, sizeof msg);
    if (setjmp(g.jump)) {
        if (h && h->queue) clFinish(h->queue);   /* as end_call: before the scratch is freed */
        clvol_status st = guard_end(&g);
        host_release(h);
        snprintf(thread_error, sizeof thread_error, "%s", msg);
        return st;
    }
    if (!out) fail(CLVOL_ERROR_ARGUMENT, "clvol_create: out is NULL");
    *out = NULL;
    h = calloc(1, sizeof *h);
    if (!h) fail(CLVOL_ERROR_MEMORY, "out of host memory");
    create(h, bundle_dir, context, device, queue);
    *out = h;
    return guard_end(&g);
}

void clvol_destroy(clvol_renderer *r) { host_release(r); }
