/* libclvol internals shared by the sources in capi/src/ (not installed).
 *
 * Errors: every public entry point sets up a `guard` (guard_init, then setjmp on its jump
 * buffer; renderer.c's ENTER) before any work. Deep code
 * reports a problem with fail(status, ...), which writes the one-line message into the
 * guard's buffer and longjmps back to the entry point, which returns the status. So the
 * 1,500 lines of host code read straight through (no status plumbing on every call), and
 * nothing exits the process.
 * Host memory taken during a call with xmalloc is recorded in the guard and freed when the
 * call ends, success or failure; memory that outlives the call (held by the renderer) is
 * handed over with keep(). cl_mem objects are recorded in the renderer (track) and released
 * by clvol_destroy or at the end of the stage that made them.
 */
#ifndef CLVOL_INTERNAL_H
#define CLVOL_INTERNAL_H

#define CL_TARGET_OPENCL_VERSION 120
#define CL_USE_DEPRECATED_OPENCL_1_2_APIS
#include "clvol.h"

/* The static library's internal names carry a prefix, so they cannot clash with a program's
 * own (a `fail` or `buffer` of the embedding engine). */
#define clvol_guard clvol__clvol_guard
#define thread_error clvol__thread_error
#define guard_init clvol__guard_init
#define guard_end clvol__guard_end
#define fail clvol__fail
#define cl_error_name clvol__cl_error_name
#define cl_check clvol__cl_check
#define xmalloc clvol__xmalloc
#define xcalloc clvol__xcalloc
#define xfree clvol__xfree
#define keep clvol__keep
#define xstrdup clvol__xstrdup
#define now_seconds clvol__now_seconds
#define path_join clvol__path_join
#define read_file clvol__read_file
#define read_raw4 clvol__read_raw4
#define manifest_read clvol__manifest_read
#define manifest_free clvol__manifest_free
#define mf_find clvol__mf_find
#define mf_str clvol__mf_str
#define mf_doubles clvol__mf_doubles
#define mf_double clvol__mf_double
#define mf_ints clvol__mf_ints
#define mf_int clvol__mf_int
#define mf_int_in clvol__mf_int_in
#define mf_has_word clvol__mf_has_word
#define mf_float4 clvol__mf_float4
#define PROGRAM_NAMES clvol__PROGRAM_NAMES
#define track clvol__track
#define release_tracked clvol__release_tracked
#define buffer clvol__buffer
#define zeros clvol__zeros
#define padded clvol__padded
#define launch clvol__launch
#define set_args clvol__set_args
#define f4 clvol__f4
#define kernel clvol__kernel
#define open_device clvol__open_device
#define describe_device clvol__describe_device
#define build_program_at clvol__build_program_at
#define build_source clvol__build_source
#define host_release clvol__host_release
#define view_jitter clvol__view_jitter

#include <setjmp.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>

/* ------------------------------------------------------------------------- errors */

typedef struct guard {
    jmp_buf jump;
    clvol_status status;
    char *msg;                 /* where fail() writes the message */
    size_t msg_size;
    void **scratch;            /* host allocations of this call (xmalloc), freed at its end */
    int n_scratch, cap_scratch;
    struct guard *outer;
} guard;

extern _Thread_local guard *clvol_guard;
/* clvol_last_error(NULL): the message of the last failed clvol_create of this thread (and of
 * the calls that have no renderer to hold one: r = NULL, clvol_pick_device). */
extern _Thread_local char thread_error[1024];

void guard_init(guard *g, char *msg, size_t msg_size);
clvol_status guard_end(guard *g);      /* frees the call's scratch; returns g->status */
#if defined(__GNUC__)
#define CLVOL_PRINTF(a, b) __attribute__((format(printf, a, b)))
#else
#define CLVOL_PRINTF(a, b)
#endif
_Noreturn void fail(clvol_status status, const char *fmt, ...) CLVOL_PRINTF(2, 3);
#define BUNDLE CLVOL_ERROR_BUNDLE

const char *cl_error_name(cl_int e);
void cl_check(cl_int err, const char *call, const char *file, int line);
#define CL(call) cl_check((call), #call, __FILE__, __LINE__)
#define CLE(err, what) cl_check((err), (what), __FILE__, __LINE__)

