/* The C test program of libclvol (tests/test_capi.py builds and runs it, also under
 * AddressSanitizer + UBSan: `make -C capi test-program asan`).
 *
 *   test_capi script BUNDLE SCRIPT    run the calls a script file lists (one a line):
 *        camera ox oy oz tx ty tz ux uy uz fov_y width height
 *        light dx dy dz ex ey ez
 *        medium ar ag ab density_scale
 *        density FILE nx ny nz              (raw float32 [nz][ny][nx])
 *        render OUT                         (clvol_render: raw float32 [h][w][4])
 *        render_buffer OUT                  (clvol_render_to_buffer into a buffer made here)
 *        expect STATUS                      (the status the next call must return)
 *     each call's status and message are printed; exit 1 at the first unexpected status.
 *     --external: the renderer runs on a context and queue made here (checked alive after).
 *   test_capi serve
 *     the fuzz driver of tests/test_capi.py: reads calls from stdin, one a line, and answers
 *     each with one line "NAME STATUS EXTRA MESSAGE" (a newline in the message is written as
 *     '|' and EXTRA is then -1), flushed:
 *        open BUNDLE                        (clvol_destroy, then clvol_create; EXTRA 0)
 *        camera X*10 width height           (X: a float32's bits in hex: origin, target, up,
 *        light X*6                           fov_y; every NaN, infinity and size reaches
 *        medium X*4                          the library as given; EXTRA 0)
 *        density nx ny nz FILE              (FILE: nx*ny*nz raw float32; sizes that are not
 *                                            all >= 1 with a product <= 2^24 pass a buffer of
 *                                            one float: the library must refuse them before
 *                                            reading it; ASan sees a read past it)
 *        density_null nx ny nz              (a NULL density)
 *        render                             (clvol_render, at most 4096 pixels, else EXTRA
 *                                            -2 and no render; EXTRA: non-finite values)
 *     exit 0 at the end of the input.
 *   test_capi checks BUNDLE DAMAGED_BUNDLE
 *     bad arguments, the caller's context and queue, render_to_buffer = render, two
 *     renderers in two threads = one at a time. Prints "ok NAME" or "FAIL NAME: why" per
 *     check; exit 0 only if all pass.
 */
#include "clvol.h"

#include <math.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int failures = 0;

static void check(int ok, const char *name, const char *why) {
    if (ok) printf("ok %s\n", name);
    else printf("FAIL %s: %s\n", name, why);
    failures += !ok;
}

/* A call that must fail with `want` and say why (a non-empty message). */
static void expect_status(clvol_status got, clvol_status want, const char *msg, const char *name) {
    char why[600];
    snprintf(why, sizeof why, "status %d (want %d), message '%s'", (int)got, (int)want,
             msg ? msg : "(null)");
    check(got == want && msg && msg[0], name, why);
    if (msg) printf("   message: %s\n", msg);
}

static float *render_image(clvol_renderer *r, int *w, int *h) {
    clvol_get_size(r, w, h);
    float *img = malloc(16 * (size_t)*w * *h);
    if (img && clvol_render(r, img) != CLVOL_OK) {
        printf("   render failed: %s\n", clvol_last_error(r));
        free(img);
        return NULL;
    }
    return img;
}

static int write_raw(const char *path, const float *data, size_t count) {
    FILE *f = fopen(path, "wb");
    if (!f) return 0;
    size_t n = fwrite(data, sizeof(float), count, f);
    return fclose(f) == 0 && n == count;
}

static cl_mem make_buffer(clvol_renderer *r, cl_context ctx, size_t bytes) {
    (void)r;
    cl_int err;
    cl_mem m = clCreateBuffer(ctx, CL_MEM_READ_WRITE, bytes, NULL, &err);
    return err == CL_SUCCESS ? m : NULL;
}

/* ------------------------------------------------------------------------ script */

