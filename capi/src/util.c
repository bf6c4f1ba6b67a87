/* libclvol: errors, host memory, files, the bundle manifest, OpenCL helpers and program
 * builds (the parts of the host that know nothing of rendering). See internal.h for how
 * errors travel. */
#define _POSIX_C_SOURCE 200809L
#include "internal.h"

#include <ctype.h>
#include <errno.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

/* ------------------------------------------------------------------------- errors */

_Thread_local guard *clvol_guard;
_Thread_local char thread_error[1024];

void guard_init(guard *g, char *msg, size_t msg_size) {
    memset(g, 0, sizeof *g);
    g->msg = msg;
    g->msg_size = msg_size;
    if (msg_size) msg[0] = 0;
    g->status = CLVOL_OK;
    g->outer = clvol_guard;
    clvol_guard = g;
}

clvol_status guard_end(guard *g) {
    for (int i = 0; i < g->n_scratch; ++i) free(g->scratch[i]);
    free(g->scratch);
    g->scratch = NULL;
    g->n_scratch = g->cap_scratch = 0;
    clvol_guard = g->outer;
    return g->status;
}

void fail(clvol_status status, const char *fmt, ...) {
    guard *g = clvol_guard;
    if (g->msg_size) {
        va_list ap;
        va_start(ap, fmt);
        vsnprintf(g->msg, g->msg_size, fmt, ap);
        va_end(ap);
        /* one line: a build log or a path may hold newlines */
        for (char *c = g->msg; *c; ++c)
            if (*c == '\n' || *c == '\r') *c = ' ';
    }
    g->status = status;
    longjmp(g->jump, 1);
}

