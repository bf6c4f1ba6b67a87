/* clvol-render: render a clvol bundle (``clvol bundle SCENE.toml DIR``) with the network method
 * from C, using only the OpenCL C API and libc. Walk-through and kernel ABI: docs/embedding.md.
 *
 *   clvol-render BUNDLE OUT.pfm [--frames N] [--device gpu|cpu|P:D]
 *   clvol-render --golden GOLDEN_DIR          (check the MLP and the gather against golden vectors)
 *
 * Steps (the Python host's, clvol/render/, in the same order and with the same launches):
 *   per volume   upload the density, majorant grid, resample the density to the light field's
 *                cube and to the network's pyramid base (host), mip chain (device);
 *   per light    light field (transmittance sweep, lambda = 1), graded transmittance (every
 *                pyramid level), bake of (tau, C) per level for the gather;
 *   per frame    F_ms at the bundle's active lattice points toward the camera (gather, MLP;
 *                the other points hold 0), ray march, read back.
 * A bundle whose scene the Python host renders with an analytic source instead of the network
 * (raymarch.ms_source = none or wrenninge: outside the network's domain, optically thin) runs
 * the light field and the march only.
 *
 * Embedding: clvol_host_create(dir, context, queue) takes an existing context and queue (or NULL,
 * NULL to make its own); every OpenCL call is checked, and a failure prints the call, the error
 * and the source line and exits with status 1 (replace fail() to report errors differently).
 */
#define CL_TARGET_OPENCL_VERSION 120
#define CL_USE_DEPRECATED_OPENCL_1_2_APIS
#include <CL/cl.h>

#include <ctype.h>
#include <errno.h>
#include <math.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

/* ------------------------------------------------------------------------------ API
 * (docs/embedding.md). One clvol_host renders one bundle; all work goes to one in-order queue. */
typedef struct clvol_host clvol_host;
/* context and queue: the caller's (both non-NULL; the caller keeps them) or NULL, NULL to make
 * a context and queue on `device` ("gpu", "cpu", "P:D", NULL: first GPU, else first CPU). */
clvol_host *clvol_host_create(const char *bundle_dir, cl_context context, cl_command_queue queue,
                              const char *device);
void clvol_host_set_light(clvol_host *h, const double dir[3]);          /* toward the light */
void clvol_host_set_camera(clvol_host *h, const double origin[3], const double forward[3],
                           const double right[3], const double up[3], double tan_half);
void clvol_host_render(clvol_host *h, float *rgb);   /* [height][width][3], top row first */
void clvol_host_destroy(clvol_host *h);

/* ------------------------------------------------------------------------------ errors */

static void fail(const char *fmt, ...) {
    va_list ap;
    va_start(ap, fmt);
    fputs("clvol-render: error: ", stderr);
    vfprintf(stderr, fmt, ap);
    fputc('\n', stderr);
    va_end(ap);
    exit(1);
}

static const char *cl_error_name(cl_int e) {
    switch (e) {
#define E(x) case x: return #x;
        E(CL_DEVICE_NOT_FOUND) E(CL_DEVICE_NOT_AVAILABLE) E(CL_COMPILER_NOT_AVAILABLE)
        E(CL_MEM_OBJECT_ALLOCATION_FAILURE) E(CL_OUT_OF_RESOURCES) E(CL_OUT_OF_HOST_MEMORY)
        E(CL_BUILD_PROGRAM_FAILURE) E(CL_INVALID_VALUE) E(CL_INVALID_DEVICE_TYPE)
        E(CL_INVALID_PLATFORM) E(CL_INVALID_DEVICE) E(CL_INVALID_CONTEXT)
        E(CL_INVALID_COMMAND_QUEUE) E(CL_INVALID_HOST_PTR) E(CL_INVALID_MEM_OBJECT)
        E(CL_INVALID_BUILD_OPTIONS) E(CL_INVALID_PROGRAM) E(CL_INVALID_PROGRAM_EXECUTABLE)
        E(CL_INVALID_KERNEL_NAME) E(CL_INVALID_KERNEL) E(CL_INVALID_ARG_INDEX)
        E(CL_INVALID_ARG_VALUE) E(CL_INVALID_ARG_SIZE) E(CL_INVALID_KERNEL_ARGS)
        E(CL_INVALID_WORK_DIMENSION) E(CL_INVALID_WORK_GROUP_SIZE) E(CL_INVALID_WORK_ITEM_SIZE)
        E(CL_INVALID_GLOBAL_OFFSET) E(CL_INVALID_EVENT_WAIT_LIST) E(CL_INVALID_OPERATION)
        E(CL_INVALID_BUFFER_SIZE) E(CL_INVALID_GLOBAL_WORK_SIZE) case -1001: return "CL_PLATFORM_NOT_FOUND_KHR (no ICD installed)";
#undef E
    default: return "unknown OpenCL error";
    }
}

static void cl_check(cl_int err, const char *call, int line) {
    if (err != CL_SUCCESS)
        fail("OpenCL call %s failed with %s (%d) at clvol_render.c:%d", call, cl_error_name(err),
             (int)err, line);
}
#define CL(call) cl_check((call), #call, __LINE__)
#define CLE(err, what) cl_check((err), (what), __LINE__)

static void *xmalloc(size_t n) {
    void *p = malloc(n ? n : 1);
    if (!p) fail("out of host memory (%zu bytes)", n);
    return p;
}

