/* clvol-render: render a clvol bundle (``clvol bundle SCENE.toml DIR``) with libclvol, the C
 * library in capi/ (API: capi/include/clvol.h; walk-through: docs/embedding.md).
 *
 *   clvol-render BUNDLE OUT.pfm [--frames N] [--device gpu|cpu|P:D] [--external-context]
 *   clvol-render --golden GOLDEN_DIR [--device ...]  (check the MLP and the gather kernels)
 *
 * OUT.pfm holds the total radiance (little-endian PFM, rows bottom to top as PFM wants);
 * ``clvol compare OUT.pfm REF.exr`` reads it. --external-context makes a context and queue here
 * and hands them to the library, as an engine that holds its own OpenCL objects would.
 * A failure prints the library's message and exits with status 1.
 */
#define _POSIX_C_SOURCE 200809L
#include "clvol.h"

#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

static double now_seconds(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

static int cmp_double(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static int error(const char *what) {
    fprintf(stderr, "clvol-render: error: %s\n", what);
    return 1;
}

/* The RGB of an RGBA image as PFM. */
static int write_pfm(const char *path, const float *rgba, int w, int h) {
    FILE *f = fopen(path, "wb");
    if (!f) {
        fprintf(stderr, "clvol-render: error: %s: cannot write (%s)\n", path, strerror(errno));
        return 1;
    }
    fprintf(f, "PF\n%d %d\n-1.0\n", w, h);   /* -1: little-endian; rows bottom to top */
    int ok = 1;
    for (int y = h - 1; y >= 0 && ok; --y)
        for (int x = 0; x < w && ok; ++x)
            ok = fwrite(rgba + ((size_t)y * w + x) * 4, sizeof(float), 3, f) == 3;
    if (fclose(f) != 0 || !ok) {
        fprintf(stderr, "clvol-render: error: %s: short write\n", path);
        return 1;
    }
    return 0;
}

int main(int argc, char **argv) {
    const char *device_spec = NULL, *golden = NULL, *paths[2] = {NULL, NULL};
    int frames = 1, np = 0, external = 0;
    for (int i = 1; i < argc; ++i) {
        if (strcmp(argv[i], "--frames") == 0 && i + 1 < argc) {
            char *end;
            long v = strtol(argv[++i], &end, 10);
            if (*end || v < 1 || v > 1000) return error("--frames: an integer from 1 to 1000");
            frames = (int)v;
        } else if (strcmp(argv[i], "--device") == 0 && i + 1 < argc) {
            device_spec = argv[++i];
        } else if (strcmp(argv[i], "--external-context") == 0) {
            external = 1;
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
    cl_device_id device = NULL;
    if (device_spec && clvol_pick_device(device_spec, &device) != CLVOL_OK)
        return error(clvol_last_error(NULL));
    if (golden) {
        static char report[8192];
        int bad = 0;
        clvol_status st = clvol_check_goldens(golden, device, report, sizeof report, &bad);
        fputs(report, stdout);
        if (st != CLVOL_OK) return 1;
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
        cl_int err;
        if (!device && clvol_pick_device(NULL, &device) != CLVOL_OK)
            return error(clvol_last_error(NULL));
        ctx = clCreateContext(NULL, 1, &device, NULL, NULL, &err);
        if (err != CL_SUCCESS) return error("clCreateContext failed");
        queue = clCreateCommandQueue(ctx, device, 0, &err);
        if (err != CL_SUCCESS) {
            clReleaseContext(ctx);
            return error("clCreateCommandQueue failed");
        }
    }
    clvol_renderer *r = NULL;
    int status = 0;
    if (clvol_create(paths[0], ctx, device, queue, &r) != CLVOL_OK) {
        status = error(clvol_last_error(NULL));
    } else {
        double t_create = now_seconds() - t0;
        int w, h;
        clvol_get_size(r, &w, &h);
        float *rgba = malloc(16 * (size_t)w * h);
        double *ft = malloc(sizeof(double) * (size_t)frames);
        if (!rgba || !ft) {
            status = error("out of host memory");
        } else {
            for (int f = 0; f < frames && !status; ++f) {
                double s = now_seconds();
                if (clvol_render(r, rgba) != CLVOL_OK) status = error(clvol_last_error(r));
                ft[f] = now_seconds() - s;
            }
        }
        if (!status) status = write_pfm(paths[1], rgba, w, h);
        if (!status) {
            qsort(ft, (size_t)frames, sizeof(double), cmp_double);
            fprintf(stderr, "clvol-render: %dx%d, create (build + volume + light) %.3f s, "
                            "frame median %.4f s over %d, total %.3f s\n",
                    w, h, t_create, ft[frames / 2], frames, now_seconds() - t0);
        }
        free(ft);
        free(rgba);
        clvol_destroy(r);
    }
    if (external) {   /* the caller's objects outlive the renderer */
        clReleaseCommandQueue(queue);
        clReleaseContext(ctx);
    }
    return status;
}