const char *cl_error_name(cl_int e) {
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


void cl_check(cl_int err, const char *call, const char *file, int line) {
    if (err != CL_SUCCESS)
        fail(CLVOL_ERROR_OPENCL, "OpenCL call %s failed with %s (%d) at %s:%d", call,
             cl_error_name(err), (int)err, strrchr(file, '/') ? strrchr(file, '/') + 1 : file,
             line);
}

/* Record p in the current call's scratch list (freed at the call's end unless kept). */
static void *scratch_add(void *p) {
    guard *g = clvol_guard;
    if (g->n_scratch == g->cap_scratch) {
        int cap = g->cap_scratch ? 2 * g->cap_scratch : 32;
        void **s = realloc(g->scratch, sizeof(void *) * (size_t)cap);
        if (!s) {
            free(p);
            fail(CLVOL_ERROR_MEMORY, "out of host memory");
        }
        g->scratch = s;
        g->cap_scratch = cap;
    }
    g->scratch[g->n_scratch++] = p;
    return p;
}

void *xmalloc(size_t n) {
    void *p = malloc(n ? n : 1);
    if (!p) fail(CLVOL_ERROR_MEMORY, "out of host memory (%zu bytes)", n);
    return scratch_add(p);
}

void *xcalloc(size_t n, size_t size) {
    void *p = calloc(n ? n : 1, size ? size : 1);
    if (!p) fail(CLVOL_ERROR_MEMORY, "out of host memory (%zu x %zu bytes)", n, size);
    return scratch_add(p);
}

/* Take p off the scratch list (searched from the newest: scratch lives briefly). */
static int scratch_remove(void *p) {
    guard *g = clvol_guard;
    for (int i = g->n_scratch - 1; i >= 0; --i)
        if (g->scratch[i] == p) {
            g->scratch[i] = g->scratch[--g->n_scratch];
            return 1;
        }
    return 0;
}

void xfree(void *p) {
    if (!p) return;
    scratch_remove(p);
    free(p);
}

void *keep(void *p) {
    scratch_remove(p);
    return p;
}

char *xstrdup(const char *s) {
    char *d = strdup(s);
    if (!d) fail(CLVOL_ERROR_MEMORY, "out of host memory");
    return d;
}

double now_seconds(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* ---------------------------------------------------------------------------- files */

char *path_join(const char *dir, const char *name) {
    size_t n = strlen(dir) + strlen(name) + 2;
    char *p = xmalloc(n);
    snprintf(p, n, "%s/%s", dir, name);
    return p;
}

char *read_file(const char *path, size_t *size) {
    FILE *f = fopen(path, "rb");
    if (!f) fail(BUNDLE, "%s: cannot open (%s)", path, strerror(errno));
    long n = -1;
    if (fseek(f, 0, SEEK_END) == 0) n = ftell(f);
    if (n < 0) {
        fclose(f);
        fail(BUNDLE, "%s: cannot size", path);
    }
    rewind(f);
    char *buf = malloc((size_t)n + 1);
    if (!buf) {
        fclose(f);
        fail(CLVOL_ERROR_MEMORY, "out of host memory (%ld bytes for %s)", n, path);
    }
    size_t got = n ? fread(buf, 1, (size_t)n, f) : 0;
    fclose(f);
    scratch_add(buf);
    if (got != (size_t)n) fail(BUNDLE, "%s: short read", path);
    buf[n] = 0;
    if (size) *size = (size_t)n;
    return buf;
}

/* A raw little-endian 4-byte array of exactly `count` elements (this host is little-endian). */
void *read_raw4(const char *dir, const char *name, size_t count) {
    char *path = path_join(dir, name);
    size_t n;
    char *buf = read_file(path, &n);
    if (n != 4 * count) fail(BUNDLE, "%s: %zu bytes, expected %zu (%zu values)", path, n, 4 * count, count);
    xfree(path);
    return buf;
}

/* ------------------------------------------------------------------------- manifest */

static char *trim(char *s) {
    while (isspace((unsigned char)*s)) ++s;
    char *e = s + strlen(s);
    while (e > s && isspace((unsigned char)e[-1])) *--e = 0;
    return s;
}

void manifest_read(manifest *m, const char *path) {
    char *text = read_file(path, NULL);
    m->n = m->cap = 0;
    m->key = m->val = NULL;
    m->where = xstrdup(path);   /* owned by the manifest: manifest_free frees it all */
    char *save = NULL;
    for (char *line = strtok_r(text, "\n", &save); line; line = strtok_r(NULL, "\n", &save)) {
        char *hash = strchr(line, '#');
        if (hash) *hash = 0;
        char *eq = strchr(line, '=');
        if (!eq) {
            if (*trim(line)) fail(BUNDLE, "%s: line without '=': %s", path, line);
            continue;
        }
        *eq = 0;
        if (m->n == m->cap) {
            int cap = m->cap ? 2 * m->cap : 64;
            char **k = realloc(m->key, (size_t)cap * sizeof(char *)), **v;
            if (!k) fail(CLVOL_ERROR_MEMORY, "out of host memory");
            m->key = k;
            v = realloc(m->val, (size_t)cap * sizeof(char *));
            if (!v) fail(CLVOL_ERROR_MEMORY, "out of host memory");
            m->val = v;
            m->cap = cap;
        }
        /* both or neither, so manifest_free sees whole entries */
        char *key = strdup(trim(line)), *val = strdup(trim(eq + 1));
        if (!key || !val) {
            free(key);
            free(val);
            fail(CLVOL_ERROR_MEMORY, "out of host memory");
        }
        m->key[m->n] = key;
        m->val[m->n] = val;
        m->n++;
    }
    xfree(text);
}

void manifest_free(manifest *m) {
    for (int i = 0; i < m->n; ++i) {
        free(m->key[i]);
        free(m->val[i]);
    }
    free(m->key);
    free(m->val);
    free(m->where);
    m->n = m->cap = 0;   /* empty again: freeing twice is harmless */
    m->key = m->val = NULL;
    m->where = NULL;
}

const char *mf_find(const manifest *m, const char *key) {
    for (int i = 0; i < m->n; ++i)
        if (strcmp(m->key[i], key) == 0) return m->val[i];
    return NULL;
}

const char *mf_str(const manifest *m, const char *key) {
    const char *v = mf_find(m, key);
    if (!v) fail(BUNDLE, "%s: missing key %s", m->where, key);
    return v;
}

/* Exactly n numbers. */
void mf_doubles(const manifest *m, const char *key, double *out, int n) {
    const char *s = mf_str(m, key);
    for (int i = 0; i < n; ++i) {
        char *end;
        errno = 0;
        out[i] = strtod(s, &end);
        if (end == s || errno) fail(BUNDLE, "%s: %s = %s: expected %d numbers", m->where, key, mf_str(m, key), n);
        s = end;
    }
    while (isspace((unsigned char)*s)) ++s;
    if (*s) fail(BUNDLE, "%s: %s: expected %d numbers, found more", m->where, key, n);
}

double mf_double(const manifest *m, const char *key) {
    double v;
    mf_doubles(m, key, &v, 1);
    return v;
}

void mf_ints(const manifest *m, const char *key, int *out, int n) {
    double d[8];
    if (n > 8) fail(CLVOL_ERROR_OPENCL, "internal: mf_ints n > 8");
    mf_doubles(m, key, d, n);
    for (int i = 0; i < n; ++i) {
        if (d[i] != floor(d[i]) || fabs(d[i]) > 2147483647.0)
            fail(BUNDLE, "%s: %s: %g is not an int", m->where, key, d[i]);
        out[i] = (int)d[i];
    }
}

int mf_int(const manifest *m, const char *key) {
    int v;
    mf_ints(m, key, &v, 1);
    return v;
}

/* Whether the space-separated list `key` holds `word`. */
int mf_has_word(const manifest *m, const char *key, const char *word) {
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

void mf_float4(const manifest *m, const char *key, int n, cl_float4 *out) {
    double d[4] = {0, 0, 0, 0};
    mf_doubles(m, key, d, n);
    for (int i = 0; i < 4; ++i) out->s[i] = (float)d[i];
}

/* mf_int within [lo, hi]: the host constants size buffers and divide work sizes, so a
 * corrupt one must stop here, not as a division by zero or a kernel reading out of bounds
 * (both found by fuzzing mutated bundles). */
int mf_int_in(const manifest *m, const char *key, int lo, int hi) {
    int v = mf_int(m, key);
    if (v < lo || v > hi) fail(BUNDLE, "%s: %s = %d: must be in [%d, %d]", m->where, key, v, lo, hi);
    return v;
}

/* ------------------------------------------------------------------- OpenCL helpers */

const char *const PROGRAM_NAMES[N_PROGRAMS] = {
    "pyramid", "majorant", "transmittance", "transmittance_w1", "transmittance_wL", "gather",
    "gather_bake", "mlp", "viewdepth", "raymarch", "pack_rgba"};

cl_mem track(clvol_host *h, cl_mem m) {
    if (h->n_mems == MAX_MEMS) {
        clReleaseMemObject(m);
        fail(CLVOL_ERROR_OPENCL, "internal: more than %d buffers", MAX_MEMS);
    }
    h->mems[h->n_mems++] = m;
    return m;
}

void release_tracked(clvol_host *h, cl_mem *m) {
    if (!*m) return;
    for (int i = 0; i < h->n_mems; ++i)
        if (h->mems[i] == *m) {
            h->mems[i] = h->mems[--h->n_mems];
            break;
        }
    CL(clReleaseMemObject(*m));
    *m = NULL;
}

cl_mem buffer(clvol_host *h, size_t bytes, const void *init) {
    cl_int err;
    if (bytes < 4) bytes = 4;    /* zero-size buffers are invalid */
    cl_mem m = clCreateBuffer(h->ctx, CL_MEM_READ_WRITE | (init ? CL_MEM_COPY_HOST_PTR : 0), bytes,
                              (void *)init, &err);
    CLE(err, "clCreateBuffer");
    return track(h, m);
}

cl_mem zeros(clvol_host *h, size_t bytes) {
    cl_mem m = buffer(h, bytes, NULL);
    const cl_float z = 0.0f;
    CL(clEnqueueFillBuffer(h->queue, m, &z, sizeof z, 0, bytes < 4 ? 4 : bytes, 0, NULL, NULL));
    return m;
}

size_t padded(size_t n, size_t multiple) {
    if (n < 1) n = 1;
    return (n + multiple - 1) / multiple * multiple;
}

void launch(clvol_host *h, cl_kernel k, size_t global, size_t local) {
    size_t g = global, l = local;
    CL(clEnqueueNDRangeKernel(h->queue, k, 1, NULL, &g, local ? &l : NULL, 0, NULL, NULL));
}

/* Set a kernel's arguments in order: 'm' cl_mem, 'i' int, 'f' float (passed as double),
 * '4' cl_float4 *, 'G' cl_float16 * (a block: cl/include/blocks.h's Block16 has its
 * size and layout). */
void set_args(cl_kernel k, const char *types, ...) {
    va_list ap;
    va_start(ap, types);
    cl_uint n_args = 0;
    CL(clGetKernelInfo(k, CL_KERNEL_NUM_ARGS, sizeof n_args, &n_args, NULL));
    char name[64] = "?";
    CL(clGetKernelInfo(k, CL_KERNEL_FUNCTION_NAME, sizeof name, name, NULL));
    if (strlen(types) != n_args) fail(BUNDLE, "kernel %s takes %u arguments, the host gives %zu", name, n_args, strlen(types));
    for (cl_uint i = 0; types[i]; ++i) {
        cl_int err = CL_SUCCESS;
        switch (types[i]) {
        case 'm': { cl_mem v = va_arg(ap, cl_mem); err = clSetKernelArg(k, i, sizeof v, &v); break; }
        case 'i': { cl_int v = va_arg(ap, int); err = clSetKernelArg(k, i, sizeof v, &v); break; }
        case 'f': { cl_float v = (cl_float)va_arg(ap, double); err = clSetKernelArg(k, i, sizeof v, &v); break; }
        case '4': { cl_float4 *v = va_arg(ap, cl_float4 *); err = clSetKernelArg(k, i, sizeof *v, v); break; }
        case 'G': { cl_float16 *v = va_arg(ap, cl_float16 *); err = clSetKernelArg(k, i, sizeof *v, v); break; }
        default: va_end(ap); fail(CLVOL_ERROR_OPENCL, "internal: bad argument type %c", types[i]);
        }
        if (err != CL_SUCCESS) {
            va_end(ap);
            fail(CLVOL_ERROR_OPENCL, "OpenCL call clSetKernelArg(%s, %u) failed with %s (%d)", name, i, cl_error_name(err), (int)err);
        }
    }
    va_end(ap);
}

cl_float4 f4(const double *v) {
    cl_float4 r = {{(float)v[0], (float)v[1], (float)v[2], 0.0f}};
    return r;
}

cl_kernel kernel(clvol_host *h, int prog, const char *name) {
    cl_int err;
    cl_kernel k = clCreateKernel(h->prog[prog], name, &err);
    if (err != CL_SUCCESS) fail(BUNDLE, "%s has no kernel %s (%s)", PROGRAM_NAMES[prog], name, cl_error_name(err));
    return k;
}


/* ------------------------------------------------------------------- device and build */

/* The device `spec` names ("gpu", "cpu", "P:D" = platform P's device D; NULL: the first GPU,
 * else the first CPU, a platform of DEFAULT_LAST's only where no other has one). */
static cl_device_id find_device(const char *spec) {
    cl_uint np = 0;
    cl_int err = clGetPlatformIDs(0, NULL, &np);
    if (err != CL_SUCCESS || np == 0)
        fail(CLVOL_ERROR_OPENCL, "no OpenCL platform found (install an ICD, e.g. pocl-opencl-icd)");
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
        char pname[256] = "";
        if (clGetPlatformInfo(plats[p], CL_PLATFORM_NAME, sizeof pname, pname, NULL) != CL_SUCCESS)
            pname[0] = 0;
        pname[sizeof pname - 1] = 0;
        const int last = clvol_default_last(pname);
        for (cl_uint d = 0; d < nd; ++d) {
            cl_device_type t;
            CL(clGetDeviceInfo(devs[d], CL_DEVICE_TYPE, sizeof t, &t, NULL));
            int rank = (t & CL_DEVICE_TYPE_GPU) ? 0 : (t & CL_DEVICE_TYPE_CPU) ? 2 : 4;
            rank += last;   /* after any other platform's device of the same type */
            if (spec) {   /* "gpu", "cpu" or "P:D" */
                char pd[32];
                snprintf(pd, sizeof pd, "%u:%u", p, d);
                int match = strcmp(spec, pd) == 0 || (strcmp(spec, "gpu") == 0 && rank / 2 == 0)
                            || (strcmp(spec, "cpu") == 0 && rank / 2 == 1);
                rank = match ? 0 : 99;
            }
            if (rank < best_rank) {
                best_rank = rank;
                best = devs[d];
            }
        }
    }
    if (!best || best_rank == 99)
        fail(spec ? CLVOL_ERROR_ARGUMENT : CLVOL_ERROR_OPENCL, "no OpenCL device matches %s "
             "(\"gpu\", \"cpu\" or platform:device such as 0:0)",
             spec ? spec : "(any)");
    return best;
}

clvol_status clvol_pick_device(const char *spec, cl_device_id *out) {
    guard g;
    guard_init(&g, thread_error, sizeof thread_error);   /* no renderer holds this message */
    if (setjmp(g.jump)) return guard_end(&g);
    if (!out) fail(CLVOL_ERROR_ARGUMENT, "clvol_pick_device: out is NULL");
    *out = find_device(spec);
    return guard_end(&g);
}

/* A new context and in-order queue on h->device (found first if NULL), owned by h. */
void open_device(clvol_host *h) {
    cl_int err;
    if (!h->device) h->device = find_device(NULL);
    h->ctx = clCreateContext(NULL, 1, &h->device, NULL, NULL, &err);
    CLE(err, "clCreateContext");
    h->owns_context = 1;
    h->queue = clCreateCommandQueue(h->ctx, h->device, 0, &err);
    CLE(err, "clCreateCommandQueue");
}



/* Driver workarounds, the rule of clvol/runtime.py DRIVER_RULES (tests/test_capi.py holds the
 * two to the same answers): on a platform whose name contains `match` (case-insensitive), the
 * -D options every program gets and the lane width (0: the device rule). The one place
 * libclvol decides them. Mesa's rusticl (22.3.6, llvmpipe; docs/opencl.md, "rusticl"):
 * MLP_DENSE_ARRAY, as the named-accumulator dense layers stall clCreateKernel in a recursive
 * NIR pass; MLP_MULADD, as fma() there is a software fma (presumably libclc's), inlined at
 * every call, which llvmpipe compiled for minutes at the network's first launch
 * (cl/include/mlp_core.h); and 4 lanes, as llvmpipe already runs work-items as SIMD lanes and
 * wider vectors only multiply the code it compiles (mlp_forward's first launch: 13-18 s at 4
 * lanes, over 230 s at 16). */
static const struct {
    const char *match, *defines;
    int lanes;
} DRIVER_RULES[] = {
    {"rusticl", "-DMLP_DENSE_ARRAY=1 -DMLP_MULADD=1", 4},
};
#define N_DRIVER_RULES (sizeof DRIVER_RULES / sizeof DRIVER_RULES[0])

static int contains_nocase(const char *s, const char *sub) {
    size_t n = strlen(sub);
    for (; *s; ++s) {
        size_t i = 0;
        while (i < n && s[i] && tolower((unsigned char)s[i]) == tolower((unsigned char)sub[i])) ++i;
        if (i == n) return 1;
    }
    return n == 0;
}

CLVOL_API const char *clvol_driver_defines(const char *platform_name) {
    for (size_t i = 0; platform_name && i < N_DRIVER_RULES; ++i)
        if (contains_nocase(platform_name, DRIVER_RULES[i].match)) return DRIVER_RULES[i].defines;
    return "";
}

/* clvol/runtime.py DEFAULT_LAST: platforms whose devices the default choice (find_device with
 * no spec) takes after any other device of the same type (Mesa's Clover; the comment there
 * says why). */
static const char *const DEFAULT_LAST[] = {"clover"};

CLVOL_API int clvol_default_last(const char *platform_name) {
    for (size_t i = 0; platform_name && i < sizeof DEFAULT_LAST / sizeof DEFAULT_LAST[0]; ++i)
        if (contains_nocase(platform_name, DEFAULT_LAST[i])) return 1;
    return 0;
}

CLVOL_API int clvol_driver_lanes(const char *platform_name) {
    for (size_t i = 0; platform_name && i < N_DRIVER_RULES; ++i)
        if (contains_nocase(platform_name, DRIVER_RULES[i].match) && DRIVER_RULES[i].lanes)
            return DRIVER_RULES[i].lanes;
    return 0;
}

void describe_device(clvol_host *h) {
    cl_platform_id plat;
    char name[256];
    cl_device_type t;
    CL(clGetDeviceInfo(h->device, CL_DEVICE_PLATFORM, sizeof plat, &plat, NULL));
    CL(clGetPlatformInfo(plat, CL_PLATFORM_NAME, sizeof name, name, NULL));
    name[sizeof name - 1] = 0;
    /* PoCL gets the Clang-only fast paths the Python host also enables there */
    h->is_pocl = strstr(name, "Portable Computing Language") != NULL;
    h->driver_opts = clvol_driver_defines(name);
    CL(clGetDeviceInfo(h->device, CL_DEVICE_TYPE, sizeof t, &t, NULL));
    h->is_cpu = (t & CL_DEVICE_TYPE_CPU) != 0;
    /* The lane width, as clvol/runtime.py device_lanes decides it: $CLVOL_LANES, else the
     * driver's rule (DRIVER_RULES), else a CPU's native float vector width (8: AVX, 4: SSE; a wider vector in a call changes its calling
     * convention), else 16 (docs/opencl.md, "Compiler warnings"). */
    cl_uint native = 0;
    if (clGetDeviceInfo(h->device, CL_DEVICE_NATIVE_VECTOR_WIDTH_FLOAT, sizeof native, &native,
                        NULL) != CL_SUCCESS)
        native = 0;
    h->lanes = (h->is_cpu && (native == 4 || native == 8)) ? (int)native : 16;
    if (clvol_driver_lanes(name)) h->lanes = clvol_driver_lanes(name);
    const char *forced = getenv("CLVOL_LANES");
    if (forced && *forced) {
        if (strcmp(forced, "16") && strcmp(forced, "8") && strcmp(forced, "4"))
            fail(CLVOL_ERROR_ARGUMENT, "CLVOL_LANES=%s: expected one of 16, 8, 4", forced);
        h->lanes = atoi(forced);
    }
}

/* Kernel sources with their quoted #includes pasted in from the include folder (each header
 * once; they have include guards too), so the build options hold no file paths: the same
 * program then hits the OpenCL driver's build cache from any bundle folder (PoCL keys its
 * cache on the source and the options), and the build does not depend on the working folder.
 * The text grows in a scratch buffer (sb_add), so a failure half-way frees it. */
typedef struct {
    char *s;
    size_t len, cap;
} strbuf;

static void sb_add(strbuf *b, const char *s, size_t n) {
    if (b->len + n + 1 > b->cap) {
        size_t cap = 2 * (b->len + n + 1);
        char *t = xmalloc(cap);
        if (b->s) memcpy(t, b->s, b->len);
        xfree(b->s);
        b->s = t;
        b->cap = cap;
    }
    memcpy(b->s + b->len, s, n);
    b->len += n;
    b->s[b->len] = 0;
}

#define MAX_HEADERS 32
typedef struct {
    char names[MAX_HEADERS][256];
    int n;
} header_set;

static void expand_source(const char *path, const char *label, const char *inc_dir, strbuf *out,
                          header_set *seen, int depth) {
    if (depth > 8) fail(BUNDLE, "%s: #include nesting deeper than 8", path);
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
            if (!close || close > p + n || close - name >= 256)
                fail(BUNDLE, "%s:%d: malformed #include", path, line_no);
            char hdr[256];
            snprintf(hdr, sizeof hdr, "%.*s", (int)(close - name), name);
            int done = 0;
            for (int i = 0; i < seen->n; ++i) done |= strcmp(seen->names[i], hdr) == 0;
            if (!done) {
                if (seen->n == MAX_HEADERS) fail(BUNDLE, "%s: more than %d headers", path, MAX_HEADERS);
                memcpy(seen->names[seen->n++], hdr, sizeof hdr);
                char *hp = path_join(inc_dir, hdr);
                expand_source(hp, hdr, inc_dir, out, seen, depth + 1);
                xfree(hp);
            }
            snprintf(line_dir, sizeof line_dir, "#line %d \"%s\"\n", line_no + 1, label);
            sb_add(out, line_dir, strlen(line_dir));
        } else {
            sb_add(out, p, n);
        }
        p += n;
    }
    sb_add(out, "\n", 1);
    xfree(text);
}