static double now_seconds(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* ---------------------------------------------------------------------------- files */

static char *path_join(const char *dir, const char *name) {
    size_t n = strlen(dir) + strlen(name) + 2;
    char *p = xmalloc(n);
    snprintf(p, n, "%s/%s", dir, name);
    return p;
}

static char *read_file(const char *path, size_t *size) {
    FILE *f = fopen(path, "rb");
    if (!f) fail("%s: cannot open (%s)", path, strerror(errno));
    if (fseek(f, 0, SEEK_END) != 0) fail("%s: cannot seek", path);
    long n = ftell(f);
    if (n < 0) fail("%s: cannot size", path);
    rewind(f);
    char *buf = xmalloc((size_t)n + 1);
    if (n && fread(buf, 1, (size_t)n, f) != (size_t)n) fail("%s: short read", path);
    buf[n] = 0;
    fclose(f);
    if (size) *size = (size_t)n;
    return buf;
}

/* A raw little-endian 4-byte array of exactly `count` elements (this host is little-endian). */
static void *read_raw4(const char *dir, const char *name, size_t count) {
    char *path = path_join(dir, name);
    size_t n;
    char *buf = read_file(path, &n);
    if (n != 4 * count) fail("%s: %zu bytes, expected %zu (%zu values)", path, n, 4 * count, count);
    free(path);
    return buf;
}

/* ------------------------------------------------------------------------- manifest */

typedef struct {
    int n;
    char **key, **val;
    char *where;
} manifest;

static char *trim(char *s) {
    while (isspace((unsigned char)*s)) ++s;
    char *e = s + strlen(s);
    while (e > s && isspace((unsigned char)e[-1])) *--e = 0;
    return s;
}

static void manifest_read(manifest *m, const char *path) {
    char *text = read_file(path, NULL);
    int cap = 64;
    m->n = 0;
    m->key = xmalloc(cap * sizeof(char *));
    m->val = xmalloc(cap * sizeof(char *));
    m->where = strdup(path);
    char *save = NULL;
    for (char *line = strtok_r(text, "\n", &save); line; line = strtok_r(NULL, "\n", &save)) {
        char *hash = strchr(line, '#');
        if (hash) *hash = 0;
        char *eq = strchr(line, '=');
        if (!eq) {
            if (*trim(line)) fail("%s: line without '=': %s", path, line);
            continue;
        }
        *eq = 0;
        if (m->n == cap) {
            cap *= 2;
            char **k = realloc(m->key, cap * sizeof(char *)), **v;
            if (!k) fail("out of host memory");
            m->key = k;
            v = realloc(m->val, cap * sizeof(char *));
            if (!v) fail("out of host memory");
            m->val = v;
        }
        m->key[m->n] = strdup(trim(line));
        m->val[m->n] = strdup(trim(eq + 1));
        m->n++;
    }
    free(text);
}

static void manifest_free(manifest *m) {
    for (int i = 0; i < m->n; ++i) {
        free(m->key[i]);
        free(m->val[i]);
    }
    free(m->key);
    free(m->val);
    free(m->where);
    m->n = 0;   /* empty again: freeing twice is harmless */
    m->key = m->val = NULL;
    m->where = NULL;
}

static const char *mf_find(const manifest *m, const char *key) {
    for (int i = 0; i < m->n; ++i)
        if (strcmp(m->key[i], key) == 0) return m->val[i];
    return NULL;
}

static const char *mf_str(const manifest *m, const char *key) {
    const char *v = mf_find(m, key);
    if (!v) fail("%s: missing key %s", m->where, key);
    return v;
}

/* Exactly n numbers. */
static void mf_doubles(const manifest *m, const char *key, double *out, int n) {
    const char *s = mf_str(m, key);
    for (int i = 0; i < n; ++i) {
        char *end;
        errno = 0;
        out[i] = strtod(s, &end);
        if (end == s || errno) fail("%s: %s = %s: expected %d numbers", m->where, key, mf_str(m, key), n);
        s = end;
    }
    while (isspace((unsigned char)*s)) ++s;
    if (*s) fail("%s: %s: expected %d numbers, found more", m->where, key, n);
}

static double mf_double(const manifest *m, const char *key) {
    double v;
    mf_doubles(m, key, &v, 1);
    return v;
}

static void mf_ints(const manifest *m, const char *key, int *out, int n) {
    double d[8];
    if (n > 8) fail("internal: mf_ints n > 8");
    mf_doubles(m, key, d, n);
    for (int i = 0; i < n; ++i) {
        if (d[i] != floor(d[i]) || fabs(d[i]) > 2147483647.0)
            fail("%s: %s: %g is not an int", m->where, key, d[i]);
        out[i] = (int)d[i];
    }
}

static int mf_int(const manifest *m, const char *key) {
    int v;
    mf_ints(m, key, &v, 1);
    return v;
}

/* Whether the space-separated list `key` holds `word`. */
static int mf_has_word(const manifest *m, const char *key, const char *word) {
    const char *s = mf_str(m, key);
    size_t n = strlen(word);
    while (*s) {
        while (isspace((unsigned char)*s)) ++s;
        size_t k = 0;
        while (s[k] && !isspace((unsigned char)s[k])) ++k;
        if (k == n && strncmp(s, word, n) == 0) return 1;
        s += k;
    }
    return 0;
}

static void mf_float4(const manifest *m, const char *key, int n, cl_float4 *out) {
    double d[4] = {0, 0, 0, 0};
    mf_doubles(m, key, d, n);
    for (int i = 0; i < 4; ++i) out->s[i] = (float)d[i];
}

/* --------------------------------------------------------------------------- host */

enum { P_PYRAMID, P_MAJORANT, P_TRANS, P_TRANS_W1, P_TRANS_W16, P_GATHER, P_BAKE, P_MLP,
       P_RAYMARCH, N_PROGRAMS };
static const char *const PROGRAM_NAMES[N_PROGRAMS] = {
    "pyramid", "majorant", "transmittance", "transmittance_w1", "transmittance_w16", "gather",
    "gather_bake", "mlp", "raymarch"};

#define MAX_MEMS 256
#define MAX_LEVELS 12

struct clvol_host {
    /* OpenCL */
    cl_context ctx;
    cl_command_queue queue;
    cl_device_id device;
    int owns_context, is_pocl, is_cpu;
    cl_program prog[N_PROGRAMS];
    cl_kernel k_mip, k_majorant, k_layout, k_sweep1, k_sweep16, k_xpass, k_rows, k_small,
        k_gather, k_mlp, k_raymarch;
    cl_mem mems[MAX_MEMS];
    int n_mems;
    /* bundle */
    char *dir;
    manifest mf;
    int pad, sweep_pad, sweep_block, sweep_slack, sweep_group, sweep_vmin, bake_min, bake_span,
        bake_pad, sort_bits, mlp_qpi, tile, rm_local;
    /* volume */
    int nx, ny, nz;
    double bmin[3], bmax[3], cube_min[3], cube_size, density_scale;
    float *density;
    int lit, network, grey, channels, light_res, light_tau, block, skip_empty;
    cl_mem d_density, d_majorant, d_light_pyr, d_light, d_dummy;
    int mx, my, mz;
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
    int *active;      /* their [z][y][x] indices, ascending */
    cl_mem d_points, d_omegas, d_order, d_feats, d_config, d_tenter, d_fms, d_planes;
    cl_mem d_out[6];
    int width, height;
    double light_dir[3], cam_origin[3], cam_fwd[3], cam_right[3], cam_up[3], tan_half;
    double t_light, t_volume, t_build;
};

static cl_mem track(clvol_host *h, cl_mem m) {
    if (h->n_mems == MAX_MEMS) fail("internal: more than %d buffers", MAX_MEMS);
    h->mems[h->n_mems++] = m;
    return m;
}

static cl_mem buffer(clvol_host *h, size_t bytes, const void *init) {
    cl_int err;
    if (bytes < 4) bytes = 4;    /* zero-size buffers are invalid */
    cl_mem m = clCreateBuffer(h->ctx, CL_MEM_READ_WRITE | (init ? CL_MEM_COPY_HOST_PTR : 0), bytes,
                              (void *)init, &err);
    CLE(err, "clCreateBuffer");
    return track(h, m);
}

static cl_mem zeros(clvol_host *h, size_t bytes) {
    cl_mem m = buffer(h, bytes, NULL);
    const cl_float z = 0.0f;
    CL(clEnqueueFillBuffer(h->queue, m, &z, sizeof z, 0, bytes < 4 ? 4 : bytes, 0, NULL, NULL));
    return m;
}

static size_t padded(size_t n, size_t multiple) {
    if (n < 1) n = 1;
    return (n + multiple - 1) / multiple * multiple;
}

static void launch(clvol_host *h, cl_kernel k, size_t global, size_t local) {
    size_t g = global, l = local;
    CL(clEnqueueNDRangeKernel(h->queue, k, 1, NULL, &g, local ? &l : NULL, 0, NULL, NULL));
}

/* Set a kernel's arguments in order: 'm' cl_mem, 'i' int, 'f' float (passed as double),
 * '4' cl_float4 *. */
static void set_args(cl_kernel k, const char *types, ...) {
    va_list ap;
    va_start(ap, types);
    cl_uint n_args = 0;
    CL(clGetKernelInfo(k, CL_KERNEL_NUM_ARGS, sizeof n_args, &n_args, NULL));
    char name[64] = "?";
    CL(clGetKernelInfo(k, CL_KERNEL_FUNCTION_NAME, sizeof name, name, NULL));
    if (strlen(types) != n_args) fail("kernel %s takes %u arguments, the host gives %zu", name, n_args, strlen(types));
    for (cl_uint i = 0; types[i]; ++i) {
        cl_int err = CL_SUCCESS;
        switch (types[i]) {
        case 'm': { cl_mem v = va_arg(ap, cl_mem); err = clSetKernelArg(k, i, sizeof v, &v); break; }
        case 'i': { cl_int v = va_arg(ap, int); err = clSetKernelArg(k, i, sizeof v, &v); break; }
        case 'f': { cl_float v = (cl_float)va_arg(ap, double); err = clSetKernelArg(k, i, sizeof v, &v); break; }
        case '4': { cl_float4 *v = va_arg(ap, cl_float4 *); err = clSetKernelArg(k, i, sizeof *v, v); break; }
        default: fail("internal: bad argument type %c", types[i]);
        }
        if (err != CL_SUCCESS)
            fail("OpenCL call clSetKernelArg(%s, %u) failed with %s (%d)", name, i, cl_error_name(err), (int)err);
    }
    va_end(ap);
}

static cl_float4 f4(const double *v) {
    cl_float4 r = {{(float)v[0], (float)v[1], (float)v[2], 0.0f}};
    return r;
}

static cl_kernel kernel(clvol_host *h, int prog, const char *name) {
    cl_int err;
    cl_kernel k = clCreateKernel(h->prog[prog], name, &err);
    if (err != CL_SUCCESS) fail("%s has no kernel %s (%s)", PROGRAM_NAMES[prog], name, cl_error_name(err));
    return k;
}

/* ------------------------------------------------------------------- device and build */

static void choose_device(clvol_host *h, const char *spec) {
    cl_uint np = 0;
    cl_int err = clGetPlatformIDs(0, NULL, &np);
    if (err != CL_SUCCESS || np == 0)
        fail("no OpenCL platform found (install an ICD, e.g. pocl-opencl-icd)");
    cl_platform_id plats[16];
    if (np > 16) np = 16;
    CL(clGetPlatformIDs(np, plats, NULL));
    cl_device_id best = NULL;
    int best_rank = 99;
    for (cl_uint p = 0; p < np; ++p) {
        cl_uint nd = 0;
        if (clGetDeviceIDs(plats[p], CL_DEVICE_TYPE_ALL, 0, NULL, &nd) != CL_SUCCESS) continue;
        cl_device_id devs[16];
        if (nd > 16) nd = 16;
        CL(clGetDeviceIDs(plats[p], CL_DEVICE_TYPE_ALL, nd, devs, NULL));
        for (cl_uint d = 0; d < nd; ++d) {
            cl_device_type t;
            CL(clGetDeviceInfo(devs[d], CL_DEVICE_TYPE, sizeof t, &t, NULL));
            int rank = (t & CL_DEVICE_TYPE_GPU) ? 0 : (t & CL_DEVICE_TYPE_CPU) ? 1 : 2;
            if (spec) {   /* "gpu", "cpu" or "P:D" */
                char pd[32];
                snprintf(pd, sizeof pd, "%u:%u", p, d);
                int match = strcmp(spec, pd) == 0 || (strcmp(spec, "gpu") == 0 && rank == 0)
                            || (strcmp(spec, "cpu") == 0 && rank == 1);
                rank = match ? 0 : 99;
            }
            if (rank < best_rank) {
                best_rank = rank;
                best = devs[d];
            }
        }
    }
    if (!best || best_rank == 99) fail("no OpenCL device matches %s", spec ? spec : "(any)");
    h->device = best;
}

/* A new context and in-order queue on the device `spec` picks (choose_device), owned by `h`. */
static void open_device(clvol_host *h, const char *spec) {
    cl_int err;
    choose_device(h, spec);
    h->ctx = clCreateContext(NULL, 1, &h->device, NULL, NULL, &err);
    CLE(err, "clCreateContext");
    h->queue = clCreateCommandQueue(h->ctx, h->device, 0, &err);
    CLE(err, "clCreateCommandQueue");
    h->owns_context = 1;
}

static void describe_device(clvol_host *h) {
    cl_platform_id plat;
    char name[256];
    cl_device_type t;
    CL(clGetDeviceInfo(h->device, CL_DEVICE_PLATFORM, sizeof plat, &plat, NULL));
    CL(clGetPlatformInfo(plat, CL_PLATFORM_NAME, sizeof name, name, NULL));
    name[sizeof name - 1] = 0;
    /* PoCL gets the Clang-only fast paths the Python host also enables there */
    h->is_pocl = strstr(name, "Portable Computing Language") != NULL;
    CL(clGetDeviceInfo(h->device, CL_DEVICE_TYPE, sizeof t, &t, NULL));
    h->is_cpu = (t & CL_DEVICE_TYPE_CPU) != 0;
}

/* Kernel sources with their quoted #includes pasted in from the include folder (each header
 * once; they have include guards too), so the build options hold no file paths: the same
 * program then hits the OpenCL driver's build cache from any bundle folder (PoCL keys its
 * cache on the source and the options), and the build does not depend on the working folder. */
typedef struct {
    char *s;
    size_t len, cap;
} strbuf;

static void sb_add(strbuf *b, const char *s, size_t n) {
    if (b->len + n + 1 > b->cap) {
        b->cap = 2 * (b->len + n + 1);
        char *t = realloc(b->s, b->cap);
        if (!t) fail("out of host memory");
        b->s = t;
    }
    memcpy(b->s + b->len, s, n);
    b->len += n;
    b->s[b->len] = 0;
}

#define MAX_HEADERS 32
static void expand_source(const char *path, const char *label, const char *inc_dir, strbuf *out,
                          char **seen, int *n_seen, int depth) {
    if (depth > 8) fail("%s: #include nesting deeper than 8", path);
    char *text = read_file(path, NULL), line_dir[600];
    int line_no = 0;
    snprintf(line_dir, sizeof line_dir, "#line 1 \"%s\"\n", label);
    sb_add(out, line_dir, strlen(line_dir));
    for (char *p = text; *p;) {
        char *end = strchr(p, '\n');
        size_t n = end ? (size_t)(end - p) + 1 : strlen(p);
        ++line_no;
        const char *q = p;
        while (*q == ' ' || *q == '\t') ++q;
        if (strncmp(q, "#include \"", 10) == 0) {
            const char *name = q + 10, *close = strchr(name, '"');
            if (!close || close > p + n) fail("%s:%d: malformed #include", path, line_no);
            char hdr[256];
            snprintf(hdr, sizeof hdr, "%.*s", (int)(close - name), name);
            int done = 0;
            for (int i = 0; i < *n_seen; ++i) done |= strcmp(seen[i], hdr) == 0;
            if (!done) {
                if (*n_seen == MAX_HEADERS) fail("more than %d headers", MAX_HEADERS);
                seen[(*n_seen)++] = strdup(hdr);
                char *hp = path_join(inc_dir, hdr);
                expand_source(hp, hdr, inc_dir, out, seen, n_seen, depth + 1);
                free(hp);
            }
            snprintf(line_dir, sizeof line_dir, "#line %d \"%s\"\n", line_no + 1, label);
            sb_add(out, line_dir, strlen(line_dir));
        } else {
            sb_add(out, p, n);
        }
        p += n;
    }
    sb_add(out, "\n", 1);
    free(text);
}

static cl_program build_program_at(clvol_host *h, const char *dir, const manifest *m,
                                   const char *name) {
    char key[96];
    snprintf(key, sizeof key, "program.%s", name);
    const char *rel = mf_str(m, key);
    char *path = path_join(dir, rel);
    char *inc = path_join(dir, mf_str(m, "include_dir"));
    strbuf src = {NULL, 0, 0};
    char *seen[MAX_HEADERS];
    int n_seen = 0;
    const char *label = strrchr(rel, '/') ? strrchr(rel, '/') + 1 : rel;
    expand_source(path, label, inc, &src, seen, &n_seen, 0);
    for (int i = 0; i < n_seen; ++i) free(seen[i]);
    snprintf(key, sizeof key, "program.%s.options", name);
    const char *opts = mf_str(m, key);
    snprintf(key, sizeof key, "program.%s.options_pocl", name);
    const char *pocl = h->is_pocl ? mf_find(m, key) : NULL;
    size_t n = strlen(opts) + (pocl ? strlen(pocl) : 0) + 4;
    char *options = xmalloc(n);
    snprintf(options, n, "%s %s", opts, pocl ? pocl : "");
    cl_int err;
    const char *srcs[1] = {src.s};
    cl_program p = clCreateProgramWithSource(h->ctx, 1, srcs, NULL, &err);
    CLE(err, "clCreateProgramWithSource");
    err = clBuildProgram(p, 1, &h->device, options, NULL, NULL);
    if (err != CL_SUCCESS) {
        size_t len = 0;
        clGetProgramBuildInfo(p, h->device, CL_PROGRAM_BUILD_LOG, 0, NULL, &len);
        char *log = xmalloc(len + 1);
        log[0] = 0;
        clGetProgramBuildInfo(p, h->device, CL_PROGRAM_BUILD_LOG, len, log, NULL);
        log[len] = 0;
        fprintf(stderr, "%s\n", log);
        fail("%s failed to build (%s) with options %s", path, cl_error_name(err), options);
    }
    free(options);
    free(inc);
    free(src.s);
    free(path);
    return p;
}

static void build_program(clvol_host *h, int idx, const char *name) {
    h->prog[idx] = build_program_at(h, h->dir, &h->mf, name);
}

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
        free(d);
        free(r.first);
        free(r.w);
        d = next;
    }
    for (long i = 0; i < (long)base * base * base; ++i) out[i] = (float)d[i];
    free(d);
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
 * sweep_layout); returns the buffer, offsets in s_off. */