void *xmalloc(size_t n);                /* freed at the end of the call unless kept */
void *xcalloc(size_t n, size_t size);
void xfree(void *p);                    /* free now */
void *keep(void *p);                    /* the renderer owns p from now on (plain free) */
char *xstrdup(const char *s);           /* not recorded: for memory the renderer owns */
double now_seconds(void);

/* --------------------------------------------------------------------- files, manifest */

char *path_join(const char *dir, const char *name);
char *read_file(const char *path, size_t *size);
void *read_raw4(const char *dir, const char *name, size_t count);

typedef struct {
    int n, cap;
    char **key, **val;
    char *where;
} manifest;

void manifest_read(manifest *m, const char *path);
void manifest_free(manifest *m);
const char *mf_find(const manifest *m, const char *key);
const char *mf_str(const manifest *m, const char *key);
void mf_doubles(const manifest *m, const char *key, double *out, int n);
double mf_double(const manifest *m, const char *key);
void mf_ints(const manifest *m, const char *key, int *out, int n);
int mf_int(const manifest *m, const char *key);
int mf_int_in(const manifest *m, const char *key, int lo, int hi);
int mf_has_word(const manifest *m, const char *key, const char *word);
void mf_float4(const manifest *m, const char *key, int n, cl_float4 *out);

/* ---------------------------------------------------------------------------- host */

enum { P_PYRAMID, P_MAJORANT, P_TRANS, P_TRANS_W1, P_TRANS_WL, P_GATHER, P_BAKE, P_MLP,
       P_VIEWDEPTH, P_RAYMARCH, P_PACK, N_PROGRAMS };
extern const char *const PROGRAM_NAMES[N_PROGRAMS];

#define MAX_MEMS 256
#define MAX_LEVELS 12

/* The multiple-scattering source the march runs (raymarch.cl's MS_SOURCE). SOURCE_NETWORK is
 * the bundle's network source: the world lattice, or (view = 1) the stochastic view table. */
enum { SOURCE_NONE, SOURCE_WRENNINGE, SOURCE_NETWORK };

/* The stochastic view source's state (clvol/render/ms/view.py StochasticViewMs and its
 * _History): the bundle's view.* keys, the draw counter, and per block of the current
 * layout the sums of F_ms, sample counts and depth sums since the history started. */
typedef struct {
    int block, block_auto, blocks_across, samples, still_samples, move_history, min_samples;
    int age;                    /* draws the history holds per block (capped through moves) */
    uint32_t seed;
    double step_factor;
    long draws;                 /* draws since clvol_create: the RNG stream's position */
    int reset;                  /* the history starts again at the next render */
    int bx, by, C;              /* the history's layout (0: none yet) */
    double *sums, *count, *depth;   /* [C][by][bx], [by][bx], [by][bx], owned */
    int have_camera;            /* the camera of the last draw (none after a reset) */
    double cam_origin[3], cam_fwd[3], cam_right[3], cam_up[3], cam_tan_half;
    long still;                 /* draws since the last move */
    cl_mem d_jitter, d_depths, d_weight, d_table;
    int cap;                    /* blocks the four buffers above hold */
} view_state;