static int run_script(const char *bundle, const char *script, int external) {
    cl_device_id dev = NULL;
    cl_context ctx = NULL;
    cl_command_queue queue = NULL;
    cl_int err;
    if (external) {
        if (clvol_pick_device(NULL, &dev) != CLVOL_OK) return 1;
        ctx = clCreateContext(NULL, 1, &dev, NULL, NULL, &err);
        queue = clCreateCommandQueue(ctx, dev, 0, &err);
    }
    clvol_renderer *r = NULL;
    clvol_status st = clvol_create(bundle, ctx, NULL, queue, &r);
    printf("create %d %s\n", (int)st, clvol_last_error(NULL));
    if (st != CLVOL_OK) return 1;
    FILE *f = fopen(script, "r");
    if (!f) return 1;
    char line[1024];
    int expect = CLVOL_OK, bad = 0;
    while (!bad && fgets(line, sizeof line, f)) {
        char cmd[32], path[700];
        float v[12];
        int n[3];
        if (sscanf(line, "%31s", cmd) != 1) continue;
        if (strcmp(cmd, "expect") == 0) {
            sscanf(line, "%*s %d", &expect);
            continue;
        }
        if (strcmp(cmd, "camera") == 0 && sscanf(line, "%*s %f %f %f %f %f %f %f %f %f %f %d %d",
                                                 &v[0], &v[1], &v[2], &v[3], &v[4], &v[5], &v[6],
                                                 &v[7], &v[8], &v[9], &n[0], &n[1]) == 12) {
            st = clvol_set_camera(r, v, v + 3, v + 6, v[9], n[0], n[1]);
        } else if (strcmp(cmd, "light") == 0 && sscanf(line, "%*s %f %f %f %f %f %f", &v[0], &v[1],
                                                        &v[2], &v[3], &v[4], &v[5]) == 6) {
            st = clvol_set_light(r, v, v + 3);
        } else if (strcmp(cmd, "medium") == 0 && sscanf(line, "%*s %f %f %f %f", &v[0], &v[1], &v[2],
                                                         &v[3]) == 4) {
            st = clvol_set_medium(r, v, v[3]);
        } else if (strcmp(cmd, "density") == 0 && sscanf(line, "%*s %699s %d %d %d", path, &n[0],
                                                          &n[1], &n[2]) == 4) {
            size_t count = (size_t)n[0] * n[1] * n[2];
            float *d = malloc(4 * count);
            FILE *df = fopen(path, "rb");
            if (!d || !df || fread(d, 4, count, df) != count || fgetc(df) != EOF) {
                printf("cannot read %s: %zu float32 expected\n", path, count);
                if (df) fclose(df);
                free(d);
                bad = 1;
                break;
            } else {
                st = clvol_set_density(r, d, n[0], n[1], n[2]);
            }
            if (df) fclose(df);
            free(d);
        } else if ((strcmp(cmd, "render") == 0 || strcmp(cmd, "render_buffer") == 0)
                   && sscanf(line, "%*s %699s", path) == 1) {
            int w, h;
            clvol_get_size(r, &w, &h);
            size_t count = 4 * (size_t)w * h;
            float *img = malloc(4 * count);
            if (strcmp(cmd, "render") == 0) {
                st = clvol_render(r, img);
            } else {
                /* the caller's buffer in the renderer's context (the external one if given) */
                cl_context rc = ctx;
                cl_mem m = NULL;
                if (!rc) {   /* the library's own context: made from its device here */
                    cl_device_id d2;
                    clvol_pick_device(NULL, &d2);
                    rc = clCreateContext(NULL, 1, &d2, NULL, NULL, &err);
                    m = make_buffer(r, rc, 4 * count);
                    st = clvol_render_to_buffer(r, m);   /* another context: refused */
                    printf("render_buffer (foreign context) %d %s\n", (int)st, clvol_last_error(r));
                    if (st != CLVOL_ERROR_ARGUMENT) bad = 1;
                    clReleaseMemObject(m);
                    clReleaseContext(rc);
                    st = clvol_render(r, img);
                } else {
                    m = make_buffer(r, rc, 4 * count);
                    st = clvol_render_to_buffer(r, m);
                    if (st == CLVOL_OK)
                        clEnqueueReadBuffer(queue, m, CL_TRUE, 0, 4 * count, img, 0, NULL, NULL);
                    clReleaseMemObject(m);
                }
            }
            if (st == CLVOL_OK && !write_raw(path, img, count)) bad = 1;
            free(img);
        } else {
            printf("bad script line: %s", line);
            bad = 1;
            break;
        }
        printf("%s %d %s\n", cmd, (int)st, clvol_last_error(r));
        if ((int)st != expect) {
            printf("unexpected status %d (expected %d)\n", (int)st, expect);
            bad = 1;
        }
        expect = CLVOL_OK;
    }
    fclose(f);
    clvol_destroy(r);
    if (external) {
        /* the caller's objects outlive the renderer: still usable */
        cl_uint refs = 0;
        cl_int e1 = clGetContextInfo(ctx, CL_CONTEXT_REFERENCE_COUNT, sizeof refs, &refs, NULL);
        cl_mem m = clCreateBuffer(ctx, CL_MEM_READ_WRITE, 64, NULL, &err);
        float z = 1.0f, back[16];
        cl_int e2 = clEnqueueFillBuffer(queue, m, &z, sizeof z, 0, 64, 0, NULL, NULL);
        cl_int e3 = clEnqueueReadBuffer(queue, m, CL_TRUE, 0, 64, back, 0, NULL, NULL);
        printf("external context alive: %s (reference count %u)\n",
               e1 == CL_SUCCESS && e2 == CL_SUCCESS && e3 == CL_SUCCESS && back[15] == 1.0f
                   ? "yes" : "no", refs);
        clReleaseMemObject(m);
        clReleaseCommandQueue(queue);
        clReleaseContext(ctx);
    }
    return bad;
}