static cl_mem sweep_layout(clvol_host *h, cl_mem pyr, const long *loff, int base, int n_levels,
                           int axis, long *s_off) {
    long total = 0;
    for (int l = 0; l < n_levels; ++l) {
        s_off[l] = total;
        total += layout_size(h, base >> l);
    }
    cl_mem buf = buffer(h, 4 * (size_t)(total + h->sweep_slack), NULL);
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
    int width = n >= h->sweep_vmin ? 16 : 1;
    cl_kernel k = width == 16 ? h->k_sweep16 : h->k_sweep1;
    if (!k) fail("%s: program transmittance_w%d is not in the bundle's programs", h->mf.where, width);
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
    long n_vox = (width == 16 && g.a == 0) ? (long)n * n / 16 : (long)SB * n * (n / width);
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
    free(stab);
    free(sftab);
    free(btab);
}

/* ----------------------------------------------------------------------------- setup */

/* mf_int within [lo, hi]: the host constants size buffers and divide work sizes, so a
 * corrupt one must stop here, not as a division by zero or a kernel reading out of bounds
 * (both found by fuzzing mutated bundles). */
static int mf_int_in(const manifest *m, const char *key, int lo, int hi) {
    int v = mf_int(m, key);
    if (v < lo || v > hi) fail("%s: %s = %d: must be in [%d, %d]", m->where, key, v, lo, hi);
    return v;
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
    h->mlp_qpi = mf_int_in(m, "host.mlp_queries_per_item", 1, 64);
    h->tile = mf_int_in(m, "host.raymarch_tile", 1, 16);
    h->rm_local = mf_int_in(m, "host.raymarch_local_size", 1, 1024);
}

