/* libclvol: the golden-vector check (``clvol goldens DIR``, docs/embedding.md) of the MLP and
 * the gather kernels, for ports and new devices. */
#define _POSIX_C_SOURCE 200809L
#include "internal.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

/* The report buffer of the running check (one line per output). */
static _Thread_local char *report_buf;
static _Thread_local size_t report_size, report_len;

static void report(const char *fmt, ...) CLVOL_PRINTF(1, 2);
static void report(const char *fmt, ...) {
    if (report_len + 1 >= report_size) return;
    va_list ap;
    va_start(ap, fmt);
    int n = vsnprintf(report_buf + report_len, report_size - report_len, fmt, ap);
    va_end(ap);
    if (n > 0) report_len += (size_t)n < report_size - report_len ? (size_t)n : report_size - report_len - 1;
}

/* A .npy of float32 or int32 (little-endian, C order): returns the data, shape in dims. */
static void *read_npy(const char *dir, const char *name, int *ndim, long dims[4], char *kind) {
    char *path = path_join(dir, name);
    size_t n;
    char *buf = read_file(path, &n);
    if (n < 10 || memcmp(buf, "\x93NUMPY", 6) != 0) fail(BUNDLE, "%s: not a .npy file", path);
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
    else fail(BUNDLE, "%s: only <f4 and <i4 arrays are read here (%s)", path, hdr);
    if (strstr(hdr, "'fortran_order': True")) fail(BUNDLE, "%s: Fortran order", path);
    char *s = strstr(hdr, "'shape': (");
    if (!s) fail(BUNDLE, "%s: no shape", path);
    s += 10;
    *ndim = 0;
    long total = 1;
    while (*s && *s != ')') {
        char *end;
        long v = strtol(s, &end, 10);
        if (end == s) break;
        if (*ndim == 4) fail(BUNDLE, "%s: more than 4 dimensions", path);
        dims[(*ndim)++] = v;
        total *= v;
        s = end;
        while (*s == ',' || *s == ' ') ++s;
    }
    if (n - start != 4 * (size_t)total) fail(BUNDLE, "%s: %zu data bytes for %ld values", path, n - start, total);
    void *data = xmalloc(4 * (size_t)total);
    memcpy(data, buf + start, 4 * (size_t)total);
    xfree(hdr);
    xfree(buf);
    xfree(path);
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
    report("golden %-28s %s  worst error %.3g of its tolerance (max |error| %.3g, values up to "
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
    xfree(data);
    return m;
}

/* One kernel's golden folder ROOT/<name>: its manifest read into h->mf, h->dir set. */
static char *golden_open(clvol_host *h, const char *root, const char *name) {
    char *mp;
    h->dir = keep(path_join(root, name));   /* host_release frees it if a check fails */
    mp = path_join(h->dir, "manifest.txt");
    manifest_read(&h->mf, mp);
    xfree(mp);
    return h->dir;
}

static void golden_close(clvol_host *h) {
    manifest_free(&h->mf);
    free(h->dir);
    h->dir = NULL;
}

/* Golden vectors of `clvol goldens DIR` for the MLP and the gather (DIR/<kernel>/manifest.txt
 * lists the programs and tolerances, the .npy files the arguments). */
static int run_goldens(clvol_host *h, const char *root) {
    int failures = 0;

    /* MLP: grey (1 channel, y) and chromatic (3 channels, decoded F) */
    {
        char *dir = golden_open(h, root, "mlp");
        long n, ny, nF, na;
        float *want_y = npy(dir, "y.npy", &ny);
        float *want_F = npy(dir, "F.npy", &nF);
        float *alb = npy(dir, "channel_albedo.npy", &na);
        int N = (int)ny, qpi = h->lanes;   /* queries per work-item: one a lane */
        cl_mem df = npy_buffer(h, "features.npy", &n), dc = npy_buffer(h, "config.npy", &n),
               dp = npy_buffer(h, "params.npy", &n), dy = buffer(h, 4 * (size_t)N, NULL),
               dF = buffer(h, 12 * (size_t)N, NULL);
        const char *names[2] = {"mlp_y", "mlp_F"};
        for (int v = 0; v < 2; ++v) {
            /* build each variant as its own program (program.mlp_y / program.mlp_F) */
            h->prog[P_MLP] = build_program_at(h, h->dir, &h->mf, names[v]);
            /* held by h, so host_release frees it if the check stops half-way */
            cl_kernel k = h->k_mlp = kernel(h, P_MLP, "mlp_forward");
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
            xfree(got);
            h->k_mlp = NULL;
            CL(clReleaseKernel(k));
            CL(clReleaseProgram(h->prog[P_MLP]));
            h->prog[P_MLP] = NULL;
        }
        xfree(want_y); xfree(want_F); xfree(alb);
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
        h->prog[P_GATHER] = build_program_at(h, h->dir, &h->mf, "gather");
        cl_kernel k = h->k_gather = kernel(h, P_GATHER, "gather");
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
        xfree(got); xfree(got_te); xfree(want); xfree(want_te);
        h->k_gather = NULL;
        CL(clReleaseKernel(k));
        golden_close(h);
    }
    return failures;
}


clvol_status clvol_check_goldens(const char *golden_dir, cl_device_id device, char *report_out,
                                 size_t size, int *failures) {
    char msg[1024];
    guard g;
    clvol_host *volatile h = NULL;
    guard_init(&g, msg, sizeof msg);
    if (setjmp(g.jump)) {
        clvol_status st = guard_end(&g);
        host_release(h);   /* also the golden folder's manifest, if a check stopped half-way */
        if (report_out && size) snprintf(report_out + report_len, size - report_len, "error: %s\n", msg);
        return st;
    }
    if (!golden_dir || !report_out || !failures || size == 0)
        fail(CLVOL_ERROR_ARGUMENT, "clvol_check_goldens: a NULL argument or an empty report buffer");
    report_buf = report_out;
    report_size = size;
    report_len = 0;
    report_out[0] = 0;
    h = calloc(1, sizeof *h);
    if (!h) fail(CLVOL_ERROR_MEMORY, "out of host memory");
    h->device = device;
    open_device(h);
    describe_device(h);
    *failures = run_goldens(h, golden_dir);
    host_release(h);
    h = NULL;
    return guard_end(&g);
}