/* ------------------------------------------------------------------------ serve */

static float hex_float(const char *tok) {
    unsigned long bits = strtoul(tok, NULL, 16);
    unsigned int b32 = (unsigned int)bits;
    float f;
    memcpy(&f, &b32, sizeof f);
    return f;
}

static void answer(const char *name, clvol_status st, long extra, const char *msg) {
    char line[2048];
    snprintf(line, sizeof line, "%s", msg ? msg : "(null)");
    for (char *p = line; *p; ++p)
        if (*p == '\n' || *p == '\r') *p = '|', extra = -1;
    printf("%s %d %ld %s\n", name, (int)st, extra, line);
    fflush(stdout);
}

static int run_serve(void) {
    clvol_renderer *r = NULL;
    char line[4096];
    while (fgets(line, sizeof line, stdin)) {
        char *tok[16];
        int n = 0;
        for (char *p = strtok(line, " \t\n"); p && n < 16; p = strtok(NULL, " \t\n")) tok[n++] = p;
        if (n == 0) continue;
        const char *cmd = tok[0];
        float v[12];
        clvol_status st;
        if (strcmp(cmd, "open") == 0 && n == 2) {
            clvol_destroy(r);
            r = NULL;
            st = clvol_create(tok[1], NULL, NULL, NULL, &r);
            answer(cmd, st, 0, st == CLVOL_OK ? "" : clvol_last_error(NULL));
            continue;
        }
        if (!r) {
            answer(cmd, CLVOL_ERROR_ARGUMENT, 0, "serve: no renderer open");
            continue;
        }
        if (strcmp(cmd, "camera") == 0 && n == 13) {
            for (int i = 0; i < 10; ++i) v[i] = hex_float(tok[1 + i]);
            st = clvol_set_camera(r, v, v + 3, v + 6, v[9], atoi(tok[11]), atoi(tok[12]));
            answer(cmd, st, 0, clvol_last_error(r));
        } else if (strcmp(cmd, "light") == 0 && n == 7) {
            for (int i = 0; i < 6; ++i) v[i] = hex_float(tok[1 + i]);
            st = clvol_set_light(r, v, v + 3);
            answer(cmd, st, 0, clvol_last_error(r));
        } else if (strcmp(cmd, "medium") == 0 && n == 5) {
            for (int i = 0; i < 4; ++i) v[i] = hex_float(tok[1 + i]);
            st = clvol_set_medium(r, v, v[3]);
            answer(cmd, st, 0, clvol_last_error(r));
        } else if (strcmp(cmd, "density_null") == 0 && n == 4) {
            st = clvol_set_density(r, NULL, atoi(tok[1]), atoi(tok[2]), atoi(tok[3]));
            answer(cmd, st, 0, clvol_last_error(r));
        } else if (strcmp(cmd, "density") == 0 && n == 5) {
            int nx = atoi(tok[1]), ny = atoi(tok[2]), nz = atoi(tok[3]);
            int small = nx >= 1 && ny >= 1 && nz >= 1 && (double)nx * ny * nz <= 16777216.0;
            size_t count = small ? (size_t)nx * ny * nz : 1;
            float *d = malloc(4 * count);
            FILE *f = small ? fopen(tok[4], "rb") : NULL;
            if (!d || (small && (!f || fread(d, 4, count, f) != count))) {
                printf("cannot read %s: %zu float32 expected\n", tok[4], count);
                if (f) fclose(f);
                free(d);
                clvol_destroy(r);
                return 1;
            }
            if (f) fclose(f);
            if (!small) d[0] = 1.0f;
            st = clvol_set_density(r, d, nx, ny, nz);
            free(d);
            answer(cmd, st, 0, clvol_last_error(r));
        } else if (strcmp(cmd, "render") == 0 && n == 1) {
            int w = 0, h = 0;
            clvol_get_size(r, &w, &h);
            if ((long)w * h > 4096) {
                answer(cmd, CLVOL_OK, -2, "not rendered: more than 4096 pixels");
                continue;
            }
            size_t count = 4 * (size_t)w * h;
            float *img = malloc(4 * count);
            st = clvol_render(r, img);
            long bad = 0;
            if (st == CLVOL_OK)
                for (size_t i = 0; i < count; ++i) bad += !isfinite(img[i]);
            free(img);
            answer(cmd, st, bad, clvol_last_error(r));
        } else {
            printf("bad line: %s\n", cmd);
            clvol_destroy(r);
            return 1;
        }
    }
    clvol_destroy(r);
    return 0;
}