/* Build the programs and upload everything that depends on the volume only. */
static void setup_volume(clvol_host *h) {
    const manifest *m = &h->mf;
    double t0 = now_seconds();
    int dims[3];
    mf_ints(m, "density.dims", dims, 3);
    h->nx = dims[0], h->ny = dims[1], h->nz = dims[2];
    if (h->nx < 1 || h->ny < 1 || h->nz < 1) fail("%s: density.dims must be >= 1", m->where);
    mf_doubles(m, "density.bbox_min", h->bmin, 3);
    mf_doubles(m, "density.bbox_max", h->bmax, 3);
    size_t count = (size_t)h->nx * h->ny * h->nz;
    h->density = read_raw4(h->dir, mf_str(m, "density.file"), count);
    h->density_scale = mf_double(m, "medium.density_scale");
    h->lit = mf_int(m, "raymarch.lit");
    const char *src = mf_str(m, "raymarch.ms_source");
    if (strcmp(src, "network") != 0 && strcmp(src, "none") != 0 && strcmp(src, "wrenninge") != 0)
        fail("%s: raymarch.ms_source = %s: this host runs network, none or wrenninge", m->where, src);
    /* none and wrenninge are the kernel's own (raymarch.cl's -D MS_SOURCE): no network */
    h->network = h->lit && strcmp(src, "network") == 0;
    h->grey = mf_int(m, "medium.grey");
    h->channels = mf_int(m, "raymarch.channels");
    h->light_res = mf_int(m, "raymarch.light_resolution");
    h->light_tau = mf_int(m, "raymarch.light_tau");
    h->block = mf_int(m, "raymarch.block");
    h->width = mf_int(m, "camera.width");
    h->height = mf_int(m, "camera.height");
    if (h->width < 1 || h->height < 1) fail("%s: camera size must be >= 1", m->where);
    /* the smallest cube centred on the box (clvol/kernels/pyramid.py cube_of) */
    double ext = 0.0;
    for (int a = 0; a < 3; ++a) ext = fmax(ext, h->bmax[a] - h->bmin[a]);
    h->cube_size = ext;
    for (int a = 0; a < 3; ++a) h->cube_min[a] = 0.5 * (h->bmin[a] + h->bmax[a]) - 0.5 * ext;

    /* the programs the bundle lists (what the Python host builds for this scene: unlit scenes
     * need only the majorant and the march, analytic sources no network) */
    for (int p = 0; p < N_PROGRAMS; ++p)
        if (mf_has_word(m, "programs", PROGRAM_NAMES[p])) build_program(h, p, PROGRAM_NAMES[p]);
    h->t_build = now_seconds() - t0;
    h->k_majorant = kernel(h, P_MAJORANT, "majorant_build");
    if (h->lit) {
        h->k_layout = kernel(h, P_TRANS, "sweep_layout");
        /* the widths the bundle's levels use (one of them when only the light field is swept) */
        if (h->prog[P_TRANS_W1]) h->k_sweep1 = kernel(h, P_TRANS_W1, "transmittance_sweep_block");
        if (h->prog[P_TRANS_W16]) h->k_sweep16 = kernel(h, P_TRANS_W16, "transmittance_sweep_block");
    }
    if (h->network) {
        h->k_mip = kernel(h, P_PYRAMID, "mip_reduce");
        h->k_xpass = kernel(h, P_BAKE, "bake_xpass");
        h->k_rows = kernel(h, P_BAKE, "bake_rows");
        h->k_small = kernel(h, P_BAKE, "bake_small");
        h->k_gather = kernel(h, P_GATHER, "gather");
        h->k_mlp = kernel(h, P_MLP, "mlp_forward");
    }
    h->k_raymarch = kernel(h, P_RAYMARCH, "raymarch");

    h->d_dummy = buffer(h, 4, NULL);
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
        free(lv0);
        h->d_light = buffer(h, 4 * (size_t)n * n * n, NULL);
    }
    if (h->network) {
        /* network pyramid: base^3 on the host, the mip chain on the device */
        h->base = mf_int(m, "network.base_resolution");
        h->L = mf_int(m, "network.n_levels");
        if (h->L < 1 || h->L > MAX_LEVELS || (h->base >> (h->L - 1)) != 1)
            fail("%s: network.n_levels = %d does not match base %d", m->where, h->L, h->base);
        h->pyr_size = 0;
        for (int l = 0; l < h->L; ++l) {
            long nl = h->base >> l;
            h->loff[l] = h->pyr_size;
            h->pyr_size += nl * nl * nl;
        }
        float *pyr = calloc((size_t)h->pyr_size, sizeof(float));
        if (!pyr) fail("out of host memory");
        resample_to_cube(h, h->base, pyr);
        h->d_pyr = buffer(h, 4 * (size_t)h->pyr_size, pyr);
        free(pyr);
        for (int l = 1; l < h->L; ++l) {
            int nd = h->base >> l;
            set_args(h->k_mip, "miii", h->d_pyr, (int)h->loff[l - 1], (int)h->loff[l], nd);
            launch(h, h->k_mip, padded((size_t)nd * nd * nd, (size_t)h->pad), 0);
        }
        int loff32[MAX_LEVELS];
        for (int l = 0; l < h->L; ++l) loff32[l] = (int)h->loff[l];
        h->d_loff = buffer(h, sizeof(int) * (size_t)h->L, loff32);

        /* network weights and the gather's tables */
        h->lam = mf_double(m, "network.lambda");
        int range[2];
        mf_ints(m, "network.params", range, 2);
        int lwr[2];
        mf_ints(m, "network.level_weights", lwr, 2);
        if (lwr[1] != h->L) fail("%s: %d level weights for %d levels", m->where, lwr[1], h->L);
        int lb = mf_int(m, "network.level_bias");
        char *path = path_join(h->dir, mf_str(m, "network.file"));
        size_t nbytes;
        float *net = (float *)read_file(path, &nbytes);
        if (nbytes / 4 < (size_t)range[0] + range[1] || nbytes / 4 < (size_t)lwr[0] + lwr[1]
            || nbytes / 4 <= (size_t)lb)
            fail("%s: %zu bytes, too short for the tensors the manifest names", path, nbytes);
        h->d_params = buffer(h, 4 * (size_t)range[1], net + range[0]);
        for (int l = 0; l < h->L; ++l) h->level_w[l] = net[lwr[0] + l];
        h->level_bias = net[lb];
        free(net);
        free(path);
        h->d_wbuf = buffer(h, sizeof(float) * (size_t)h->L, h->level_w);
        float taufac[MAX_LEVELS];
        for (int l = 0; l < h->L; ++l)
            taufac[l] = (float)(h->density_scale * (h->cube_size / (double)(h->base >> l)));
        h->d_taufac = buffer(h, sizeof(float) * (size_t)h->L, taufac);
        h->np_ = mf_int(m, "gather.np");
        h->npad = mf_int(m, "gather.npad");
        h->n_alpha = mf_int(m, "gather.n_alpha");
        float *tpl = read_raw4(h->dir, mf_str(m, "gather.templates"), 3 * (size_t)h->npad);
        int *pinfo = read_raw4(h->dir, mf_str(m, "gather.pinfo"), (size_t)h->npad);
        float *ptab = read_raw4(h->dir, mf_str(m, "gather.phase_table"), (size_t)h->n_alpha * h->npad);
        /* The gather indexes levels and voxels with these: a level outside the pyramid or a
         * non-finite position would read outside its buffers (a fuzzed bundle crashed the
         * kernel that way), so they are checked here. */
        for (int j = 0; j < h->npad; ++j) {
            if (pinfo[j] >= h->L || pinfo[j] < -4)
                fail("%s: gather.pinfo[%d] = %d: must be a level 0..%d or a highlight layer "
                     "-1..-4", m->where, j, pinfo[j], h->L - 1);
            for (int a = 0; a < 3; ++a)
                if (!isfinite(tpl[(size_t)a * h->npad + j]))
                    fail("%s: gather.templates: point %d is not finite", m->where, j);
        }
        for (size_t j = 0; j < (size_t)h->n_alpha * h->npad; ++j)
            if (!isfinite(ptab[j]))
                fail("%s: gather.phase_table: entry %zu is not finite", m->where, j);
        double hl[4];
        mf_doubles(m, "gather.hl_spacing", hl, 4);
        for (int k = 0; k < 4; ++k)
            if (!(isfinite(hl[k]) && hl[k] >= 0.0))
                fail("%s: gather.hl_spacing[%d] = %g: must be finite and >= 0", m->where, k, hl[k]);
        float hlf[4] = {(float)hl[0], (float)hl[1], (float)hl[2], (float)hl[3]};
        h->d_tpl = buffer(h, 4 * 3 * (size_t)h->npad, tpl);
        h->d_pinfo = buffer(h, 4 * (size_t)h->npad, pinfo);
        h->d_ptab = buffer(h, 4 * (size_t)h->n_alpha * h->npad, ptab);
        h->d_hl = buffer(h, sizeof hlf, hlf);
        free(tpl);
        free(pinfo);
        free(ptab);
        h->d_graded = buffer(h, 4 * (size_t)h->pyr_size, NULL);
        h->d_baked = buffer(h, 4 * (size_t)(2 * h->pyr_size + h->bake_pad), NULL);
        const cl_float z = 0.0f;
        CL(clEnqueueFillBuffer(h->queue, h->d_baked, &z, sizeof z, 4 * (size_t)(2 * h->pyr_size),
                               4 * (size_t)h->bake_pad, 0, NULL, NULL));
        /* the lattice points the network evaluates */
        mf_ints(m, "network.ms_resolution", h->res, 3);
        long N = (long)h->res[0] * h->res[1] * h->res[2];
        if (h->res[0] < 1 || h->res[1] < 1 || h->res[2] < 1 || N > 1L << 24)
            fail("%s: network.ms_resolution out of range", m->where);
        h->n_active = mf_int(m, "network.active_points");
        if (h->n_active < 0 || h->n_active > N)
            fail("%s: network.active_points = %d: must be in [0, %ld]", m->where, h->n_active, N);
        h->active = read_raw4(h->dir, mf_str(m, "network.active_file"), (size_t)h->n_active);
        for (int k = 0; k < h->n_active; ++k)
            if (h->active[k] < 0 || h->active[k] >= N || (k && h->active[k] <= h->active[k - 1]))
                fail("%s: network.active_file: index %d at %d is out of range or not ascending",
                     m->where, h->active[k], k);
    }
    CL(clFinish(h->queue));
    h->t_volume = now_seconds() - t0;
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