/* Build `source` with `options`; a build failure names `what` and quotes the log's start. */
cl_program build_source(clvol_host *h, const char *source, const char *options,
                        const char *what) {
    cl_int err;
    const char *srcs[1] = {source};
    cl_program p = clCreateProgramWithSource(h->ctx, 1, srcs, NULL, &err);
    CLE(err, "clCreateProgramWithSource");
    err = clBuildProgram(p, 1, &h->device, options, NULL, NULL);
    if (err != CL_SUCCESS) {
        char log[400] = "";
        size_t len = 0;
        clGetProgramBuildInfo(p, h->device, CL_PROGRAM_BUILD_LOG, sizeof log - 1, log, &len);
        log[sizeof log - 1] = 0;
        clReleaseProgram(p);
        fail(BUNDLE, "%s failed to build (%s) with options %s; build log: %s", what,
             cl_error_name(err), options, log);
    }
    return p;
}

cl_program build_program_at(clvol_host *h, const char *dir, const manifest *m,
                            const char *name) {
    char key[96];
    snprintf(key, sizeof key, "program.%s", name);
    const char *rel = mf_str(m, key);
    char *path = path_join(dir, rel);
    char *inc = path_join(dir, mf_str(m, "include_dir"));
    strbuf src = {NULL, 0, 0};
    header_set *seen = xcalloc(1, sizeof *seen);
    const char *label = strrchr(rel, '/') ? strrchr(rel, '/') + 1 : rel;
    expand_source(path, label, inc, &src, seen, 0);
    snprintf(key, sizeof key, "program.%s.options", name);
    const char *opts = mf_str(m, key);
    snprintf(key, sizeof key, "program.%s.options_pocl", name);
    const char *pocl = h->is_pocl ? mf_find(m, key) : NULL;
    const char *drv = h->driver_opts ? h->driver_opts : "";
    size_t n = strlen(opts) + (pocl ? strlen(pocl) : 0) + strlen(drv) + 32;
    char *options = xmalloc(n);
    snprintf(options, n, "%s -DLANES=%d %s %s", opts, h->lanes, pocl ? pocl : "", drv);
    cl_program p = build_source(h, src.s, options, path);
    xfree(options);
    xfree(seen);
    xfree(inc);
    xfree(src.s);
    xfree(path);
    return p;
}

/* Everything h holds, released; errors are ignored (this runs on failure paths too). */
void host_release(clvol_host *h) {
    if (!h) return;
    if (h->queue) clFinish(h->queue);
    for (int i = 0; i < h->n_mems; ++i) clReleaseMemObject(h->mems[i]);
    h->n_mems = 0;
    cl_kernel ks[] = {h->k_mip, h->k_majorant, h->k_layout, h->k_sweep1, h->k_sweepL, h->k_xpass,
                      h->k_rows, h->k_small, h->k_gather, h->k_mlp, h->k_raymarch, h->k_pack,
                      h->k_viewdepth};
    for (size_t i = 0; i < sizeof ks / sizeof ks[0]; ++i)
        if (ks[i]) clReleaseKernel(ks[i]);
    for (int p = 0; p < N_PROGRAMS; ++p)
        if (h->prog[p]) clReleaseProgram(h->prog[p]);
    if (h->owns_context) {
        if (h->queue) clReleaseCommandQueue(h->queue);
        if (h->ctx) clReleaseContext(h->ctx);
    }
    manifest_free(&h->mf);
    free(h->density);
    free(h->active);
    free(h->vs.sums);
    free(h->vs.count);
    free(h->vs.depth);
    free(h->dir);
    free(h);
}
