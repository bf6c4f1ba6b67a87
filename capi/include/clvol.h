/* libclvol: render a clvol bundle (``clvol bundle SCENE.toml DIR``) from C or C++.
 *
 * A renderer holds one bundle's programs and device state and recomputes only what a change
 * invalidates (as clvol.Renderer does). Ownership, threading, what each setter recomputes and
 * the ABI: docs/embedding.md. Every function returns a status; none exits or prints.
 *
 * Threading: one renderer is used by one thread at a time; different renderers may be used
 * from different threads at once. clvol_last_error(NULL) is per thread.
 */
#ifndef CLVOL_H
#define CLVOL_H

#ifndef CL_TARGET_OPENCL_VERSION
#define CL_TARGET_OPENCL_VERSION 120
#endif
#include <CL/cl.h>
#include <stddef.h>

#ifdef __cplusplus
extern "C" {
#endif

/* The library is built with -fvisibility=hidden: only these names are exported. */
#if defined(CLVOL_BUILDING) && defined(__GNUC__)
#define CLVOL_API __attribute__((visibility("default")))
#else
#define CLVOL_API
#endif

/* Bumped whenever a signature, a struct or an enum value below changes meaning. */
#define CLVOL_ABI_VERSION 1

typedef struct clvol_renderer clvol_renderer;

typedef enum {
    CLVOL_OK = 0,
    CLVOL_ERROR_ARGUMENT,     /* a NULL pointer, a size < 1, a non-finite or out-of-range value */
    CLVOL_ERROR_BUNDLE,       /* the bundle is missing, incomplete or damaged */
    CLVOL_ERROR_OPENCL,       /* an OpenCL call failed (the renderer can only be destroyed) */
    CLVOL_ERROR_MEMORY,       /* out of host memory (the renderer can only be destroyed) */
    CLVOL_ERROR_UNSUPPORTED   /* the change needs programs or data the bundle does not hold */
} clvol_status;

/* Open a bundle. context, device and queue may all be NULL: the library picks a device (the
 * first GPU, else the first CPU) and owns the context and queue. A device alone: the library
 * makes (and owns) a context and queue on it. A context and an in-order queue (device NULL or
 * the queue's): the library renders on them and never releases them. */
CLVOL_API clvol_status clvol_create(const char *bundle_dir, cl_context context,
                                    cl_device_id device, cl_command_queue queue,
                                    clvol_renderer **out);

/* The largest image side, as clvol's scene files and Renderer.render take it
 * (clvol.scenemodel.MAX_IMAGE_SIZE; tests/test_capi.py holds the two equal). */
#define CLVOL_MAX_IMAGE_SIZE 16384

/* The volume's rules, as clvol's scene files and Renderer.render apply them (tests/test_capi.py
 * holds them equal to Python's): each side of the bundle's box at least CLVOL_MIN_RELATIVE_SIDE
 * of the box's scale (its longest side or its farthest coordinate from the origin;
 * clvol.volume.grid.MIN_RELATIVE_SIDE), else float32 cannot resolve it (clvol_create refuses
 * such a bundle); density_scale x the largest density x the box's diagonal below
 * CLVOL_MAX_OPTICAL_DEPTH (clvol.kernels.transmittance.MAX_OPTICAL_DEPTH), else optical depths
 * leave float32's range (clvol_set_medium and clvol_set_density refuse it, clvol_create
 * refuses such a bundle). */
#define CLVOL_MIN_RELATIVE_SIDE 1e-5
#define CLVOL_MAX_OPTICAL_DEPTH 1e37

/* Pinhole camera: origin, target and up finite, target != origin, up not parallel to
 * target - origin (sine of the angle >= 1e-6, as a scene file's [camera]); fov_y_degrees in
 * (0, 180); width and height in [1, CLVOL_MAX_IMAGE_SIZE]. */
CLVOL_API clvol_status clvol_set_camera(clvol_renderer *r, const float origin[3],
                                        const float target[3], const float up[3],
                                        float fov_y_degrees, int width, int height);
/* to_light: toward the light (any non-zero length); irradiance: RGB, >= 0. */
CLVOL_API clvol_status clvol_set_light(clvol_renderer *r, const float to_light[3],
                                       const float irradiance[3]);
/* albedo: RGB in [0, 1]; density_scale finite and >= 0 (sigma_t = density x density_scale;
 * 0, an empty medium, is in range as in a scene file), and density_scale x the largest density
 * x the box's diagonal < CLVOL_MAX_OPTICAL_DEPTH. */
CLVOL_API clvol_status clvol_set_medium(clvol_renderer *r, const float albedo[3],
                                        float density_scale);
/* density[z][y][x], float32, finite and >= 0; the volume keeps its bounding box; the largest
 * density x density_scale x the box's diagonal < CLVOL_MAX_OPTICAL_DEPTH */
CLVOL_API clvol_status clvol_set_density(clvol_renderer *r, const float *density, int nx,
                                         int ny, int nz);

/* rgba: width*height*4 floats, linear radiance, rows top to bottom, alpha = 1 - transmittance */
CLVOL_API clvol_status clvol_render(clvol_renderer *r, float *rgba);
/* The same into a buffer of the renderer's context (at least width*height*4 floats), no host
 * copy. The work is enqueued on the renderer's queue and has finished when this returns. */
CLVOL_API clvol_status clvol_render_to_buffer(clvol_renderer *r, cl_mem rgba);

/* One line naming what was wrong in r's last call ("" if it succeeded). NULL: the last failed
 * clvol_create of this thread (and of calls given r = NULL). The text lives until the next
 * call on r (for NULL: the next such failure on this thread). */
CLVOL_API const char *clvol_last_error(const clvol_renderer *r);

CLVOL_API void clvol_destroy(clvol_renderer *r);   /* NULL is allowed */

CLVOL_API int clvol_abi_version(void);   /* CLVOL_ABI_VERSION of the library that is linked */

/* ---------------------------------------------------------------- additions */

/* The current image size. */
CLVOL_API clvol_status clvol_get_size(const clvol_renderer *r, int *width, int *height);

/* How often a stage has been computed since clvol_create (tests and profiling). */
typedef enum {
    CLVOL_STAGE_VOLUME = 0,   /* density upload, majorant, resampled cubes, pyramid */
    CLVOL_STAGE_LIGHT,        /* light field, graded transmittance, bake */
    CLVOL_STAGE_LATTICE,      /* F_ms at the lattice points (gather + network); for a
                                 stochastic-view bundle the view table's draws */
    CLVOL_STAGE_MARCH,        /* the ray march (every render) */
    CLVOL_STAGE_COUNT
} clvol_stage;
CLVOL_API long clvol_stage_count(const clvol_renderer *r, clvol_stage stage);

/* The device that spec names: "gpu", "cpu" or "P:D" (platform P, device D); NULL: the
 * first GPU, else the first CPU, Mesa's Clover last (what clvol_create picks). */
CLVOL_API clvol_status clvol_pick_device(const char *spec, cl_device_id *out);

/* Check the MLP and gather kernels against ``clvol goldens DIR`` on `device` (NULL: the first
 * GPU, else the first CPU). One line per output is written into report (NUL-terminated,
 * truncated to report_size); *failures: outputs outside their tolerance. */
CLVOL_API clvol_status clvol_check_goldens(const char *golden_dir, cl_device_id device,
                                           char *report, size_t report_size, int *failures);

/* Driver workarounds: the -D options the library adds to every program it builds on an OpenCL
 * platform of this CL_PLATFORM_NAME ("-DMLP_DENSE_ARRAY=1 ..." on Mesa's rusticl, "" on any
 * other and for NULL), and the lane width it builds them with there (4 on rusticl; 0: the
 * device's rule, docs/embedding.md). The rules of clvol/runtime.py DRIVER_RULES, which
 * tests/test_capi.py holds these to; docs/opencl.md, "rusticl", says why. */
CLVOL_API const char *clvol_driver_defines(const char *platform_name);
CLVOL_API int clvol_driver_lanes(const char *platform_name);
/* 1 if the default device choice (no spec) takes this platform's devices after any other
 * platform's of the same type (Mesa's Clover), else 0; clvol/runtime.py DEFAULT_LAST. */
CLVOL_API int clvol_default_last(const char *platform_name);

#ifdef __cplusplus
}
#endif
#endif