/* Per light: the light field and the graded transmittance + bake for the gather, for a light
 * toward `dir` (normalised here). Scratch buffers are released before returning. */
void clvol_host_set_light(clvol_host *h, const double dir[3]) {
    double norm = sqrt(dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]);
    if (!(norm > 0.0) || !isfinite(norm)) fail("light direction must be a finite non-zero vector");
    double l[3] = {dir[0] / norm, dir[1] / norm, dir[2] / norm};
    memcpy(h->light_dir, l, sizeof l);
    if (!h->lit) return;
    double t0 = now_seconds();
    int mark = h->n_mems;
    sweep_geom g = sweep_geometry(l);
    long s_off[MAX_LEVELS];
    long zero = 0;
    /* light field: lambda = 1 on the light cube's level 0 */
    int n = h->light_res;
    cl_mem lay = sweep_layout(h, h->d_light_pyr, &zero, n, 1, g.a, s_off);
    sweep_level(h, lay, s_off[0], n, h->density_scale * (h->cube_size / n), l, h->light_tau,
                h->d_light, 0);
    if (h->network) {
        /* graded transmittance: every level l with lambda^(l+1) */
        cl_mem glay = sweep_layout(h, h->d_pyr, h->loff, h->base, h->L, g.a, s_off);
        for (int lv = 0; lv < h->L; ++lv) {
            int nl = h->base >> lv;
            double scale = pow(h->lam, lv + 1) * h->density_scale * (h->cube_size / nl);
            sweep_level(h, glay, s_off[lv], nl, scale, l, 0, h->d_graded, h->loff[lv]);
        }
        bake(h);
    }
    CL(clFinish(h->queue));
    for (int i = mark; i < h->n_mems; ++i) CL(clReleaseMemObject(h->mems[i]));
    h->n_mems = mark;
    h->t_light = now_seconds() - t0;
}

/* Per camera: a pinhole at `origin` with an orthonormal basis (forward, right, up) and
 * tan(fov_y / 2); the image size is the bundle's. */
void clvol_host_set_camera(clvol_host *h, const double origin[3], const double forward[3],
                           const double right[3], const double up[3], double tan_half) {
    memcpy(h->cam_origin, origin, sizeof h->cam_origin);
    memcpy(h->cam_fwd, forward, sizeof h->cam_fwd);
    memcpy(h->cam_right, right, sizeof h->cam_right);
    memcpy(h->cam_up, up, sizeof h->cam_up);
    h->tan_half = tan_half;
}

static uint32_t spread_bits(uint32_t v, int bits) {
    uint32_t out = 0;
    for (int b = 0; b < bits; ++b) out |= ((v >> b) & 1u) << (3 * b);
    return out;
}

/* Per frame: F_ms lattice (gather + MLP) and the march for the current camera and light;
 * `rgb` gets the total radiance, [height][width][3] float, top row first. */