struct clvol_renderer {
    /* OpenCL */
    cl_context ctx;
    cl_command_queue queue;
    cl_device_id device;
    int owns_context, is_pocl, is_cpu;
    int lanes;                  /* -D LANES of every program: the device's (describe_device) */
    const char *driver_opts;    /* clvol_driver_defines of its platform (describe_device) */
    cl_program prog[N_PROGRAMS];
    cl_kernel k_mip, k_majorant, k_layout, k_sweep1, k_sweepL, k_xpass, k_rows, k_small,
        k_gather, k_mlp, k_raymarch, k_pack, k_viewdepth;
    cl_mem mems[MAX_MEMS];
    int n_mems;
    /* errors */
    char err[1024];
    clvol_status broken;        /* an OpenCL or memory failure: later calls return it */
    /* bundle */
    char *dir;
    manifest mf;
    int pad, sweep_pad, sweep_block, sweep_slack, sweep_group, sweep_vmin, bake_min, bake_span,
        bake_pad, sort_bits, tile, rm_local;
    int cfg_dim, cfg_albedo, cfg_alpha;   /* the network config layout (host.config_*) */
    int source;                 /* SOURCE_*: the bundle's, fixed (its programs) */
    int view;                   /* the bundle's network source is the stochastic view table */
    view_state vs;
    /* volume (V) */
    int nx, ny, nz;
    double bmin[3], bmax[3], cube_min[3], cube_size;
    float *density;             /* [nz][ny][nx], owned */
    double unit_thickness;      /* largest optical thickness at density scale 1 */
    double max_density;         /* the largest density value (CLVOL_MAX_OPTICAL_DEPTH's rule) */
    double step_voxels, step;   /* march step: in voxels (the option) and world units */
    int lit, network, grey, channels, light_res, light_tau, block, skip_empty;
    cl_mem d_density, d_majorant, d_light_pyr, d_light, d_dummy;
    cl_mem d_light_layout[3], d_graded_layout[3];   /* per sweep axis, made on first use */
    int mx, my, mz;
    /* medium (M) */
    double albedo[3], density_scale;
    /* the ray marcher's medium block as the bundle wrote it (raymarch.medium) and the slots of
     * the density scale and albedo, which clvol_set_medium changes (host.medium_*) */
    double medium[16];
    int medium_ds_slot, medium_albedo_slot;
    /* the same for the light block (raymarch.light): direction and irradiance, which
     * clvol_set_light changes (host.light_*) */
    double light_block[16];
    int light_dir_slot, light_irradiance_slot;
    /* read once at create: the march's threshold and octaves, the queries' phase fields */
    double threshold, octave_abc[3], config_phase[16];
    /* network */
    int base, L, np_, npad, n_alpha, res[3];
    double lam, level_bias, ms_min[3], ms_max[3];
    float level_w[MAX_LEVELS];
    long loff[MAX_LEVELS];
    long pyr_size;
    cl_mem d_pyr, d_loff, d_graded, d_baked, d_params, d_tpl, d_pinfo, d_hl, d_ptab, d_wbuf,
        d_taufac;
    /* frame */
    int n_active;     /* lattice points the network evaluates; the others hold F_ms = 0 */
    int *active;      /* their [z][y][x] indices, ascending, owned */
    cl_mem d_points, d_omegas, d_order, d_feats, d_config, d_tenter, d_fms, d_planes;
    int net_cap;      /* queries the network's buffers above hold (d_points .. d_fms) */
    int net_chunk;    /* the most queries one gather + MLP launch takes (host.network_chunk) */
    cl_mem d_out[6];
    int width, height, out_width, out_height;
    double light_dir[3], irradiance[3], background[3];
    double cam_origin[3], cam_fwd[3], cam_right[3], cam_up[3], tan_half;
    /* what a change invalidated: done again by the next render */
    int volume_dirty, light_dirty, lattice_dirty;
    long counts[CLVOL_STAGE_COUNT];
    double t_light, t_volume, t_build;
};
typedef struct clvol_renderer clvol_host;

cl_mem track(clvol_host *h, cl_mem m);
void release_tracked(clvol_host *h, cl_mem *m);   /* release one tracked buffer, NULL it */
cl_mem buffer(clvol_host *h, size_t bytes, const void *init);
cl_mem zeros(clvol_host *h, size_t bytes);
size_t padded(size_t n, size_t multiple);
void launch(clvol_host *h, cl_kernel k, size_t global, size_t local);
void set_args(cl_kernel k, const char *types, ...);
cl_float4 f4(const double *v);
cl_kernel kernel(clvol_host *h, int prog, const char *name);

void open_device(clvol_host *h);
void describe_device(clvol_host *h);
cl_program build_program_at(clvol_host *h, const char *dir, const manifest *m,
                            const char *name);
cl_program build_source(clvol_host *h, const char *source, const char *options,
                        const char *what);
void host_release(clvol_host *h);   /* everything h holds; never fails */

/* The stochastic view source's jitter of draw `draw`: out[3 b + k] for block b < n, k < 3,
 * the first three uniforms of Philox4x32-10 keyed by seed, counter (b, 0, draw, 0)
 * (cl/include/rng.h; clvol/render/ms/view.py view_jitter draws the same floats). */
void view_jitter(uint32_t seed, uint32_t draw, long n, float *out);

#endif