/* ------------------------------------------------------------------------ checks */

typedef struct {
    const char *bundle;
    float origin[3];
    float *image;
    int w, h;
} job;

/* One renderer's sequence: create, move the camera, render. */
static void *run_job(void *arg) {
    job *j = arg;
    clvol_renderer *r = NULL;
    if (clvol_create(j->bundle, NULL, NULL, NULL, &r) != CLVOL_OK) return NULL;
    const float target[3] = {0, 0, 0}, up[3] = {0, 1, 0};
    if (clvol_set_camera(r, j->origin, target, up, 35.0f, 24, 16) == CLVOL_OK)
        j->image = render_image(r, &j->w, &j->h);
    clvol_destroy(r);
    return NULL;
}

static int same_image(const job *a, const job *b) {
    return a->image && b->image && a->w == b->w && a->h == b->h
           && memcmp(a->image, b->image, 16 * (size_t)a->w * a->h) == 0;
}

static void run_checks(const char *bundle, const char *damaged) {
    clvol_renderer *r = NULL;
    const float v3[3] = {0.5f, 0.5f, 0.5f}, zero3[3] = {0, 0, 0}, up[3] = {0, 1, 0};
    const float far3[3] = {0.3f, 0.4f, 2.5f};

    check(clvol_abi_version() == CLVOL_ABI_VERSION, "abi_version", "library and header differ");

    /* clvol_create: bad arguments, a missing and a damaged bundle */
    expect_status(clvol_create(bundle, NULL, NULL, NULL, NULL), CLVOL_ERROR_ARGUMENT,
                  clvol_last_error(NULL), "create out NULL");
    expect_status(clvol_create(NULL, NULL, NULL, NULL, &r), CLVOL_ERROR_ARGUMENT,
                  clvol_last_error(NULL), "create bundle_dir NULL");
    check(r == NULL, "create failure leaves *out NULL", "out was set");
    expect_status(clvol_create("/nonexistent/bundle", NULL, NULL, NULL, &r), CLVOL_ERROR_BUNDLE,
                  clvol_last_error(NULL), "create missing bundle");
    check(strstr(clvol_last_error(NULL), "/nonexistent/bundle/manifest.txt") != NULL,
          "missing bundle named", clvol_last_error(NULL));
    expect_status(clvol_create(damaged, NULL, NULL, NULL, &r), CLVOL_ERROR_BUNDLE,
                  clvol_last_error(NULL), "create damaged bundle");
    cl_device_id dev = NULL;
    cl_int err;
    clvol_pick_device(NULL, &dev);
    cl_context ctx = clCreateContext(NULL, 1, &dev, NULL, NULL, &err);
    cl_command_queue queue = clCreateCommandQueue(ctx, dev, 0, &err);
    expect_status(clvol_create(bundle, ctx, NULL, NULL, &r), CLVOL_ERROR_ARGUMENT,
                  clvol_last_error(NULL), "create context without queue");
    expect_status(clvol_pick_device("7:7", &dev), CLVOL_ERROR_ARGUMENT, clvol_last_error(NULL),
                  "pick_device no such device");

    /* a renderer on the caller's context and queue */
    clvol_status st = clvol_create(bundle, ctx, dev, queue, &r);
    check(st == CLVOL_OK, "create on the caller's context", clvol_last_error(NULL));
    if (st != CLVOL_OK) return;

    /* every setter: NULL pointers, zero or negative sizes, non-finite values */
    expect_status(clvol_set_camera(NULL, far3, zero3, up, 40, 8, 8), CLVOL_ERROR_ARGUMENT,
                  clvol_last_error(NULL), "set_camera renderer NULL");
    expect_status(clvol_set_camera(r, NULL, zero3, up, 40, 8, 8), CLVOL_ERROR_ARGUMENT,
                  clvol_last_error(r), "set_camera origin NULL");
    expect_status(clvol_set_camera(r, far3, zero3, up, 40, 0, 8), CLVOL_ERROR_ARGUMENT,
                  clvol_last_error(r), "set_camera width 0");
    expect_status(clvol_set_camera(r, far3, zero3, up, 40, 8, -3), CLVOL_ERROR_ARGUMENT,
                  clvol_last_error(r), "set_camera height negative");
    expect_status(clvol_set_camera(r, far3, zero3, up, 0, 8, 8), CLVOL_ERROR_ARGUMENT,
                  clvol_last_error(r), "set_camera fov 0");
    expect_status(clvol_set_camera(r, far3, far3, up, 40, 8, 8), CLVOL_ERROR_ARGUMENT,
                  clvol_last_error(r), "set_camera origin = target");
    expect_status(clvol_set_light(r, zero3, v3), CLVOL_ERROR_ARGUMENT, clvol_last_error(r),
                  "set_light zero direction");
    expect_status(clvol_set_light(r, v3, NULL), CLVOL_ERROR_ARGUMENT, clvol_last_error(r),
                  "set_light irradiance NULL");
    const float nan3[3] = {NAN, 0.5f, 0.5f};
    expect_status(clvol_set_medium(r, nan3, 1.0f), CLVOL_ERROR_ARGUMENT, clvol_last_error(r),
                  "set_medium albedo NaN");
    expect_status(clvol_set_medium(r, v3, -1.0f), CLVOL_ERROR_ARGUMENT, clvol_last_error(r),
                  "set_medium negative density scale");
    float dens[4 * 3 * 2];
    for (int i = 0; i < 24; ++i) dens[i] = 1.0f;
    expect_status(clvol_set_density(r, NULL, 4, 3, 2), CLVOL_ERROR_ARGUMENT, clvol_last_error(r),
                  "set_density NULL");
    expect_status(clvol_set_density(r, dens, 0, 3, 2), CLVOL_ERROR_ARGUMENT, clvol_last_error(r),
                  "set_density nx 0");
    expect_status(clvol_set_density(r, dens, 4, -3, 2), CLVOL_ERROR_ARGUMENT, clvol_last_error(r),
                  "set_density ny negative");
    dens[17] = NAN;
    expect_status(clvol_set_density(r, dens, 4, 3, 2), CLVOL_ERROR_ARGUMENT, clvol_last_error(r),
                  "set_density NaN");
    check(strstr(clvol_last_error(r), "density[17]") != NULL, "NaN voxel named", clvol_last_error(r));
    expect_status(clvol_render(r, NULL), CLVOL_ERROR_ARGUMENT, clvol_last_error(r), "render NULL");
    expect_status(clvol_render_to_buffer(r, NULL), CLVOL_ERROR_ARGUMENT, clvol_last_error(r),
                  "render_to_buffer NULL");
    cl_mem small = clCreateBuffer(ctx, CL_MEM_READ_WRITE, 16, NULL, &err);
    expect_status(clvol_render_to_buffer(r, small), CLVOL_ERROR_ARGUMENT, clvol_last_error(r),
                  "render_to_buffer too small");
    clReleaseMemObject(small);
    /* after all those refusals the renderer still renders, and a later success clears the
     * message */
    check(clvol_set_camera(r, far3, zero3, up, 40, 20, 12) == CLVOL_OK
          && clvol_last_error(r)[0] == 0, "renderer usable after refusals", clvol_last_error(r));

    /* render_to_buffer (no host copy) = render */
    int w, h;
    float *a = render_image(r, &w, &h);
    cl_mem m = clCreateBuffer(ctx, CL_MEM_READ_WRITE, 16 * (size_t)w * h, NULL, &err);
    float *b = malloc(16 * (size_t)w * h);
    st = clvol_render_to_buffer(r, m);
    clEnqueueReadBuffer(queue, m, CL_TRUE, 0, 16 * (size_t)w * h, b, 0, NULL, NULL);
    int nonzero = 0;
    for (int i = 0; a && i < 4 * w * h; ++i) nonzero |= a[i] != 0.0f;
    check(st == CLVOL_OK && a && nonzero && memcmp(a, b, 16 * (size_t)w * h) == 0,
          "render_to_buffer equals render", clvol_last_error(r));
    clReleaseMemObject(m);
    free(a);
    free(b);
    clvol_destroy(r);
    clvol_destroy(NULL);   /* allowed */

    /* the caller's context and queue outlive the renderer */
    cl_mem after = clCreateBuffer(ctx, CL_MEM_READ_WRITE, 64, NULL, &err);
    float one = 1.0f, back[16] = {0};
    cl_int e1 = clEnqueueFillBuffer(queue, after, &one, sizeof one, 0, 64, 0, NULL, NULL);
    cl_int e2 = clEnqueueReadBuffer(queue, after, CL_TRUE, 0, 64, back, 0, NULL, NULL);
    check(err == CL_SUCCESS && e1 == CL_SUCCESS && e2 == CL_SUCCESS && back[15] == 1.0f,
          "caller's context and queue alive after destroy", "an OpenCL call on them failed");
    clReleaseMemObject(after);
    clReleaseCommandQueue(queue);
    clReleaseContext(ctx);

    /* two renderers in two threads = the same two, one at a time */
    job seq[2] = {{bundle, {0.3f, 0.4f, 2.5f}, NULL, 0, 0}, {bundle, {-1.5f, 0.8f, 1.9f}, NULL, 0, 0}};
    job par[2] = {seq[0], seq[1]};
    run_job(&seq[0]);
    run_job(&seq[1]);
    pthread_t t[2];
    for (int i = 0; i < 2; ++i) pthread_create(&t[i], NULL, run_job, &par[i]);
    for (int i = 0; i < 2; ++i) pthread_join(t[i], NULL);
    check(seq[0].image && seq[1].image && !same_image(&seq[0], &seq[1]),
          "two camera positions give two images", "a render failed or the images are equal");
    check(same_image(&seq[0], &par[0]) && same_image(&seq[1], &par[1]),
          "two threads give the images of one at a time", "the images differ");
    for (int i = 0; i < 2; ++i) {
        free(seq[i].image);
        free(par[i].image);
    }
    /* clvol_last_error(NULL) is per thread: a failure here leaves another thread's alone */
    clvol_create("/nonexistent/a", NULL, NULL, NULL, &r);
    pthread_t other;
    job dummy = {"/nonexistent/b", {0, 0, 1}, NULL, 0, 0};
    pthread_create(&other, NULL, run_job, &dummy);
    pthread_join(other, NULL);
    check(strstr(clvol_last_error(NULL), "/nonexistent/a") != NULL,
          "last_error(NULL) is per thread", clvol_last_error(NULL));
}

int main(int argc, char **argv) {
    if (argc >= 4 && strcmp(argv[1], "script") == 0)
        return run_script(argv[2], argv[3], argc >= 5 && strcmp(argv[4], "--external") == 0);
    if (argc == 2 && strcmp(argv[1], "serve") == 0) return run_serve();
    if (argc == 4 && strcmp(argv[1], "checks") == 0) {
        run_checks(argv[2], argv[3]);
        printf("%s: %d check(s) failed\n", failures ? "FAILED" : "passed", failures);
        return failures ? 1 : 0;
    }
    fprintf(stderr, "usage: test_capi script BUNDLE SCRIPT [--external] | serve | checks BUNDLE DAMAGED\n");
    return 2;
}