void clvol_host_render(clvol_host *h, float *rgb) {
    const manifest *m = &h->mf;
    double irr[3], alb[3], bg[3], abc[3];
    const double *origin = h->cam_origin, *fwd = h->cam_fwd, *right = h->cam_right,
                 *up = h->cam_up, *l = h->light_dir;
    mf_doubles(m, "light.irradiance", irr, 3);
    mf_doubles(m, "medium.albedo", alb, 3);
    mf_doubles(m, "light.background", bg, 3);
    mf_doubles(m, "raymarch.octave_abc", abc, 3);
    int gres[3] = {1, 1, 1};
    int C = 1;
    cl_mem planes = h->d_dummy;
    double gmin[3] = {0, 0, 0}, gmax[3] = {1, 1, 1};
    if (h->network) {
        mf_doubles(m, "network.ms_bbox_min", h->ms_min, 3);
        mf_doubles(m, "network.ms_bbox_max", h->ms_max, 3);
        for (int a = 0; a < 3; ++a) {
            gres[a] = h->res[a];
            gmin[a] = h->ms_min[a];
            gmax[a] = h->ms_max[a];
        }
        C = h->channels;
        int N = h->res[0] * h->res[1] * h->res[2];
        /* the network runs at the active points only (n queries, in ascending lattice order:
         * the Python host's order); the others get F_ms = 0 */
        int n = h->n_active, nq = n > 0 ? n : 1;   /* nq: buffers are never empty */
        double cphase[7];
        mf_doubles(m, "medium.config_phase", cphase, 7);
        /* lattice: voxel centres over the box, [z][y][x], omega toward the camera */
        float *pts = xmalloc(sizeof(float) * 3 * (size_t)nq);
        float *oms = xmalloc(sizeof(float) * 3 * (size_t)nq);
        float *cfg = xmalloc(sizeof(float) * 9 * (size_t)nq);
        int *order = xmalloc(sizeof(int) * (size_t)nq);
        uint32_t *key = xmalloc(sizeof(uint32_t) * (size_t)nq);
        int cells = 1 << h->sort_bits;
        long nkeys = 1L << (3 * h->sort_bits);
        int *count = calloc((size_t)nkeys + 1, sizeof(int));
        if (!count) fail("out of host memory");
        for (int q = 0; q < n; ++q) {
            int i = h->active[q];
            int idx[3] = {i % h->res[0], (i / h->res[0]) % h->res[1],
                          i / (h->res[0] * h->res[1])};
            double p[3], w[3], norm = 0.0;
            for (int a = 0; a < 3; ++a) {
                p[a] = h->ms_min[a] + ((double)idx[a] + 0.5) * (h->ms_max[a] - h->ms_min[a]) / h->res[a];
                w[a] = origin[a] - p[a];
                norm += w[a] * w[a];
            }
            norm = fmax(sqrt(norm), 1e-30);
            double mu = 0.0;
            uint32_t kk = 0;
            for (int a = 0; a < 3; ++a) {
                pts[3 * q + a] = (float)p[a];
                oms[3 * q + a] = (float)(w[a] / norm);
                mu -= (double)oms[3 * q + a] * l[a];
                double gcell = (p[a] - h->cube_min[a]) * (cells / h->cube_size);
                uint32_t c = (uint32_t)clampd(gcell, 0.0, cells - 1);
                kk |= spread_bits(c, h->sort_bits) << a;
            }
            key[q] = kk;
            count[kk + 1]++;
            for (int f = 0; f < 7; ++f) cfg[9 * q + f] = (float)cphase[f];
            cfg[9 * q + 7] = (float)alb[0];
            cfg[9 * q + 8] = (float)acos(clampd(mu, -1.0, 1.0));
        }
        /* queries in Morton order of their coarse cell (stable counting sort): only speed */
        for (long i = 0; i < nkeys; ++i) count[i + 1] += count[i];
        for (int i = 0; i < n; ++i) order[count[key[i]]++] = i;
        free(count);
        free(key);
        if (!h->d_points) {   /* made once, rewritten every frame */
            h->d_points = buffer(h, sizeof(float) * 3 * (size_t)nq, NULL);
            h->d_omegas = buffer(h, sizeof(float) * 3 * (size_t)nq, NULL);
            h->d_order = buffer(h, sizeof(int) * (size_t)nq, NULL);
            h->d_config = buffer(h, sizeof(float) * 9 * (size_t)nq, NULL);
            h->d_feats = buffer(h, sizeof(float) * 3 * (size_t)h->np_ * nq, NULL);
            h->d_tenter = buffer(h, sizeof(float) * (size_t)nq, NULL);
            h->d_fms = buffer(h, sizeof(float) * (size_t)C * nq, NULL);
            h->d_planes = buffer(h, sizeof(float) * (size_t)C * N, NULL);
        }
        float *fms = xmalloc(sizeof(float) * (size_t)C * nq);
        float *pl = calloc((size_t)C * N, sizeof(float));
        if (!pl) fail("out of host memory");
        if (n > 0) {
            CL(clEnqueueWriteBuffer(h->queue, h->d_points, CL_FALSE, 0, 12 * (size_t)n, pts, 0, NULL, NULL));
            CL(clEnqueueWriteBuffer(h->queue, h->d_omegas, CL_FALSE, 0, 12 * (size_t)n, oms, 0, NULL, NULL));
            CL(clEnqueueWriteBuffer(h->queue, h->d_order, CL_FALSE, 0, 4 * (size_t)n, order, 0, NULL, NULL));
            CL(clEnqueueWriteBuffer(h->queue, h->d_config, CL_FALSE, 0, 36 * (size_t)n, cfg, 0, NULL, NULL));
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
            /* MLP: 16 queries per work-item; groups of one work-item on a CPU (private arrays
             * of ~105 KB each overflow PoCL's stack in bigger groups) */
            cl_float4 ca = {{0, 0, 0, 0}};
            if (C == 3)
                for (int c = 0; c < 3; ++c) ca.s[c] = (float)alb[c];
            set_args(h->k_mlp, "mmm4im", h->d_feats, h->d_config, h->d_params, &ca, n, h->d_fms);
            size_t items = (size_t)(n + h->mlp_qpi - 1) / (size_t)h->mlp_qpi;
            if (h->is_cpu)
                launch(h, h->k_mlp, items, 1);
            else
                launch(h, h->k_mlp, padded(items, (size_t)h->pad), 0);
            /* F_ms: clamp at 0, refuse non-finite, planes [C][gz][gy][gx] */
            CL(clEnqueueReadBuffer(h->queue, h->d_fms, CL_TRUE, 0, sizeof(float) * (size_t)C * n, fms,
                                   0, NULL, NULL));
        }
        for (int q = 0; q < n; ++q)
            for (int c = 0; c < C; ++c) {
                float v = fms[(size_t)q * C + c];
                int i = h->active[q];
                if (!isfinite(v)) fail("the network produced a non-finite F_ms at lattice point %d", i);
                pl[(size_t)c * N + i] = v > 0.0f ? v : 0.0f;
            }
        CL(clEnqueueWriteBuffer(h->queue, h->d_planes, CL_TRUE, 0, sizeof(float) * (size_t)C * N, pl,
                                0, NULL, NULL));
        planes = h->d_planes;
        free(fms);
        free(pl);
        free(pts);
        free(oms);
        free(cfg);
        free(order);
    }
    /* ray march */
    int W = h->width, H = h->height;
    if (!h->d_out[0]) {
        int ch[6] = {3, 3, 3, 1, 1, 0};
        for (int i = 0; i < 5; ++i) h->d_out[i] = buffer(h, 4 * (size_t)W * H * ch[i], NULL);
        h->d_out[5] = buffer(h, 4, NULL);   /* stats: unused without RAYMARCH_STATS */
    }
    cl_float4 bmin = f4(h->bmin), bmax = f4(h->bmax), cmin4 = f4(h->cube_min), gmin4 = f4(gmin),
              gmax4 = f4(gmax), o4 = f4(origin), fw4 = f4(fwd), r4 = f4(right), u4 = f4(up),
              l4 = f4(l), e4 = f4(irr), a4 = f4(alb), bg4 = f4(bg), rg, rw;
    mf_float4(m, "raymarch.lobe_g", 4, &rg);
    mf_float4(m, "raymarch.lobe_w", 4, &rw);
    int ln = h->lit ? h->light_res : 1;
    set_args(h->k_raymarch, "miii44fmiiiimi4fmiii444444fii444444fffffmmmmmm",
             h->d_density, h->nx, h->ny, h->nz, &bmin, &bmax, h->density_scale,
             h->d_majorant, h->mx, h->my, h->mz, h->block,
             h->lit ? h->d_light : h->d_dummy, ln, &cmin4, h->lit ? h->cube_size : 1.0,
             planes, gres[0], gres[1], gres[2], &gmin4, &gmax4,
             &o4, &fw4, &r4, &u4, h->tan_half, W, H,
             &l4, &e4, &a4, &rg, &rw, &bg4, abc[0], abc[1], abc[2],
             mf_double(m, "raymarch.step"), mf_double(m, "raymarch.threshold"),
             h->d_out[0], h->d_out[1], h->d_out[2], h->d_out[3], h->d_out[4], h->d_out[5]);
    size_t tiles = (size_t)((W + h->tile - 1) / h->tile) * (size_t)((H + h->tile - 1) / h->tile);
    launch(h, h->k_raymarch, padded(tiles, (size_t)h->rm_local), (size_t)h->rm_local);
    CL(clEnqueueReadBuffer(h->queue, h->d_out[0], CL_TRUE, 0, 12 * (size_t)W * H, rgb, 0, NULL, NULL));
}

/* ------------------------------------------------------------------------ public API */

/* Open a bundle on an existing context and queue (both non-NULL: the caller keeps ownership;
 * the queue must be in-order and belong to the context), or on a new one (both NULL; `device`
 * picks it: "gpu", "cpu", "P:D" or NULL for the first GPU, else the first CPU). */
clvol_host *clvol_host_create(const char *bundle_dir, cl_context context, cl_command_queue queue,
                              const char *device) {
    clvol_host *h = calloc(1, sizeof *h);
    if (!h) fail("out of host memory");
    h->dir = strdup(bundle_dir);
    char *mpath = path_join(bundle_dir, "manifest.txt");
    manifest_read(&h->mf, mpath);
    free(mpath);
    if (strcmp(mf_str(&h->mf, "format"), "clvol-bundle") != 0 || mf_int(&h->mf, "format_version") != 1)
        fail("%s: not a clvol-bundle of format_version 1", h->mf.where);
    read_host_constants(h);
    if ((context == NULL) != (queue == NULL)) fail("pass both a context and a queue, or neither");
    if (context) {
        h->ctx = context;
        h->queue = queue;
        CL(clGetCommandQueueInfo(queue, CL_QUEUE_DEVICE, sizeof h->device, &h->device, NULL));
    } else {
        open_device(h, device);
    }
    describe_device(h);
    setup_volume(h);
    double v[4][3], l[3];
    const char *cam[4] = {"camera.origin", "camera.forward", "camera.right", "camera.up"};
    for (int i = 0; i < 4; ++i) mf_doubles(&h->mf, cam[i], v[i], 3);
    clvol_host_set_camera(h, v[0], v[1], v[2], v[3], mf_double(&h->mf, "camera.tan_half"));
    mf_doubles(&h->mf, "light.direction", l, 3);
    clvol_host_set_light(h, l);
    return h;
}

void clvol_host_destroy(clvol_host *h) {
    if (!h) return;
    if (h->queue) CL(clFinish(h->queue));
    for (int i = 0; i < h->n_mems; ++i) CL(clReleaseMemObject(h->mems[i]));
    cl_kernel ks[] = {h->k_mip, h->k_majorant, h->k_layout, h->k_sweep1, h->k_sweep16, h->k_xpass,
                      h->k_rows, h->k_small, h->k_gather, h->k_mlp, h->k_raymarch};
    for (size_t i = 0; i < sizeof ks / sizeof ks[0]; ++i)
        if (ks[i]) CL(clReleaseKernel(ks[i]));
    for (int p = 0; p < N_PROGRAMS; ++p)
        if (h->prog[p]) CL(clReleaseProgram(h->prog[p]));
    if (h->owns_context) {
        CL(clReleaseCommandQueue(h->queue));
        CL(clReleaseContext(h->ctx));
    }
    manifest_free(&h->mf);
    free(h->density);
    free(h->active);
    free(h->dir);
    free(h);
}

/* ------------------------------------------------------------------------- goldens */

/* A .npy of float32 or int32 (little-endian, C order): returns the data, shape in dims. */
static void *read_npy(const char *dir, const char *name, int *ndim, long dims[4], char *kind) {
    char *path = path_join(dir, name);
    size_t n;
    char *buf = read_file(path, &n);
    if (n < 10 || memcmp(buf, "\x93NUMPY", 6) != 0) fail("%s: not a .npy file", path);
    int major = (unsigned char)buf[6];
    size_t hlen = major == 1 ? (size_t)((unsigned char)buf[8] | ((unsigned char)buf[9] << 8))
                             : (size_t)((unsigned char)buf[8] | ((unsigned char)buf[9] << 8)
                                        | ((unsigned char)buf[10] << 16) | ((unsigned char)buf[11] << 24));
    size_t start = (major == 1 ? 10 : 12) + hlen;
    char *hdr = xmalloc(hlen + 1);
    memcpy(hdr, buf + (major == 1 ? 10 : 12), hlen);
    hdr[hlen] = 0;
    if (strstr(hdr, "'<f4'")) *kind = 'f';
    else if (strstr(hdr, "'<i4'")) *kind = 'i';
    else fail("%s: only <f4 and <i4 arrays are read here (%s)", path, hdr);
    if (strstr(hdr, "'fortran_order': True")) fail("%s: Fortran order", path);
    char *s = strstr(hdr, "'shape': (");
    if (!s) fail("%s: no shape", path);
    s += 10;
    *ndim = 0;
    long total = 1;
    while (*s && *s != ')') {
        char *end;
        long v = strtol(s, &end, 10);
        if (end == s) break;
        if (*ndim == 4) fail("%s: more than 4 dimensions", path);
        dims[(*ndim)++] = v;
        total *= v;
        s = end;
        while (*s == ',' || *s == ' ') ++s;
    }
    if (n - start != 4 * (size_t)total) fail("%s: %zu data bytes for %ld values", path, n - start, total);
    void *data = xmalloc(4 * (size_t)total);
    memcpy(data, buf + start, 4 * (size_t)total);
    free(hdr);
    free(buf);
    free(path);
    return data;
}

static void *npy(const char *dir, const char *name, long *count) {
    int nd;
    long dims[4];
    char kind;
    void *d = read_npy(dir, name, &nd, dims, &kind);
    long t = 1;
    for (int i = 0; i < nd; ++i) t *= dims[i];
    *count = t;
    return d;
}

/* max |got - want| over the elements where |got - want| > atol + rtol |want| (0 = all pass). */
static int compare(const char *what, const float *got, const float *want, long n, long stride,
                   long first, long len, double atol, double rtol) {
    int bad = 0;
    double worst = 0.0, share = 0.0, biggest = 0.0;
    for (long i = 0; i < n; ++i)
        for (long j = first; j < first + len; ++j) {
            double g = got[i * stride + j], w = want[i * stride + j], e = fabs(g - w);
            double tol = atol + rtol * fabs(w);
            if (!(e <= tol)) ++bad;
            if (!(e <= worst)) worst = e;
            if (!(fabs(w) <= biggest)) biggest = fabs(w);
            /* the error as a share of its own tolerance: <= 1 passes, whatever the scale */
            double s = tol > 0.0 ? e / tol : (e > 0.0 ? INFINITY : 0.0);
            if (!(s <= share)) share = s;
        }
    printf("golden %-28s %s  worst error %.3g of its tolerance (max |error| %.3g, values up to "
           "%.3g; atol %.3g, rtol %.3g)\n", what, bad ? "FAIL" : "ok", share, worst, biggest,
           atol, rtol);
    return bad;
}

/* compare() with the manifest's tolerance.<key> = rtol, atol; atol in units of `scale`. */
static int compare_tol(const clvol_host *h, const char *what, const char *key, const float *got,
                       const float *want, long n, long stride, long first, long len, double scale) {
    char k[64];
    double tol[2];
    snprintf(k, sizeof k, "tolerance.%s", key);
    mf_doubles(&h->mf, k, tol, 2);
    return compare(what, got, want, n, stride, first, len, tol[1] * scale, tol[0]);
}

/* The golden folder's NAME (float32 or int32) as a device buffer released with the host;
 * *count: its number of elements. */
static cl_mem npy_buffer(clvol_host *h, const char *name, long *count) {
    void *data = npy(h->dir, name, count);
    cl_mem m = buffer(h, 4 * (size_t)*count, data);
    free(data);
    return m;
}

/* One kernel's golden folder ROOT/<name>: its manifest read into h->mf, h->dir set. */
static char *golden_open(clvol_host *h, const char *root, const char *name) {
    char *mp;
    h->dir = path_join(root, name);
    mp = path_join(h->dir, "manifest.txt");
    manifest_read(&h->mf, mp);
    free(mp);
    return h->dir;
}

static void golden_close(clvol_host *h) {
    manifest_free(&h->mf);
    free(h->dir);
    h->dir = NULL;
}

/* Golden vectors of `clvol goldens DIR` for the MLP and the gather (DIR/<kernel>/manifest.txt
 * lists the programs and tolerances, the .npy files the arguments). */
static int run_goldens(const char *root, const char *device) {
    int failures = 0;
    clvol_host *h = calloc(1, sizeof *h);
    if (!h) fail("out of host memory");
    open_device(h, device);
    describe_device(h);

    /* MLP: grey (1 channel, y) and chromatic (3 channels, decoded F) */
    {
        char *dir = golden_open(h, root, "mlp");
        long n, ny, nF, na;
        float *want_y = npy(dir, "y.npy", &ny);
        float *want_F = npy(dir, "F.npy", &nF);
        float *alb = npy(dir, "channel_albedo.npy", &na);
        int N = (int)ny, qpi = mf_int(&h->mf, "host.mlp_queries_per_item");
        cl_mem df = npy_buffer(h, "features.npy", &n), dc = npy_buffer(h, "config.npy", &n),
               dp = npy_buffer(h, "params.npy", &n), dy = buffer(h, 4 * (size_t)N, NULL),
               dF = buffer(h, 12 * (size_t)N, NULL);
        const char *names[2] = {"mlp_y", "mlp_F"};
        for (int v = 0; v < 2; ++v) {
            /* build each variant as its own program (program.mlp_y / program.mlp_F) */
            build_program(h, P_MLP, names[v]);
            cl_kernel k = kernel(h, P_MLP, "mlp_forward");
            cl_float4 ca = {{0, 0, 0, 0}};
            if (v == 1)
                for (int c = 0; c < 3 && c < na; ++c) ca.s[c] = alb[c];
            set_args(k, "mmm4im", df, dc, dp, &ca, N, v ? dF : dy);
            size_t items = (size_t)(N + qpi - 1) / (size_t)qpi;
            if (h->is_cpu) launch(h, k, items, 1);
            else launch(h, k, padded(items, 64), 0);
            float *got = xmalloc(12 * (size_t)N);
            CL(clEnqueueReadBuffer(h->queue, v ? dF : dy, CL_TRUE, 0, (v ? 12 : 4) * (size_t)N, got,
                                   0, NULL, NULL));
            double want_max = 0.0;
            const float *want = v ? want_F : want_y;
            for (long i = 0; i < (v ? 3L : 1L) * N; ++i) want_max = fmax(want_max, fabs(want[i]));
            /* atol as a fraction of max |want| */
            failures += compare_tol(h, names[v], names[v], got, want, N, v ? 3 : 1, 0, v ? 3 : 1,
                                    want_max);
            free(got);
            CL(clReleaseKernel(k));
            CL(clReleaseProgram(h->prog[P_MLP]));
            h->prog[P_MLP] = NULL;
        }
        free(want_y); free(want_F); free(alb);
        golden_close(h);
    }
    /* gather, render mode */
    {
        char *dir = golden_open(h, root, "gather");
        long n, n_loff, n_order, n_want, n_te;
        float *want = npy(dir, "features.npy", &n_want);
        float *want_te = npy(dir, "t_enter.npy", &n_te);
        cl_mem dd = npy_buffer(h, "dens.npy", &n), db = npy_buffer(h, "baked.npy", &n),
               dl = npy_buffer(h, "loff.npy", &n_loff), dt = npy_buffer(h, "tpl.npy", &n),
               dpi = npy_buffer(h, "pinfo.npy", &n), dh = npy_buffer(h, "hl_spacing.npy", &n),
               dpt = npy_buffer(h, "ptab.npy", &n), dp = npy_buffer(h, "points.npy", &n),
               dom = npy_buffer(h, "omegas.npy", &n), dor = npy_buffer(h, "order.npy", &n_order);
        build_program(h, P_GATHER, "gather");
        cl_kernel k = kernel(h, P_GATHER, "gather");
        int N = (int)n_order, L = (int)n_loff, NP = mf_int(&h->mf, "gather.np");
        double cmin[3], l[3];
        mf_doubles(&h->mf, "arg.cmin", cmin, 3);
        mf_doubles(&h->mf, "arg.light", l, 3);
        cl_float4 c4 = f4(cmin), l4 = f4(l), lg, lw;
        mf_float4(&h->mf, "arg.lobe_g", 4, &lg);
        mf_float4(&h->mf, "arg.lobe_w", 4, &lw);
        cl_mem dout = buffer(h, 4 * (size_t)N * 3 * NP, NULL), dte = buffer(h, 4 * (size_t)N, NULL),
               dummy = buffer(h, 4, NULL);
        set_args(k, "mmmmii4fmmmmmimm444fmimmm", dd, dd, db, dl, L, mf_int(&h->mf, "arg.n0"), &c4,
                 mf_double(&h->mf, "arg.csize"), dummy, dt, dpi, dh, dpt, mf_int(&h->mf, "arg.NA"),
                 dp, dom, &l4, &lg, &lw, mf_double(&h->mf, "arg.c_out"), dor, N, dout, dummy, dte);
        launch(h, k, padded((size_t)N, 64), 0);
        float *got = xmalloc(4 * (size_t)N * 3 * NP), *got_te = xmalloc(4 * (size_t)N);
        CL(clEnqueueReadBuffer(h->queue, dout, CL_TRUE, 0, 4 * (size_t)N * 3 * NP, got, 0, NULL, NULL));
        CL(clEnqueueReadBuffer(h->queue, dte, CL_TRUE, 0, 4 * (size_t)N, got_te, 0, NULL, NULL));
        failures += compare_tol(h, "gather t_enter", "t_enter", got_te, want_te, N, 1, 0, 1, 1.0);
        failures += compare_tol(h, "gather density", "density", got, want, N, 3 * NP, 0, NP, 1.0);
        failures += compare_tol(h, "gather transmittance", "transmittance", got, want, N, 3 * NP,
                                NP, NP, 1.0);
        failures += compare_tol(h, "gather phase", "phase", got, want, N, 3 * NP, 2 * NP, NP, 1.0);
        free(got); free(got_te); free(want); free(want_te);
        CL(clReleaseKernel(k));
        golden_close(h);
    }
    clvol_host_destroy(h);
    return failures;
}

/* ---------------------------------------------------------------------------- main */

static void write_pfm(const char *path, const float *rgb, int w, int h) {
    FILE *f = fopen(path, "wb");
    if (!f) fail("%s: cannot write (%s)", path, strerror(errno));
    fprintf(f, "PF\n%d %d\n-1.0\n", w, h);   /* -1: little-endian; rows bottom to top */
    for (int y = h - 1; y >= 0; --y)
        if (fwrite(rgb + (size_t)y * w * 3, sizeof(float), (size_t)w * 3, f) != (size_t)w * 3)
            fail("%s: short write", path);
    if (fclose(f) != 0) fail("%s: cannot close (%s)", path, strerror(errno));
}

static int cmp_double(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

int main(int argc, char **argv) {
    const char *device = NULL, *golden = NULL, *paths[2] = {NULL, NULL};
    int frames = 1, np = 0, external = 0;
    for (int i = 1; i < argc; ++i) {
        if (strcmp(argv[i], "--frames") == 0 && i + 1 < argc) {
            char *end;
            long v = strtol(argv[++i], &end, 10);
            if (*end || v < 1 || v > 1000) fail("--frames %s: an integer from 1 to 1000", argv[i]);
            frames = (int)v;
        } else if (strcmp(argv[i], "--device") == 0 && i + 1 < argc) {
            device = argv[++i];
        } else if (strcmp(argv[i], "--external-context") == 0) {
            external = 1;   /* exercise the embedding path: a context and queue made here */
        } else if (strcmp(argv[i], "--golden") == 0 && i + 1 < argc) {
            golden = argv[++i];
        } else if (argv[i][0] == '-' || np == 2) {
            fprintf(stderr, "usage: clvol-render BUNDLE OUT.pfm [--frames N] [--device gpu|cpu|P:D] [--external-context]\n"
                            "       clvol-render --golden GOLDEN_DIR [--device ...]\n");
            return 2;
        } else {
            paths[np++] = argv[i];
        }
    }
    if (golden) {
        int bad = run_goldens(golden, device);
        printf("goldens: %s\n", bad ? "FAILED" : "all within tolerance");
        return bad ? 1 : 0;
    }
    if (np != 2) {
        fprintf(stderr, "usage: clvol-render BUNDLE OUT.pfm [--frames N] [--device gpu|cpu|P:D]\n");
        return 2;
    }
    double t0 = now_seconds();
    cl_context ctx = NULL;
    cl_command_queue queue = NULL;
    if (external) {   /* what a renderer that already holds OpenCL objects does */
        clvol_host probe = {0};
        open_device(&probe, device);
        ctx = probe.ctx;
        queue = probe.queue;
    }
    clvol_host *h = clvol_host_create(paths[0], ctx, queue, device);
    float *rgb = xmalloc(12 * (size_t)h->width * h->height);
    double *ft = xmalloc(sizeof(double) * (size_t)frames);
    for (int f = 0; f < frames; ++f) {
        double s = now_seconds();
        clvol_host_render(h, rgb);
        ft[f] = now_seconds() - s;
    }
    double total = now_seconds() - t0;
    write_pfm(paths[1], rgb, h->width, h->height);
    qsort(ft, (size_t)frames, sizeof(double), cmp_double);
    fprintf(stderr, "clvol-render: %dx%d, setup (build + volume) %.3f s, light %.3f s, "
                    "frame median %.4f s over %d, total %.3f s (of the setup: build %.3f s)\n",
            h->width, h->height, h->t_volume, h->t_light, ft[frames / 2], frames, total,
            h->t_build);
    free(ft);
    free(rgb);
    clvol_host_destroy(h);
    if (external) {   /* the caller's objects outlive the host */
        CL(clReleaseCommandQueue(queue));
        CL(clReleaseContext(ctx));
    }
    return 0;
}
